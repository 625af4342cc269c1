rule ingest:
    input:
        views=item_views,
    output:
        directory(f"{PROCESSED}/ingest/{{item}}.zarr"),
    log:
        f"{LOGS}/ingest/{{item}}.log",
    benchmark:
        f"{LOGS}/benchmarks/ingest/{{item}}.tsv"
    priority: RESULTS_FIRST
    conda:
        ENV
    threads: 1
    resources:
        mem_mb=1000,
    params:
        campaign=str(CAMPAIGN),
        settings=item_settings,
        chunks=config["chunks"],
        code=STAGE_VERSION["ingest"],
    script:
        "../scripts/ingest.py"
