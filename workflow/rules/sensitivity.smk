rule sensitivity:
    output:
        table=f"{PROCESSED}/sensitivity/sensitivity.csv",
        store=directory(f"{PROCESSED}/sensitivity/sensitivity.zarr"),
        slopes=f"{PROCESSED}/sensitivity/slopes.csv",
        separation_figure=report(
            f"{PROCESSED}/sensitivity/separation.png",
            caption="../report/sensitivity_separation.rst",
            category="5. Sensitivity",
            labels={"figure": "two views against separation (Fig. 11)"},
        ),
        views_figure=report(
            f"{PROCESSED}/sensitivity/views.png",
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
