# An item's chain from its view files to its features: one rule per stage of
# surffin.pipeline.table, each calling one surffin.pipeline.run function. The jobs
# run in snakemake's own threads (force-use-threads in profiles/default), so a
# job costs no process start-up and a parameter change reruns only the stages
# it touches. An item's jobs share a worker process when it is idle (affinity),
# which keeps the stores they load.


rule ingest:
    input:
        views=from_plan("item_views", "item"),
    output:
        directory(stage_output("ingest")),
    log:
        f"{LOGS}/ingest/{{item}}.log",
    priority: RESULTS_FIRST
    threads: 1
    resources:
        mem_mb=1000,
    params:
        campaign=str(CAMPAIGN),
        settings=from_plan("item_settings", "item"),
        chunks=config["chunks"],
        code=STAGES["ingest"].version,
    run:
        in_worker(
            run_ingest,
            params.campaign,
            wildcards.item,
            output[0],
            chunks=params.chunks,
            log_path=log[0],
            affinity=wildcards.item,
        )


rule aoi:
    input:
        **stage_inputs("aoi"),
    output:
        directory(stage_output("aoi")),
    log:
        f"{LOGS}/aoi/{{item}}.log",
    priority: RESULTS_FIRST
    threads: 1
    resources:
        mem_mb=1000,
    params:
        stage=aoi_parameters(config),
        job=STAGE_JOB,
        code=STAGES["aoi"].version,
    run:
        in_worker(
            run_stage,
            aoi_stage,
            output[0],
            stores=dict(input.items()),
            params=params.stage,
            **params.job,
            threads=threads,
            log_path=log[0],
            affinity=wildcards.item,
        )


rule reflectance:
    input:
        **stage_inputs("reflectance"),
    output:
        directory(stage_output("reflectance")),
    log:
        f"{LOGS}/reflectance/{{item}}.log",
    priority: RESULTS_FIRST
    threads: 1
    resources:
        mem_mb=1000,
    params:
        job=STAGE_JOB,
        code=STAGES["reflectance"].version,
    run:
        in_worker(
            run_stage,
            reflectance_stage,
            output[0],
            stores=dict(input.items()),
            **params.job,
            threads=threads,
            log_path=log[0],
            affinity=wildcards.item,
        )


rule registration:
    input:
        **stage_inputs("registration"),
    output:
        directory(stage_output("registration")),
    log:
        f"{LOGS}/registered/{{item}}.log",
    priority: RESULTS_FIRST
    threads: 1
    resources:
        mem_mb=1000,
    params:
        stage=from_plan("registration_parameters", "item"),
        job=STAGE_JOB,
        code=STAGES["registration"].version,
    run:
        in_worker(
            run_stage,
            registration_stage,
            output[0],
            stores=dict(input.items()),
            params=params.stage,
            **params.job,
            threads=threads,
            log_path=log[0],
            affinity=wildcards.item,
        )


rule features:
    input:
        **stage_inputs("features"),
    output:
        directory(stage_output("features")),
    log:
        f"{LOGS}/features/{{item}}.log",
    priority: RESULTS_FIRST
    threads: 1
    resources:
        mem_mb=1000,
    params:
        stage=from_plan("feature_parameters", "item"),
        job=STAGE_JOB,
        code=STAGES["features"].version,
    run:
        in_worker(
            run_stage,
            features_stage,
            output[0],
            stores=dict(input.items()),
            params=params.stage,
            **params.job,
            threads=threads,
            log_path=log[0],
            affinity=wildcards.item,
        )
