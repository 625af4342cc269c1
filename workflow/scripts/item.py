from surffin.pipeline import run_item

run_item(
    snakemake.params.campaign,
    snakemake.wildcards.item,
    dict(snakemake.output.items()),
    calibration=snakemake.input.calibration,
    params=snakemake.params.stage_params,
    chunks=snakemake.params.chunks,
    scheduler=snakemake.params.scheduler,
    threads=snakemake.threads,
    log_path=snakemake.log[0],
)
