rule roughness_relation:
    input:
        unpack(roughness_features),
    output:
        f"{PROCESSED}/roughness/relation.json",
    log:
        f"{LOGS}/roughness/relation.log",
    benchmark:
        f"{LOGS}/benchmarks/roughness/relation.tsv"
    conda:
        ENV
    threads: 1
    resources:
        mem_mb=1000,
    params:
        specimens=roughness_settings,
        code=STAGE_VERSION["roughness"],
    script:
        "../scripts/roughness_relation.py"


rule roughness_map:
    input:
        features=f"{PROCESSED}/features/{{scene}}.zarr",
        relation=f"{PROCESSED}/roughness/relation.json",
    output:
        directory(f"{PROCESSED}/roughness/{{scene}}.zarr"),
    log:
        f"{LOGS}/roughness/{{scene}}.log",
    benchmark:
        f"{LOGS}/benchmarks/roughness/{{scene}}.tsv"
    conda:
        ENV
    threads: 1
    resources:
        mem_mb=1000,
    params:
        chunks=config["chunks"],
        scheduler=config["scheduler"],
        code=STAGE_VERSION["roughness"],
    script:
        "../scripts/roughness_map.py"


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
    benchmark:
        f"{LOGS}/benchmarks/figures/roughness/{{scene}}.tsv"
    conda:
        ENV
    threads: 1
    resources:
        mem_mb=1000,
    params:
        code=STAGE_VERSION["figures"],
    script:
        "../scripts/figures.py"
