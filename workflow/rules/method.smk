rule aoi:
    input:
        ingest=f"{PROCESSED}/ingest/{{item}}.zarr",
    output:
        directory(f"{PROCESSED}/aoi/{{item}}.zarr"),
    log:
        f"{LOGS}/aoi/{{item}}.log",
    benchmark:
        f"{LOGS}/benchmarks/aoi/{{item}}.tsv"
    priority: RESULTS_FIRST
    conda:
        ENV
    threads: 1
    resources:
        mem_mb=1000,
    params:
        stage="aoi",
        stage_params=aoi_params,
        chunks=config["chunks"],
        scheduler=config["scheduler"],
        code=STAGE_VERSION["aoi"],
    script:
        "../scripts/stage.py"


rule reflectance:
    input:
        ingest=f"{PROCESSED}/ingest/{{item}}.zarr",
        aoi=f"{PROCESSED}/aoi/{{item}}.zarr",
        calibration=CALIBRATION,
    output:
        directory(f"{PROCESSED}/reflectance/{{item}}.zarr"),
    log:
        f"{LOGS}/reflectance/{{item}}.log",
    benchmark:
        f"{LOGS}/benchmarks/reflectance/{{item}}.tsv"
    priority: RESULTS_FIRST
    conda:
        ENV
    threads: 1
    resources:
        mem_mb=1000,
    params:
        stage="reflectance",
        stage_params={},
        chunks=config["chunks"],
        scheduler=config["scheduler"],
        code=STAGE_VERSION["reflectance"],
    script:
        "../scripts/stage.py"


rule registration:
    input:
        ingest=f"{PROCESSED}/ingest/{{item}}.zarr",
        aoi=f"{PROCESSED}/aoi/{{item}}.zarr",
        reflectance=f"{PROCESSED}/reflectance/{{item}}.zarr",
    output:
        directory(f"{PROCESSED}/registered/{{item}}.zarr"),
    log:
        f"{LOGS}/registered/{{item}}.log",
    benchmark:
        f"{LOGS}/benchmarks/registered/{{item}}.tsv"
    priority: RESULTS_FIRST
    conda:
        ENV
    threads: 1
    resources:
        mem_mb=1000,
    params:
        stage="registration",
        stage_params=registration_params,
        chunks=config["chunks"],
        scheduler=config["scheduler"],
        code=STAGE_VERSION["registration"],
    script:
        "../scripts/stage.py"


rule features:
    input:
        registered=f"{PROCESSED}/registered/{{item}}.zarr",
        reflectance=f"{PROCESSED}/reflectance/{{item}}.zarr",
        aoi=f"{PROCESSED}/aoi/{{item}}.zarr",
    output:
        directory(f"{PROCESSED}/features/{{item}}.zarr"),
    log:
        f"{LOGS}/features/{{item}}.log",
    benchmark:
        f"{LOGS}/benchmarks/features/{{item}}.tsv"
    priority: RESULTS_FIRST
    conda:
        ENV
    threads: 1
    resources:
        mem_mb=1000,
    params:
        stage="features",
        stage_params=feature_params,
        chunks=config["chunks"],
        scheduler=config["scheduler"],
        code=STAGE_VERSION["features"],
    script:
        "../scripts/stage.py"
