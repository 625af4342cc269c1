from surffin.pipeline import run_training

run_training(
    snakemake.output[0],
    specimens=snakemake.params.specimens,
    extra=tuple(snakemake.params.extra),
    log_path=snakemake.log[0],
)
