report: "../report/workflow.rst"


rule calibration_figures:
    input:
        calibration=CALIBRATION,
    output:
        calibration_fit=report(
            f"{PROCESSED}/figures/calibration_fit.png",
            caption="../report/calibration_fit.rst",
            category="1. Calibration",
            labels={"figure": "fit of sample pixels (Fig. 9)"},
        ),
        calibration_r2=report(
            f"{PROCESSED}/figures/calibration_r2.png",
            caption="../report/calibration_r2.rst",
            category="1. Calibration",
            labels={"figure": "R² per pixel"},
        ),
        calibration_table=[
            report(
                f"{PROCESSED}/figures/calibration_parameters.html",
                caption="../report/calibration_table.rst",
                category="1. Calibration",
                labels={"figure": "coefficients: correlation, variability (Table 2)"},
            ),
            f"{PROCESSED}/figures/calibration_parameters.csv",
        ],
        wall_reflectance=report(
            f"{PROCESSED}/figures/wall_reflectance.png",
            caption="../report/wall_reflectance.rst",
            category="1. Calibration",
            labels={"figure": "reflectance of the wall (Fig. 10)"},
        ),
    log:
        f"{LOGS}/figures/calibration.log",
    priority: BEFORE_FIGURES
    threads: 1
    resources:
        mem_mb=1500,
    params:
        code=STAGES["figures"].version,
    run:
        in_worker(run_figures, dict(output.items()), **dict(input.items()), log_path=log[0])


rule classification_figures:
    input:
        training=f"{PROCESSED}/training.zarr",
        summary=f"{PROCESSED}/summary.json",
    output:
        feature_space=report(
            f"{PROCESSED}/figures/feature_space.png",
            caption="../report/feature_space.rst",
            category="3. Classification",
            labels={"figure": "feature space of the specimens (Fig. 14)"},
        ),
        accuracy_table=[
            report(
                f"{PROCESSED}/figures/accuracy.html",
                caption="../report/accuracy.rst",
                category="3. Classification",
                labels={"figure": "accuracy and class fractions"},
            ),
            f"{PROCESSED}/figures/accuracy.csv",
        ],
    log:
        f"{LOGS}/figures/classification.log",
    threads: 1
    resources:
        mem_mb=1000,
    params:
        code=STAGES["figures"].version,
    run:
        in_worker(run_figures, dict(output.items()), **dict(input.items()), log_path=log[0])


rule item_figures:
    input:
        features=f"{PROCESSED}/features/{{item}}.zarr",
        registered=f"{PROCESSED}/registered/{{item}}.zarr",
    output:
        features=report(
            f"{PROCESSED}/figures/features/{{item}}.png",
            caption="../report/features.rst",
            category="2. Features",
            labels={"item": "{item}", "figure": "feature images (Fig. 13)"},
        ),
    log:
        f"{LOGS}/figures/features/{{item}}.log",
    threads: 1
    resources:
        mem_mb=1000,
    params:
        roi=from_plan("roi", "item"),
        code=STAGES["figures"].version,
    run:
        in_worker(run_figures, dict(output.items()), **dict(input.items()), roi=params.roi, log_path=log[0])


rule scene_figures:
    input:
        labels=f"{PROCESSED}/labels/{{scene}}.zarr",
        ingest=f"{PROCESSED}/ingest/{{scene}}.zarr",
        summary=f"{PROCESSED}/summary.json",
    output:
        labels=report(
            f"{PROCESSED}/figures/labels/{{scene}}.png",
            caption="../report/labels.rst",
            category="3. Classification",
            labels={"scene": "{scene}", "figure": "label map (Fig. 15)"},
        ),
    log:
        f"{LOGS}/figures/labels/{{scene}}.log",
    threads: 1
    resources:
        mem_mb=1000,
    params:
        code=STAGES["figures"].version,
    run:
        in_worker(run_figures, dict(output.items()), **dict(input.items()), log_path=log[0])


rule export:
    input:
        unpack(from_plan("export_inputs")),
        calibration=CALIBRATION,
    output:
        directory(f"{PROCESSED}/export"),
    log:
        f"{LOGS}/export.log",
    threads: 1
    resources:
        mem_mb=1000,
    params:
        code=STAGES["export"].version,
    run:
        in_worker(run_export, output[0], training=input.training, calibration=input.calibration, log_path=log[0])
