from surffin.analysis.reproduction import run_paper_comparison

run_paper_comparison(
    snakemake.output[0],
    summary=snakemake.input.summary,
    specimens=snakemake.params.specimens,
    diagnostics=snakemake.input.diagnostics,
    sensitivity=snakemake.input.sensitivity,
    slopes=snakemake.input.slopes,
    relation=snakemake.input.get("relation"),
    runtime=snakemake.params.runtime,
    log_path=snakemake.log[0],
)
