from surffin.pipeline.run import run_summary

run_summary(
    snakemake.output[0],
    features=snakemake.params.features,
    labels=snakemake.params.labels,
    truth=snakemake.params.truth,
    log_path=snakemake.log[0],
)
