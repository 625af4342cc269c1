from surffin.pipeline.run import run_training

run_training(
    snakemake.output[0],
    specimens=snakemake.params.specimens,
    extra=tuple(snakemake.params.extra),
    max_per_class=snakemake.params.max_per_class,
    log_path=snakemake.log[0],
)
