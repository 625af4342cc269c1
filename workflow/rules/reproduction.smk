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
    params:
        specimens=specimens_by_roughness,
        runtime=runtime_settings,
        code=STAGE_VERSION["comparison"],
    threads: 1
    conda:
        ENV
    resources:
        mem_mb=500,
    script:
        "../scripts/paper_comparison.py"
