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


rule all:
    default_target: True
    input:
        final_outputs,
        rules.calibration_figures.output,
        rules.calibration_diagnostics.output,
        rules.classification_figures.output,
        rules.sensitivity.output,
        rules.paper_comparison.output,
