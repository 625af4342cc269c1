from surffin.pipeline.run import run_calibration

run_calibration(
    snakemake.params.campaign,
    snakemake.output[0],
    params=snakemake.params.stage_params,
    log_path=snakemake.log[0],
)
