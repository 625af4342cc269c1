from snakemake.utils import min_version

min_version("9.1.4")


configfile: workflow.source_path("config/config.yaml")


include: "workflow/rules/common.smk"
include: "workflow/rules/campaign.smk"
include: "workflow/rules/calibration.smk"
include: "workflow/rules/diagnostics.smk"
include: "workflow/rules/method.smk"
include: "workflow/rules/classify.smk"
include: "workflow/rules/roughness.smk"
include: "workflow/rules/report.smk"
include: "workflow/rules/sensitivity.smk"
include: "workflow/rules/reproduction.smk"


# snakemake's job rate limiter (--max-jobs-per-timespan, 100/1s by default) throttles
# submissions to a cluster. Run locally it costs much and limits nothing: every scheduling
# round arms one more 1 s timer whose round arms the next, so each finished job adds a chain
# of rounds, each stat-ing the inputs of every ready job. On a 48-specimen campaign that was 99
# of snakemake's CPU-s against 23 without it (docs/performance.md). A local run turns it off.
onstart:
    if workflow.local_exec and hasattr(getattr(workflow, "scheduler", None), "job_rate_limiter"):
        workflow.scheduler.job_rate_limiter = None
        logger.info("surffin: local run, snakemake's job rate limiter is off")


rule all:
    default_target: True
    input:
        final_outputs,
        rules.calibration_figures.output,
        rules.calibration_diagnostics.output,
        rules.classification_figures.output,
        rules.sensitivity.output,
        rules.paper_comparison.output,
