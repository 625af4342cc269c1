rule training:
    input:
        unpack(from_plan("specimen_features")),
        extra=config["extra_training"],
    output:
        directory(f"{PROCESSED}/training.zarr"),
    log:
        f"{LOGS}/training.log",
    priority: RESULTS_FIRST
    threads: 1
    resources:
        mem_mb=1000,
    params:
        specimens=from_plan("specimen_settings"),
        extra=config["extra_training"],
        max_per_class=config["classify"]["max_training_samples"],
        code=STAGES["training"].version,
    run:
        in_worker(
            run_training,
            output[0],
            specimens=params.specimens,
            extra=tuple(params.extra),
            max_per_class=params.max_per_class,
            log_path=log[0],
        )


rule labels:
    input:
        features=f"{PROCESSED}/features/{{scene}}.zarr",
        training=f"{PROCESSED}/training.zarr",
    output:
        directory(f"{PROCESSED}/labels/{{scene}}.zarr"),
    log:
        f"{LOGS}/labels/{{scene}}.log",
    priority: RESULTS_FIRST
    threads: 1
    resources:
        mem_mb=1500,
    params:
        stage=label_parameters(config),
        job=STAGE_JOB,
        code=STAGES["labels"].version,
    run:
        in_worker(
            run_stage,
            labels_stage,
            output[0],
            stores=dict(input.items()),
            params=params.stage,
            **params.job,
            threads=threads,
            log_path=log[0],
        )


rule summary:
    input:
        features=from_plan("item_features"),
        labels=from_plan("scene_label_stores"),
        truth=from_plan("truth_files"),
    output:
        f"{PROCESSED}/summary.json",
    log:
        f"{LOGS}/summary.log",
    priority: RESULTS_FIRST
    threads: 1
    resources:
        mem_mb=1000,
    params:
        features=from_plan("summary_features"),
        labels=from_plan("scene_labels"),
        truth=from_plan("scene_truth"),
        code=STAGES["summary"].version,
    run:
        in_worker(
            run_summary,
            output[0],
            features=params.features,
            labels=params.labels,
            truth=params.truth,
            log_path=log[0],
        )
