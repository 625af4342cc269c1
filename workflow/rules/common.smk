from pathlib import Path

from snakemake.exceptions import WorkflowError
from snakemake.utils import validate

from surffin.errors import SurffinError
from surffin.io.campaign import NAME_PATTERN
from surffin.method.stages import aoi_stage, features_stage, labels_stage, reflectance_stage, registration_stage
from surffin.pipeline.analyses import (
    run_calibration_diagnostics,
    run_export,
    run_figures,
    run_paper_comparison,
    run_sensitivity,
)
from surffin.pipeline.jobs import in_worker, start_workers
from surffin.pipeline.parameters import aoi_parameters, calibration_parameters, label_parameters
from surffin.pipeline.run import (
    run_calibration,
    run_default_campaign,
    run_ingest,
    run_roughness_map,
    run_roughness_relation,
    run_stage,
    run_summary,
    run_training,
)
from surffin.pipeline.table import CHAIN, STAGES, input_paths, output_path
from surffin.pipeline.workflow import Plan
from surffin.report.sensitivity import OUTPUTS as SENSITIVITY_FILES

validate(config, "../schemas/config.schema.yaml")

DEFAULT_CAMPAIGN = Path(workflow.basedir, "data", "raw").resolve()
CAMPAIGN = Path(config["campaign"])
PROCESSED = config["processed"]
LOGS = config["logs"]
# Per-item stages' job settings: the output stores' chunks and the dask scheduler.
STAGE_JOB = {"chunks": config["chunks"], "scheduler": config["scheduler"]}
# run_sensitivity names its files (SENSITIVITY_FILES) in the folder it is given.
SENSITIVITY = {key: f"{PROCESSED}/sensitivity/{name}" for key, name in SENSITIVITY_FILES.items()}
# The jobs on the way to summary.json run first; the diagnostics, sensitivity and figures take
# the cores left over (benchmarks/bench_campaign.py).
RESULTS_FIRST = 10
# Among jobs of one priority the greedy scheduler starts those of the most input bytes first: the
# sensitivity analysis (no input) and the calibration and roughness figures (one store each) take a
# core before the items' figures, rather than running alone on one at the end of a run.
BEFORE_FIGURES = 1
# The repeat calibration and the calibration diagnostics (one after the other, the longest chain off the
# results' path) start before the other jobs off it, so that the run does not end with them alone on a core.
DIAGNOSTICS_FIRST = 2
_PLAN = []


wildcard_constraints:
    item=NAME_PATTERN.pattern,
    scene=NAME_PATTERN.pattern,


def plan():
    """The campaign's Plan, read once (every view file checked); the default campaign is rendered first when absent."""
    if not _PLAN:
        if workflow.local_exec and not workflow.dryrun:
            start_workers()  # the job workers import surffin while the DAG is built
        if CAMPAIGN.resolve() == DEFAULT_CAMPAIGN and not (CAMPAIGN / "campaign.yaml").exists():
            checkpoints.default_campaign.get()
        try:
            _PLAN.append(Plan.read(CAMPAIGN, config))
        except SurffinError as exc:
            raise WorkflowError(str(exc)) from None
        if not workflow.dryrun:
            _PLAN[0].keep_checked()
    return _PLAN[0]


CALIBRATION = config["calibration_store"] or output_path("calibration", PROCESSED)


def from_plan(method, *keys):
    """An input or params function: the Plan's ``method`` of the job's wildcards ``keys``."""

    def function(wildcards):
        return getattr(plan(), method)(*(wildcards[key] for key in keys))

    function.__name__ = method
    return function


def stage_output(stage):
    return output_path(stage, PROCESSED)


def stage_inputs(stage):
    return input_paths(stage, PROCESSED, CALIBRATION)


def repeat_calibration_views(wildcards):
    if plan().repeat is None:
        raise WorkflowError(
            f"no repeat calibration set in {CAMPAIGN}: calibration_repeat is null or names folders the campaign lacks"
        )
    return plan().repeat_views()


def repeat_calibration_store(wildcards):
    """The repeat calibration store when there is a repeat set; else none (the diagnostics say why)."""
    return [] if plan().repeat is None else f"{PROCESSED}/diagnostics/calibration-repeat.zarr"


def comparison_inputs(wildcards):
    inputs = {
        "summary": stage_output("summary"),
        "diagnostics": f"{PROCESSED}/diagnostics/calibration.json",
        "sensitivity": SENSITIVITY["store"],
        "slopes": SENSITIVITY["slopes"],
    }
    return inputs | ({"relation": stage_output("roughness_relation")} if plan().roughness_outputs() else {})


def runtime_settings(wildcards):
    """Per scene, its view count and the logs of its jobs from raw views to labels (they time themselves)."""
    return {
        name: {
            "views": len(item.views),
            "logs": [expand(getattr(rules, rule).log[0], item=name, scene=name)[0] for rule in (*CHAIN, "labels")],
        }
        for name, item in plan().campaign.scenes.items()
    }


def final_outputs(wildcards):
    """Everything the default target makes: results, figures, diagnostics, sensitivity, comparison."""
    camp = plan().campaign
    return [
        *plan().results(),
        *expand(rules.item_figures.output.features, item=plan().figure_items()),
        *expand(rules.scene_figures.output.labels, scene=camp.scenes),
        *rules.export.output,
    ]
