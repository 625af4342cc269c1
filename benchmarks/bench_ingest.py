"""Ingest jobs and the workflow's start-up check: CPU seconds of this tree against another revision's.

Run by hand: ``python benchmarks/bench_ingest.py CAMPAIGN --baseline TREE [--items S1-01 ...] [--repeat 5]``
(``TREE``: a checkout of the other revision). Each round runs a process of each tree in turn, the
baseline first. In it, ``run_ingest`` writes each item's ingest store as the workflow's job does,
after one untimed call (a worker process runs many jobs: imports and caches are warm), and
``Plan.read`` reads the campaign and checks every view file's pixels as the workflow's start does
when the processed folder records no checked files (``CHECKED_VIEWS``). Prints the medians over
the rounds of the CPU seconds (``time.process_time``, all threads: the machine may be shared) of
an ingest job (the mean over the items) and of ``Plan.read``, old and new and their ratio, and
whether the two trees' ingest stores are identical (``xarray.testing.assert_identical`` and equal
attributes, dataset's and variables').
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import xarray as xr
from _trees import THIS_TREE, run_in_tree  # benchmarks/_trees.py: this folder is on sys.path when run as a script

from surffin.io.campaign import read_campaign
from surffin.io.store import open_store

#: The workflow configuration's keys that ``Plan.read`` reads, as a first run has them.
CONFIG = {"calibration_store": None, "extra_training": [], "calibration_repeat": None}


def time_tree(campaign: Path, items: list[str], outputs: Path) -> dict:
    """Time the ingest jobs of ``items`` (stores written to ``outputs``) and ``Plan.read`` in this process."""
    from surffin.pipeline.run import run_ingest
    from surffin.pipeline.workflow import Plan

    run_ingest(campaign, items[0], outputs / "warm-up.zarr")
    seconds = {"ingest job": [], "Plan.read": []}
    for item in items:
        start = time.process_time()
        run_ingest(campaign, item, outputs / f"{item}.zarr")
        seconds["ingest job"].append(time.process_time() - start)
    with tempfile.TemporaryDirectory() as processed:
        start = time.process_time()
        Plan.read(campaign, {**CONFIG, "processed": processed})
        seconds["Plan.read"].append(time.process_time() - start)
    return {task: float(np.mean(values)) for task, values in seconds.items()}


def differences(old: xr.Dataset, new: xr.Dataset) -> list[str]:
    """Say how two stores differ: values, coordinates and attributes (the dataset's and each variable's)."""
    try:
        xr.testing.assert_identical(old, new)
    except AssertionError as error:
        return [str(error).splitlines()[0]]
    found = [] if old.attrs == new.attrs else ["attrs"]
    return found + [f"{name}.attrs" for name in old.variables if old[name].attrs != new[name].attrs]


def compare_trees(campaign: Path, baseline: Path, items: list[str], repeat: int) -> None:
    """Print the median CPU seconds of each tree, their ratio, and whether the ingest stores agree."""
    trees = {"old": baseline, "new": THIS_TREE}
    seconds = {label: {} for label in trees}
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(repeat):
            for label, tree in trees.items():
                printed = run_in_tree(
                    tree, __file__, str(campaign), "--outputs", str(Path(tmp, label)), "--items", *items
                )
                for task, value in json.loads(printed).items():
                    seconds[label].setdefault(task, []).append(value)
        different = {}
        for item in items:
            old, new = (open_store(Path(tmp, label, f"{item}.zarr")).load() for label in trees)
            if problems := differences(old, new):
                different[item] = problems
    print(f"{campaign}: {len(items)} ingest jobs, CPU s, medians of {repeat} alternating rounds")
    print(f"{'task':12s}{'old':>9s}{'new':>9s}{'new/old':>9s}")
    for task in seconds["old"]:
        old, new = (float(np.median(seconds[label][task])) for label in trees)
        print(f"{task:12s}{old:9.4f}{new:9.4f}{new / old:9.2f}")
    print(f"ingest stores: {f'differ: {different}' if different else f'identical ({len(items)} items)'}")


def main():
    """Compare the trees, or (``--outputs``) time this process's tree and print its seconds as JSON."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("campaign", type=Path, help="a campaign directory")
    parser.add_argument("--baseline", type=Path, help="the tree of the revision to compare with")
    parser.add_argument("--items", nargs="+", help="the items whose ingest jobs run (default: all)")
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--outputs", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    items = args.items or list(read_campaign(args.campaign, check_views=False, require_calibration=False).items)
    if args.outputs:
        print(json.dumps(time_tree(args.campaign, items, args.outputs)))
    elif args.baseline is None:
        parser.error("--baseline is needed")
    else:
        compare_trees(args.campaign, args.baseline, items, args.repeat)


if __name__ == "__main__":
    main()
