from snakemake.utils import min_version

min_version("9.0")


configfile: workflow.source_path("config/config.yaml")


include: "workflow/rules/common.smk"
include: "workflow/rules/ingest.smk"
include: "workflow/rules/calibration.smk"
include: "workflow/rules/method.smk"
include: "workflow/rules/classify.smk"


rule all:
    input:
        final_outputs,
    default_target: True
