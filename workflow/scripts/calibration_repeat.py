from surffin.pipeline.run import run_calibration

run_calibration(
    snakemake.params.campaign,
    snakemake.output[0],
    params=snakemake.params.stage_params,
    folders=snakemake.params.folders,
    log_path=snakemake.log[0],
)
