rule calibration_repeat:
    input:
        views=repeat_calibration_views,
    output:
        directory(f"{PROCESSED}/diagnostics/calibration-repeat.zarr"),
    log:
        f"{LOGS}/diagnostics/calibration-repeat.log",
    priority: DIAGNOSTICS_FIRST
    threads: 1
    resources:
        mem_mb=1500,
    params:
        campaign=str(CAMPAIGN),
        folders=config["calibration_repeat"],
        settings=from_plan("calibration_settings"),
        stage=rules.calibration.params.stage,
        code=STAGES["calibration"].version,
    run:
        in_worker(
            run_calibration,
            params.campaign,
            output[0],
            params=params.stage,
            folders=params.folders,
            log_path=log[0],
        )


rule calibration_diagnostics:
    input:
        calibration=CALIBRATION,
        repeat=repeat_calibration_store,
        views=from_plan("diagnostics_views"),
        stores=from_plan("diagnostics_store_files"),
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
    priority: DIAGNOSTICS_FIRST
    threads: 1
    resources:
        mem_mb=2000,
    params:
        campaign=str(CAMPAIGN),
        repeat_folders=config["calibration_repeat"],
        settings=from_plan("diagnostics_settings"),
        item_params=from_plan("diagnostics_item_parameters"),
        stores=from_plan("diagnostics_stores"),
        code=STAGES["diagnostics"].version,
    run:
        in_worker(
            run_calibration_diagnostics,
            output.json,
            calibration=input.calibration,
            repeat=input.repeat or None,
            campaign=params.campaign,
            repeat_folders=params.repeat_folders,
            item_params=params.item_params,
            specimen_stores=params.stores,
            figures_dir=Path(output.correlation).parent,
            log_path=log[0],
        )
