rule paper_comparison:
    input:
        unpack(comparison_inputs),
        benchmarks=runtime_benchmarks,
    output:
        f"{PROCESSED}/paper-comparison.md",
    log:
        f"{LOGS}/paper-comparison.log",
    benchmark:
        f"{LOGS}/benchmarks/paper-comparison.tsv"
    conda:
        ENV
    threads: 1
    resources:
        mem_mb=500,
    params:
        specimens=specimens_by_roughness,
        runtime=runtime_settings,
        code=STAGE_VERSION["comparison"],
    script:
        "../scripts/paper_comparison.py"
