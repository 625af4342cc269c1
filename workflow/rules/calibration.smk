rule calibration:
    input:
        views=from_plan("calibration_views"),
    output:
        directory(f"{PROCESSED}/calibration.zarr"),
    log:
        f"{LOGS}/calibration.log",
    priority: RESULTS_FIRST
    threads: 1
    resources:
        mem_mb=1500,
    params:
        campaign=str(CAMPAIGN),
        settings=from_plan("calibration_settings"),
        stage=calibration_parameters(config),
        code=STAGES["calibration"].version,
    run:
        in_worker(run_calibration, params.campaign, output[0], params=params.stage, log_path=log[0])
