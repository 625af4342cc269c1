from surffin.pipeline.run import run_items

chains = snakemake.params.chains
run_items(
    snakemake.params.campaign,
    {name: chain["stores"] for name, chain in chains.items()},
    calibration=snakemake.input.calibration,
    params={name: chain["params"] for name, chain in chains.items()},
    chunks=snakemake.params.chunks,
    scheduler=snakemake.params.scheduler,
    threads=snakemake.threads,
    log_path=snakemake.log[0],
)
