from surffin.analysis.sensitivity import OUTPUTS as SENSITIVITY_FILES

# run_sensitivity names its files (SENSITIVITY_FILES) in the folder it is given.
SENSITIVITY = {key: f"{PROCESSED}/sensitivity/{name}" for key, name in SENSITIVITY_FILES.items()}


rule sensitivity:
    output:
        table=SENSITIVITY["table"],
        store=directory(SENSITIVITY["store"]),
        slopes=SENSITIVITY["slopes"],
        separation_figure=report(
            SENSITIVITY["separation_figure"],
            caption="../report/sensitivity_separation.rst",
            category="5. Sensitivity",
            labels={"figure": "two views against separation (Fig. 11)"},
        ),
        views_figure=report(
            SENSITIVITY["views_figure"],
            caption="../report/sensitivity_views.rst",
            category="5. Sensitivity",
            labels={"figure": "K views over 45 deg (Fig. 12)"},
        ),
    log:
        f"{LOGS}/sensitivity.log",
    benchmark:
        f"{LOGS}/benchmarks/sensitivity.tsv"
    conda:
        ENV
    threads: 1
    resources:
        mem_mb=500,
    params:
        draws=config["sensitivity"]["draws"],
        seed=config["sensitivity"]["seed"],
        code=STAGE_VERSION["sensitivity"],
    script:
        "../scripts/sensitivity.py"
