# The bundled default campaign (config campaign: data/raw) is rendered by a job the first time it
# is needed, not when the workflow is read: `snakemake -n` and `--lint` write nothing.


checkpoint default_campaign:
    output:
        f"{DEFAULT_CAMPAIGN}/campaign.yaml",
    log:
        f"{LOGS}/default_campaign.log",
    params:
        preset=config["default_campaign"]["preset"],
        seed=config["default_campaign"]["seed"],
    run:
        in_worker(run_default_campaign, DEFAULT_CAMPAIGN, preset=params.preset, seed=params.seed, log_path=log[0])
