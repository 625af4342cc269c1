rule calibration:
    input:
        views=calibration_views,
    output:
        directory(f"{PROCESSED}/calibration.zarr"),
    log:
        f"{LOGS}/calibration.log",
    benchmark:
        f"{LOGS}/benchmarks/calibration.tsv"
    priority: RESULTS_FIRST
    conda:
        ENV
    threads: 1
    resources:
        mem_mb=1500,
    params:
        campaign=str(CAMPAIGN),
        settings=calibration_settings,
        stage_params=calibration_parameters(config),
        code=STAGE_VERSION["calibration"],
    script:
        "../scripts/calibration.py"
