from pathlib import Path

from surffin.analysis.sensitivity import run_sensitivity

run_sensitivity(
    Path(snakemake.output.store).parent,
    draws=snakemake.params.draws,
    seed=snakemake.params.seed,
    log_path=snakemake.log[0],
)
