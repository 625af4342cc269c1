# config jobs: item. One job per item runs its chain from view files to features in one
# process (pipeline.run_item), writing the stores of ingest.smk and method.smk, which it
# replaces. Its parameters and code versions are those of all five stages.
rule item:
    input:
        views=item_views,
        calibration=CALIBRATION,
    output:
        ingest=directory(f"{PROCESSED}/ingest/{{item}}.zarr"),
        aoi=directory(f"{PROCESSED}/aoi/{{item}}.zarr"),
        reflectance=directory(f"{PROCESSED}/reflectance/{{item}}.zarr"),
        registered=directory(f"{PROCESSED}/registered/{{item}}.zarr"),
        features=directory(f"{PROCESSED}/features/{{item}}.zarr"),
    log:
        f"{LOGS}/item/{{item}}.log",
    benchmark:
        f"{LOGS}/benchmarks/item/{{item}}.tsv"
    priority: RESULTS_FIRST
    conda:
        ENV
    threads: 1
    resources:
        mem_mb=1000,
    params:
        campaign=str(CAMPAIGN),
        settings=item_settings,
        stage_params=item_stage_params,
        chunks=config["chunks"],
        scheduler=config["scheduler"],
        code={stage: STAGE_VERSION[stage] for stage in CHAIN_STAGES},
    script:
        "../scripts/item.py"
