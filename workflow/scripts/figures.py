from surffin.report.figures import run_figures

run_figures(
    dict(snakemake.output.items()),
    **dict(snakemake.input.items()),
    roi=snakemake.params.get("roi"),
    log_path=snakemake.log[0],
)
