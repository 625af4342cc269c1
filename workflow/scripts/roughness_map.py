from surffin.pipeline.run import run_roughness_map

run_roughness_map(
    snakemake.output[0],
    features=snakemake.input.features,
    relation=snakemake.input.relation,
    chunks=snakemake.params.chunks,
    scheduler=snakemake.params.scheduler,
    threads=snakemake.threads,
    log_path=snakemake.log[0],
)
