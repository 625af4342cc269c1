rule calibration_repeat:
    input:
        views=repeat_calibration_views,
    output:
        directory(f"{PROCESSED}/diagnostics/calibration-repeat.zarr"),
    log:
        f"{LOGS}/diagnostics/calibration-repeat.log",
    benchmark:
        f"{LOGS}/benchmarks/diagnostics/calibration-repeat.tsv"
    conda:
        ENV
    threads: 1
    resources:
        mem_mb=1500,
    params:
        campaign=str(CAMPAIGN),
        folders=config["calibration_repeat"],
        settings=calibration_settings,
        stage_params=rules.calibration.params.stage_params,
        code=STAGE_VERSION["calibration"],
    script:
        "../scripts/calibration_repeat.py"


rule calibration_diagnostics:
    input:
        calibration=CALIBRATION,
        repeat=repeat_calibration_store,
        views=diagnostics_views,
    output:
        json=f"{PROCESSED}/diagnostics/calibration.json",
        correlation=report(
            f"{PROCESSED}/figures/calibration_correlation.png",
            caption="../report/calibration_correlation.rst",
            category="1. Calibration",
            labels={"figure": "coefficient correlation (Table 2)"},
        ),
        repeatability=report(
            f"{PROCESSED}/figures/calibration_repeatability.png",
            caption="../report/calibration_repeatability.rst",
            category="1. Calibration",
            labels={"figure": "repeatability of two calibration sets"},
        ),
    log:
        f"{LOGS}/diagnostics/calibration.log",
    benchmark:
        f"{LOGS}/benchmarks/diagnostics/calibration.tsv"
    conda:
        ENV
    threads: 1
    resources:
        mem_mb=2000,
    params:
        campaign=str(CAMPAIGN),
        repeat_folders=config["calibration_repeat"],
        settings=diagnostics_settings,
        item_params=diagnostics_item_params,
        code=STAGE_VERSION["diagnostics"],
    script:
        "../scripts/calibration_diagnostics.py"
