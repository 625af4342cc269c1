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
    priority: BEFORE_FIGURES
    threads: 1
    resources:
        mem_mb=500,
    params:
        draws=config["sensitivity"]["draws"],
        seed=config["sensitivity"]["seed"],
        code=STAGES["sensitivity"].version,
    run:
        in_worker(run_sensitivity, Path(output.store).parent, draws=params.draws, seed=params.seed, log_path=log[0])
