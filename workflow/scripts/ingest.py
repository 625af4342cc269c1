from surffin.pipeline.run import run_ingest

run_ingest(
    snakemake.params.campaign,
    snakemake.wildcards.item,
    snakemake.output[0],
    chunks=snakemake.params.chunks,
    log_path=snakemake.log[0],
)
