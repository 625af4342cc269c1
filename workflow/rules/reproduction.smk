rule paper_comparison:
    input:
        unpack(comparison_inputs),
    output:
        f"{PROCESSED}/paper-comparison.md",
    log:
        f"{LOGS}/paper-comparison.log",
    threads: 1
    resources:
        mem_mb=500,
    params:
        specimens=from_plan("specimens_by_roughness"),
        runtime=runtime_settings,
        code=STAGES["comparison"].version,
    run:
        in_worker(
            run_paper_comparison,
            output[0],
            summary=input.summary,
            specimens=params.specimens,
            diagnostics=input.diagnostics,
            sensitivity=input.sensitivity,
            slopes=input.slopes,
            relation=input.get("relation"),
            runtime=params.runtime,
            log_path=log[0],
        )
