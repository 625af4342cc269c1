rule ingest:
    input:
        views=item_views,
    output:
        directory(f"{PROCESSED}/ingest/{{item}}.zarr"),
    log:
        f"{LOGS}/ingest/{{item}}.log",
    benchmark:
        f"{LOGS}/benchmarks/ingest/{{item}}.tsv"
    params:
        campaign=str(CAMPAIGN),
        settings=item_settings,
        chunks=config["chunks"],
        code=STAGE_VERSION["ingest"],
    threads: 1
    conda:
        ENV
    resources:
        mem_mb=1000,
    script:
        "../scripts/ingest.py"
