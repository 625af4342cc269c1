"""How many wall views a calibration needs: the k f error against truth for subsets of a wall set.

Run by hand: ``python benchmarks/bench_wall_views.py [--validation val-plaster] [--seed 0]
[--campaign DIR] [--every 1 2 4]``. Renders the validation campaign (or takes ``--campaign``, a
rendered campaign with its truth in ``<DIR>-truth``), then fits the calibration with the
workflow's parameters from every k-th wall view (the wall set interleaves distances and tilts,
so each subset spans the same range) and prints the median relative error of the fitted
``k f(d, theta)`` against the simulator's (``surffin.analysis.evaluation.calibration_error``).
The subsets are symlinked copies of the campaign in a temporary folder; nothing is written in
the repository. docs/acquisition.md quotes its table.
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path

import surffin
from surffin.analysis.evaluation import calibration_error
from surffin.io.store import open_store
from surffin.method.calibration import calibrate
from surffin.pipeline.parameters import calibration_parameters, read_config
from surffin.simulate import simulate_campaign
from surffin.simulate.validation import VALIDATION


def subset(campaign: Path, folder: Path, wall: list[Path], chosen: list[Path]) -> Path:
    """Copy ``campaign`` into ``folder`` (files symlinked) with only the ``chosen`` wall views."""
    wall_folder = wall[0].parent
    shutil.copytree(campaign, folder, symlinks=True, ignore=lambda d, names: names if Path(d) == wall_folder else [])
    for view in chosen:
        os.symlink(view, folder / view.relative_to(campaign))
    return folder


def main():
    """Render or read the campaign, fit each subset's calibration and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--validation", default="val-plaster", choices=sorted(VALIDATION))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--campaign", type=Path, help="a rendered campaign with its truth beside it")
    parser.add_argument("--every", type=int, nargs="+", default=[1, 2, 4], help="keep every k-th wall view")
    args = parser.parse_args()
    params = calibration_parameters(read_config())
    with tempfile.TemporaryDirectory() as tmp:
        campaign = args.campaign
        if campaign is None:
            campaign = Path(tmp) / args.validation
            spec = VALIDATION[args.validation]
            simulate_campaign(
                campaign, preset=spec.preset, seed=args.seed, fmt=spec.fmt, units=spec.units, poses=spec.poses
            )
        campaign = campaign.resolve()
        camp = surffin.read_campaign(campaign)
        instrument = open_store(Path(f"{campaign}-truth") / "instrument.zarr").compute()
        wall = sorted(camp.calibration.wall)
        print(f"\n{campaign.name}: {len(wall)} wall views; k f error = median |fitted / true - 1| over the crop")
        print(f"{'wall views':>10}  {'k f error %':>11}  {'fit s':>6}")
        for every in args.every:
            chosen = wall[::every]
            folder = subset(campaign, Path(tmp) / f"every-{every}", wall, chosen)
            start = time.perf_counter()
            fitted = calibrate(surffin.read_campaign(folder), **params)
            seconds = time.perf_counter() - start
            error = 100 * calibration_error(fitted, instrument, camp.crop)
            print(f"{len(chosen):>10}  {error:>11.2f}  {seconds:>6.1f}")


if __name__ == "__main__":
    main()
