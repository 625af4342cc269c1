from pathlib import Path

from surffin.analysis.diagnostics import run_calibration_diagnostics

run_calibration_diagnostics(
    snakemake.output.json,
    calibration=snakemake.input.calibration,
    repeat=snakemake.input.repeat or None,
    campaign=snakemake.params.campaign,
    repeat_folders=snakemake.params.repeat_folders,
    item_params=snakemake.params.item_params,
    figures_dir=Path(snakemake.output.correlation).parent,
    log_path=snakemake.log[0],
)
