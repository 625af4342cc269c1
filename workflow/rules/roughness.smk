rule roughness_relation:
    input:
        unpack(from_plan("roughness_features")),
    output:
        f"{PROCESSED}/roughness/relation.json",
    log:
        f"{LOGS}/roughness/relation.log",
    threads: 1
    resources:
        mem_mb=1000,
    params:
        specimens=from_plan("roughness_settings"),
        code=STAGES["roughness_relation"].version,
    run:
        in_worker(run_roughness_relation, output[0], specimens=params.specimens, log_path=log[0])


rule roughness_map:
    input:
        features=f"{PROCESSED}/features/{{scene}}.zarr",
        relation=f"{PROCESSED}/roughness/relation.json",
    output:
        directory(f"{PROCESSED}/roughness/{{scene}}.zarr"),
    log:
        f"{LOGS}/roughness/{{scene}}.log",
    threads: 1
    resources:
        mem_mb=1000,
    params:
        chunks=config["chunks"],
        scheduler=config["scheduler"],
        code=STAGES["roughness"].version,
    run:
        in_worker(
            run_roughness_map,
            output[0],
            features=input.features,
            relation=input.relation,
            chunks=params.chunks,
            scheduler=params.scheduler,
            threads=threads,
            log_path=log[0],
        )


rule roughness_figures:
    input:
        roughness=f"{PROCESSED}/roughness/{{scene}}.zarr",
    output:
        roughness=report(
            f"{PROCESSED}/figures/roughness/{{scene}}.png",
            caption="../report/roughness.rst",
            category="4. Roughness (indicative)",
            labels={"scene": "{scene}", "figure": "roughness from n"},
        ),
    log:
        f"{LOGS}/figures/roughness/{{scene}}.log",
    priority: BEFORE_FIGURES
    threads: 1
    resources:
        mem_mb=1000,
    params:
        code=STAGES["figures"].version,
    run:
        in_worker(run_figures, dict(output.items()), **dict(input.items()), log_path=log[0])
