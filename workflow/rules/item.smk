# config jobs: item. One job per item runs its chain from view files to features in one
# process (pipeline.run_items), writing the stores of ingest.smk and method.smk, which it
# replaces. Its parameters and code versions are those of all five stages. With
# item_batches N > 0 the specimens' chains run in N batch jobs instead (rules item_batch_<k>),
# each a process for several specimens; scenes keep a job each.


rule item:
    input:
        views=item_views,
        calibration=CALIBRATION,
    output:
        **{name: directory(path) for name, path in chain_stores("{item}").items()},
    log:
        f"{LOGS}/item/{{item}}.log",
    benchmark:
        f"{LOGS}/benchmarks/item/{{item}}.tsv"
    wildcard_constraints:
        item="|".join(re.escape(name) for name in CAMP.items if name not in BATCHED) or "(?!)",
    priority: RESULTS_FIRST
    conda:
        ENV
    threads: 1
    resources:
        mem_mb=1000,
    params:
        **CHAIN_JOB_PARAMS,
        chains=lambda wildcards: chains([wildcards.item]),
    script:
        "../scripts/item.py"


for batch, names in item_batches().items():

    rule:
        name:
            f"item_batch_{batch}"
        input:
            views=batch_views(names),
            calibration=CALIBRATION,
        output:
            [directory(path) for name in names for path in chain_stores(name).values()],
        log:
            f"{LOGS}/item_batch/{batch}.log",
        benchmark:
            f"{LOGS}/benchmarks/item_batch/{batch}.tsv"
        priority: RESULTS_FIRST
        conda:
            ENV
        threads: 1
        resources:
            mem_mb=1000,
        params:
            **CHAIN_JOB_PARAMS,
            chains=chains(names),
        script:
            "../scripts/item.py"
