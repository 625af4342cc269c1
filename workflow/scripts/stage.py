from surffin.pipeline.run import run_stage

run_stage(
    snakemake.params.stage,
    snakemake.output[0],
    stores=dict(snakemake.input.items()),
    params=snakemake.params.stage_params,
    chunks=snakemake.params.chunks,
    scheduler=snakemake.params.scheduler,
    threads=snakemake.threads,
    log_path=snakemake.log[0],
)
