rule training:
    input:
        unpack(specimen_features),
        extra=config["extra_training"],
    output:
        directory(f"{PROCESSED}/training.zarr"),
    log:
        f"{LOGS}/training.log",
    benchmark:
        f"{LOGS}/benchmarks/training.tsv"
    priority: RESULTS_FIRST
    conda:
        ENV
    threads: 1
    resources:
        mem_mb=1000,
    params:
        specimens=specimen_settings,
        extra=config["extra_training"],
        max_per_class=config["classify"]["max_training_samples"],
        code=STAGE_VERSION["training"],
    script:
        "../scripts/training.py"


rule labels:
    input:
        features=f"{PROCESSED}/features/{{scene}}.zarr",
        training=f"{PROCESSED}/training.zarr",
    output:
        directory(f"{PROCESSED}/labels/{{scene}}.zarr"),
    log:
        f"{LOGS}/labels/{{scene}}.log",
    benchmark:
        f"{LOGS}/benchmarks/labels/{{scene}}.tsv"
    priority: RESULTS_FIRST
    conda:
        ENV
    threads: 1
    resources:
        mem_mb=1500,
    params:
        stage="labels",
        stage_params=label_parameters(config),
        chunks=config["chunks"],
        scheduler=config["scheduler"],
        code=STAGE_VERSION["labels"],
    script:
        "../scripts/stage.py"


rule summary:
    input:
        features=item_stores("features"),
        labels=expand(f"{PROCESSED}/labels/{{scene}}.zarr", scene=CAMP.scenes),
        truth=truth_files,
    output:
        f"{PROCESSED}/summary.json",
    log:
        f"{LOGS}/summary.log",
    benchmark:
        f"{LOGS}/benchmarks/summary.tsv"
    priority: RESULTS_FIRST
    conda:
        ENV
    threads: 1
    resources:
        mem_mb=1000,
    params:
        features=summary_features,
        labels={name: f"{PROCESSED}/labels/{name}.zarr" for name in CAMP.scenes},
        truth=scene_truth,
        code=STAGE_VERSION["summary"],
    script:
        "../scripts/summary.py"
