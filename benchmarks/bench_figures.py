"""The report's figures: CPU seconds per figure kind, against saving an empty figure.

Run by hand: ``python benchmarks/bench_figures.py [--campaign DIR] [--repeat 7]``. Without ``--campaign``
it renders the ``paper`` preset into a temporary folder. The stores are made once, as the workflow
makes them: the calibration, every item's chain (``bench_chunks.run_chain``), the training set of the
specimens and the first scene's labels. Then each figure kind but ``roughness`` (it needs the
specimens' roughness) is written by :func:`~surffin.report.figures.write_figures` from those stores
(``features``: the first specimen, with its roi), the kinds taking turns so that the machine's load
(it is shared) falls on all of them alike; one warm-up round is not counted. The reference is
matplotlib alone saving an empty figure of 19 x 9.5 in as PNG. Prints per kind
the median CPU seconds of the process (``time.process_time``) over the rounds and its ratio to the
reference. With ``--against REV`` (a git revision, e.g. ``HEAD``) each kind is also drawn, in the same
rounds, by the ``report/figures.py`` and ``report/canvas.py`` of that revision (:func:`figures_at`), and
the table gets their median and the speed-up (their median / this tree's). The last row, ``features in a row``,
is the feature figure of every item drawn one after another in a process forked for them (one a round and
revision), per figure: as a workflow's worker draws them, where a figure's garbage weighs on the collections
of the next ones, which the kinds drawn in turns in this one process do not show.
"""

from __future__ import annotations

import argparse
import io
import multiprocessing
import statistics
import subprocess
import sys
import tempfile
import time
import types
from pathlib import Path
from unittest import mock

from _paper import paper_campaign  # benchmarks/_paper.py: this folder is on sys.path when run as a script
from bench_chunks import CONFIG, quiet_logs, run_chain

from surffin.method.stages import labels_stage
from surffin.pipeline import parameters
from surffin.pipeline.run import run_calibration, run_stage, run_training
from surffin.report import figures as current
from surffin.report.canvas import DPI

#: Size of the reference's empty figure, inches (the feature figure's until it was made smaller).
REFERENCE_SIZE = (19.0, 9.5)
#: The row of :func:`features_in_a_row`.
ROW = "features in a row"


def make_stores(camp, folder: Path, specimen: str, scene: str) -> tuple[dict[str, Path], dict[str, dict[str, Path]]]:
    """Write the calibration, every item's chain, the training set and the scene's labels.

    Returns the figures' stores (``features`` and ``registered`` the specimen's) and each item's chain.
    """
    calibration = run_calibration(
        camp.path, folder / "calibration.zarr", params=parameters.calibration_parameters(CONFIG)
    )
    chains = {name: run_chain(camp, name, folder, calibration)[0] for name in camp.items}
    training = run_training(
        folder / "training.zarr",
        specimens={
            name: {
                "store": chains[name]["features"],
                "class": item.cls,
                "roi": None if item.roi is None else item.roi.as_mapping(),
            }
            for name, item in camp.specimens.items()
        },
        max_per_class=CONFIG["classify"]["max_training_samples"],
    )
    labels = run_stage(
        labels_stage,
        folder / "labels" / f"{scene}.zarr",
        stores={"features": chains[scene]["features"], "training": training},
        params=parameters.label_parameters(CONFIG),
    )
    stores = {
        "calibration": calibration,
        "training": training,
        "features": chains[specimen]["features"],
        "registered": chains[specimen]["registered"],
        "labels": labels,
        "ingest": chains[scene]["ingest"],
    }
    return stores, chains


def figures_at(revision: str) -> types.ModuleType:
    """Import ``surffin/report/figures.py`` of a git revision, drawing on that revision's ``canvas.py``.

    The rest of surffin is this tree's. Both modules are read with ``git show`` and made under other
    names; the old canvas stands in for :mod:`surffin.report.canvas` while the old figures import it.
    """
    root = Path(__file__).resolve().parents[1]

    def module(name: str, path: str) -> types.ModuleType:
        source = subprocess.run(
            ["git", "show", f"{revision}:{path}"], cwd=root, check=True, capture_output=True, text=True
        ).stdout
        made = types.ModuleType(name)
        made.__file__ = f"{revision}:{path}"
        exec(compile(source, made.__file__, "exec"), made.__dict__)
        return made

    canvas = module(f"canvas@{revision}", "surffin/report/canvas.py")
    with mock.patch.dict(sys.modules, {"surffin.report.canvas": canvas}):
        return module(f"figures@{revision}", "surffin/report/figures.py")


def features_in_a_row(module: types.ModuleType, items: dict, out: Path) -> float:
    """CPU seconds per figure of ``module`` writing the feature figure of each item in turn, in a forked process.

    ``items``: name -> (the ``inputs`` of ``write_figures``, the roi).
    """
    context = multiprocessing.get_context("fork")
    receive, send = context.Pipe(duplex=False)

    def draw() -> None:
        start = time.process_time()
        for name, (inputs, roi) in items.items():
            module.write_figures({"features": out / f"row-{name}.png"}, inputs, roi=roi)
        send.send((time.process_time() - start) / len(items))

    child = context.Process(target=draw)
    child.start()
    send.close()  # the child's end only: a child that fails ends the pipe
    seconds = receive.recv()
    child.join()
    return seconds


def reference() -> None:
    """Save an empty figure of :data:`REFERENCE_SIZE` as PNG, with matplotlib alone."""
    from matplotlib.figure import Figure

    Figure(figsize=REFERENCE_SIZE).savefig(io.BytesIO(), format="png", dpi=DPI)


def main():
    """Make the stores, write each figure kind in turns and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--campaign", type=Path, help="a rendered paper campaign")
    parser.add_argument("--repeat", type=int, default=7, help="counted rounds")
    parser.add_argument("--against", metavar="REV", help="also draw with the figures of this git revision")
    args = parser.parse_args()
    quiet_logs()
    with paper_campaign(args.campaign) as (camp, _), tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        specimen, scene = next(iter(camp.specimens)), next(iter(camp.scenes))
        stores, chains = make_stores(camp, out, specimen, scene)
        items = {
            name: ({"features": chain["features"], "registered": chain["registered"]}, camp.items[name].roi)
            for name, chain in chains.items()
        }
        figures = {
            "features": {"features": stores["features"], "registered": stores["registered"]},
            "labels": {"labels": stores["labels"], "ingest": stores["ingest"]},
            "calibration_fit": {"calibration": stores["calibration"]},
            "calibration_r2": {"calibration": stores["calibration"]},
            "wall_reflectance": {"calibration": stores["calibration"]},
            "feature_space": {"training": stores["training"]},
        }
        modules = {"": current, **({f"@{args.against}": figures_at(args.against)} if args.against else {})}
        kinds = {
            "reference": reference,
            **{
                kind + suffix: lambda kind=kind, inputs=inputs, module=module: module.write_figures(
                    {kind: out / f"{kind}{suffix}.png"}, inputs, roi=camp.items[specimen].roi
                )
                for kind, inputs in figures.items()
                for suffix, module in modules.items()
            },
        }
        times = {kind: [] for kind in kinds}
        for round_ in range(args.repeat + 1):
            for kind, draw in kinds.items():
                start = time.process_time()
                draw()
                if round_:
                    times[kind].append(time.process_time() - start)
            for suffix, module in modules.items():
                seconds = features_in_a_row(module, items, out)
                if round_:
                    times.setdefault(ROW + suffix, []).append(seconds)
        print(
            f"figures of the paper campaign (features: {specimen}, labels: {scene}), "
            f"CPU seconds, {args.repeat} rounds; reference: an empty {REFERENCE_SIZE[0]}x{REFERENCE_SIZE[1]} in "
            f"figure saved as PNG at {DPI} dpi"
        )
        medians = {kind: statistics.median(values) for kind, values in times.items()}
        base = medians["reference"]
        against = f"@{args.against}" if args.against else ""
        print(
            f"{'figure':18s}{'median s':>10s}{'ratio':>8s}"
            + (f"{against + ' s':>14s}{'speed-up':>10s}" * bool(against))
        )
        for kind in ("reference", *figures, ROW):
            row = f"{kind:18s}{medians[kind]:10.3f}{medians[kind] / base:8.2f}"
            if against and kind != "reference":
                row += f"{medians[kind + against]:14.3f}{medians[kind + against] / medians[kind]:10.2f}"
            print(row)


if __name__ == "__main__":
    main()
