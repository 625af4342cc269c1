"""Accuracy on the validation campaigns, against their truth and against a true-geometry ceiling.

Run by hand: ``python benchmarks/bench_validation.py [--campaigns NAME ...] [--imperfect] [--imperfections NAMES]
[--seeds 0 1 2] [--workdir DIR] [--config config/config.yaml] [--set SECTION.KEY=VALUE ...]``.

Each validation campaign (:data:`surffin.simulate.validation.VALIDATION`; ``paper`` and ``tiny`` too) is
rendered at each seed into ``--workdir`` (kept, and reused by later runs) and evaluated in this process with the
workflow's parameters (:func:`surffin.analysis.evaluation.evaluate_campaign`). By default the campaigns of an
ideal camera; ``--imperfect`` adds those of a real camera's imperfections
(:data:`~surffin.simulate.validation.IMPERFECT`: each alone, ``val-all`` together, ``val-bare-raw`` raw files
without poses or intrinsics, ``val-curved-all`` all on curved panels), whose truth is still the true geometry;
the ceiling then shows what the true AOI and the true instrument function make of the imperfect data (with the
residual systematics, which the instrument truth records as their factor, ``systematic``). ``--imperfections NAMES``
renders every chosen campaign with those imperfections instead of its own (names of
:data:`~surffin.simulate.imperfections.STANDARD`, e.g. ``--campaigns tiny --imperfections all``, a quick end-to-end
check). Printed per campaign and seed, then the mean and the range over the seeds:

- ``cal %``: median relative error over the crop of the fitted ``k f(d, theta) c(d, theta)`` (``c``: the
  calibration's residual correction, if any) against the true one (with the systematics);
- ``R0 %``, ``n %``: median relative error of the smoothed features on the specimen interiors of every item;
  ``ceil R0``, ``ceil n``: the same for a fit of the same data with the true AOI and instrument function (what
  the data allow);
- ``missing``: the largest share of an item's interior without features, %;
- ``label``, ``filtered``: the worst scene's accuracy (%) before and after the label filter, unclassified pixels
  counting as wrong; ``unclass``: the largest share of a scene's scored pixels left unclassified, %;
  ``ceiling``: the worst scene's accuracy of 1-NN on the ceiling's features, after the filter;
- ``board rej``: the smallest share of a scene's board pixels left unclassified, %.

Then the risk-coverage table: the scenes' scored pixels ranked by the class model's posterior of their k-NN
class, and the error rate (%) among the classified ones when only the most confident share is classified
(100 % = no reject option); and the posterior's calibration: per posterior bin, the error the posterior predicts
(mean of 1 - posterior) beside the error observed.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import dask
import numpy as np
import yaml

import surffin
from surffin.analysis.evaluation import evaluate_campaign, risk_coverage
from surffin.pipeline import parameters

ROWS = ("cal %", "R0 %", "n %", "ceil R0", "ceil n", "missing", "label", "filtered", "unclass", "ceiling", "board rej")
COVERAGES = (1.0, 0.999, 0.995, 0.99, 0.98, 0.95)
#: Posterior bins of the calibration check: does a posterior p err 1 - p of the time?
CALIBRATION_BINS = (0.0, 0.5, 0.9, 0.99, 0.999, 1.000001)


def campaigns() -> dict:
    """Name -> :class:`~surffin.simulate.validation.Validation` of every campaign the benchmark knows."""
    from surffin.simulate import PRESETS
    from surffin.simulate.validation import VALIDATION, Validation

    return {**{name: Validation(preset) for name, preset in PRESETS.items()}, **VALIDATION}


def render(name: str, seed: int, workdir: Path, imperfections: str | None = None) -> Path:
    """Return the campaign ``name`` at ``seed`` under ``workdir``, rendering it unless it is already there.

    ``imperfections`` (names of :data:`~surffin.simulate.imperfections.STANDARD`, comma-separated) replace
    the campaign's own; the directory's name then carries them.
    """
    from surffin.simulate import named_imperfections

    chosen = campaigns()[name]
    if imperfections is not None:
        chosen = dataclasses.replace(chosen, imperfections=named_imperfections(imperfections))
        name = f"{name}+{imperfections.replace(',', '+')}"
    directory = workdir / f"{name}-s{seed}"
    if not (directory / "campaign.yaml").exists():
        start = time.perf_counter()
        surffin.simulate_campaign(
            directory,
            chosen.preset,
            seed,
            fmt=chosen.fmt,
            units=chosen.units,
            poses=chosen.poses,
            imperfections=chosen.imperfections,
        )
        print(f"  rendered {directory.name} in {time.perf_counter() - start:.0f} s", flush=True)
    return directory


def row(result: dict) -> dict:
    """One line of the table from :func:`~surffin.analysis.evaluation.evaluate_campaign`'s result."""
    scenes, features = result["scenes"].values(), result["features"]
    return {
        "cal %": 100 * result["calibration_error"],
        "R0 %": 100 * features["R0"],
        "n %": 100 * features["n"],
        "ceil R0": 100 * features["ceiling_R0"],
        "ceil n": 100 * features["ceiling_n"],
        "missing": 100 * max(item["missing"] for item in result["items"].values()),
        "label": 100 * min(scene["label"] for scene in scenes),
        "filtered": 100 * min(scene["label_filtered"] for scene in scenes),
        "unclass": 100 * max(scene["unclassified"] for scene in scenes),
        "ceiling": 100 * min(scene["ceiling"] for scene in scenes),
        "board rej": 100 * min(scene["board_rejected"] for scene in scenes),
    }


def line(label: str, values: dict) -> str:
    """Format one table line: ``label``, then the value of each of :data:`ROWS`."""
    return f"{label:26s}" + "".join(f"{values[key]:10.2f}" for key in ROWS)


def main() -> None:
    """Parse the command line, evaluate every campaign at every seed and print the tables."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--campaigns", nargs="+", default=None, help="default: every validation campaign of an ideal camera"
    )
    parser.add_argument("--imperfect", action="store_true", help="add the campaigns of a real camera's imperfections")
    parser.add_argument(
        "--imperfections", default=None, metavar="NAMES", help="render every campaign with these imperfections instead"
    )
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--workdir", type=Path, default=Path("benchmarks/results/validation"))
    parser.add_argument("--config", type=Path, default=parameters.DEFAULT_CONFIG)
    parser.add_argument("--set", nargs="*", default=[], metavar="SECTION.KEY=VALUE", help="override config keys")
    args = parser.parse_args()
    config = parameters.read_config(args.config)
    for setting in args.set:
        key, value = setting.split("=", 1)
        section, _, leaf = key.partition(".")
        config[section][leaf] = yaml.safe_load(value)
    from surffin.simulate.validation import IMPERFECT, VALIDATION

    names = args.campaigns or [name for name in VALIDATION if name not in IMPERFECT]
    names += [name for name in IMPERFECT if args.imperfect and name not in names]
    args.workdir.mkdir(parents=True, exist_ok=True)
    print(f"{'campaign, seed':26s}" + "".join(f"{key:>10s}" for key in ROWS))
    results = {}
    with dask.config.set(scheduler="threads", num_workers=2):
        for name in names:
            shown = name if args.imperfections is None else f"{name}+{args.imperfections}"
            results[shown] = []
            for seed in args.seeds:
                start = time.perf_counter()
                directory = render(name, seed, args.workdir, args.imperfections)
                result = evaluate_campaign(directory, **parameters.evaluation_parameters(config))
                results[shown].append(result)
                reasons = {scene: value["reasons"] for scene, value in result["scenes"].items()}
                label = f"{shown} s{seed} ({time.perf_counter() - start:.0f} s)"
                print(line(label, row(result)), reasons, flush=True)
    print("\nmean over seeds, then min and max")
    for name, runs in results.items():
        rows = [row(result) for result in runs]
        print(line(name, {key: float(np.mean([r[key] for r in rows])) for key in ROWS}))
        print(line("  min", {key: min(r[key] for r in rows) for key in ROWS}))
        print(line("  max", {key: max(r[key] for r in rows) for key in ROWS}))
    print("\nrisk-coverage: error % among the classified scene pixels, by share classified (most confident first)")
    print(f"{'campaign':26s}" + "".join(f"{100 * c:>9.1f}%" for c in COVERAGES))
    for name, runs in results.items():
        posterior = np.concatenate([result["posterior"] for result in runs])
        correct = np.concatenate([result["correct"] for result in runs])
        curve = risk_coverage(posterior, correct, COVERAGES)
        print(f"{name:26s}" + "".join(f"{100 * error:10.3f}" for error in curve))
    print(
        "\nposterior calibration: per posterior bin, pixels, predicted error % (mean 1 - posterior), observed error %"
    )
    for name, runs in results.items():
        posterior = np.concatenate([result["posterior"] for result in runs])
        correct = np.concatenate([result["correct"] for result in runs])
        cells = []
        for low, high in zip(CALIBRATION_BINS[:-1], CALIBRATION_BINS[1:]):
            inside = (posterior >= low) & (posterior < high)
            if inside.any():
                predicted, observed = 100 * np.mean(1 - posterior[inside]), 100 * np.mean(~correct[inside])
                cells.append(f"[{low:g}, {high:g}): {inside.sum()} px {predicted:.2f} / {observed:.2f}")
        print(f"{name:26s}" + "; ".join(cells))


if __name__ == "__main__":
    main()
