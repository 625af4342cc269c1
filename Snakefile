from snakemake.utils import min_version

min_version("9.0")


configfile: workflow.source_path("config/config.yaml")


include: "workflow/rules/common.smk"
include: "workflow/rules/calibration.smk"
include: "workflow/rules/diagnostics.smk"


if config["jobs"] == "item":

    include: "workflow/rules/item.smk"

else:

    include: "workflow/rules/ingest.smk"
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
        expand(rules.item_figures.output.features, item=figure_items()),
        expand(rules.scene_figures.output.labels, scene=CAMP.scenes),
        rules.sensitivity.output,
        rules.paper_comparison.output,
