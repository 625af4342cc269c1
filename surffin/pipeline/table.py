"""The stage table: every stage of a run, its function, input stores, output and code version.

The workflow's rules, the entry points of :mod:`surffin.pipeline.run`, the
benchmarks and ``surffin inspect`` read it. An item's chain (ingest to
features) is :data:`surffin.method.stages.ITEM_CHAIN`, whose stages take their
input stores from the function's positional arguments; the table adds their
code versions and outputs. Bump a stage's ``version`` when a change to surffin
alters what it writes: the stores record it (``surffin_code_version``) and the
workflow reruns that stage and what depends on it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from surffin.analysis.diagnostics import calibration_report
from surffin.analysis.reproduction import write_comparison
from surffin.analysis.summary import summarise
from surffin.io.ingest import ingest_item
from surffin.method.calibration import calibrate
from surffin.method.classify import training_set
from surffin.method.roughness import roughness_relation
from surffin.method.stages import ITEM_CHAIN, labels_stage, roughness_stage
from surffin.report.export import export_results
from surffin.report.figures import write_figures
from surffin.report.sensitivity import write_sensitivity

__all__ = ["Stage", "STAGES", "CHAIN", "stage_of", "output_path", "input_paths"]


@dataclass(frozen=True)
class Stage:
    """A stage of a run.

    Attributes
    ----------
    name : str
        The stage's name, as the rule that runs it.
    function : callable
        What computes its output.
    inputs : tuple of str
        Its input stores (or files), by the function's argument names.
    output : str
        Its output under the processed folder; ``{item}``/``{scene}`` for one per item or scene.
    version : int
        Its code version.
    """

    name: str
    function: Callable
    inputs: tuple[str, ...]
    output: str
    version: int


def _chain(name: str, version: int) -> Stage:
    step = next(step for step in ITEM_CHAIN if step.name == name)
    return Stage(name, step.function, step.inputs, f"{step.output}/{{item}}.zarr", version)


STAGES = {
    stage.name: stage
    for stage in (
        Stage("calibration", calibrate, ("views",), "calibration.zarr", 7),
        Stage("ingest", ingest_item, ("views",), "ingest/{item}.zarr", 3),
        _chain("aoi", 6),
        _chain("reflectance", 5),
        _chain("registration", 8),
        _chain("features", 7),
        Stage("training", training_set, ("features",), "training.zarr", 4),
        Stage("labels", labels_stage, ("features", "training"), "labels/{scene}.zarr", 4),
        Stage("summary", summarise, ("features", "labels", "truth"), "summary.json", 2),
        Stage("roughness_relation", roughness_relation, ("features",), "roughness/relation.json", 1),
        Stage("roughness", roughness_stage, ("features",), "roughness/{scene}.zarr", 2),
        Stage("export", export_results, ("features", "labels", "training", "summary"), "export", 1),
        Stage("figures", write_figures, ("calibration", "training", "summary", "features", "labels"), "figures", 4),
        Stage(
            "diagnostics",
            calibration_report,
            ("calibration", "views", "ingest", "aoi", "registered", "features"),
            "diagnostics",
            4,
        ),
        Stage("sensitivity", write_sensitivity, (), "sensitivity", 3),
        Stage("comparison", write_comparison, ("summary", "diagnostics", "sensitivity"), "paper-comparison.md", 4),
    )
}

#: The item chain's stages in order, from view files to features.
CHAIN = ("ingest", *(step.name for step in ITEM_CHAIN))


def stage_of(function: Callable) -> Stage:
    """Return the stage whose function is ``function``.

    Raises
    ------
    KeyError
        No stage of the table computes with it.
    """
    for stage in STAGES.values():
        if stage.function is function:
            return stage
    raise KeyError(f"{getattr(function, '__qualname__', function)!r} is no stage's function in surffin.pipeline.table")


#: The stage whose store an item stage's input of that name is.
_STORE_STAGE = {"ingest": "ingest", **{step.output: step.name for step in ITEM_CHAIN}}


def output_path(stage: str, processed: str, name: str | None = None) -> str:
    """Return a stage's output under the ``processed`` folder, for one item or scene (``{item}`` when None)."""
    pattern = f"{processed}/{STAGES[stage].output}"
    return pattern if name is None else pattern.format(item=name, scene=name)


def input_paths(stage: str, processed: str, calibration: str) -> dict[str, str]:
    """Return an item stage's input stores by argument name (with ``{item}``); ``calibration`` is its store."""
    return {
        arg: calibration if arg == "calibration" else output_path(_STORE_STAGE[arg], processed)
        for arg in STAGES[stage].inputs
    }
