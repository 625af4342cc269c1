from surffin.pipeline.run import run_roughness_relation

run_roughness_relation(
    snakemake.output[0],
    specimens=snakemake.params.specimens,
    log_path=snakemake.log[0],
)
