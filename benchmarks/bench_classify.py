"""CPU seconds of the training and labels jobs: this checkout against another (e.g. origin/main).

Run by hand: ``python benchmarks/bench_classify.py --campaign DIR --processed DIR --other DIR [--rounds 7]``.
``--processed`` holds a finished run's feature stores of the campaign at ``--campaign`` (it is only read);
``--other`` is a checkout to compare with (``git worktree add /tmp/old origin/main``). Each job runs as the
workflow's rule does (``run_training``; ``run_stage(labels_stage, ...)`` on ``--scene``), with the
parameters of config/config.yaml, in a fresh process per run whose imports (those of a job worker, and
scikit-learn) come before the clock starts. The two checkouts alternate, the first of each round
swapped every round, so that the load of the machine (it is shared) falls on both alike. Prints per job
the median CPU seconds (``time.process_time``) of each checkout, the ratio, and whether the two
checkouts' stores are the same byte for byte.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import yaml
from _trees import THIS_TREE, run_in_tree  # benchmarks/_trees.py: this folder is on sys.path when run as a script

JOBS = ("training", "labels")


def run_job(job: str, campaign: str, processed: str, scene: str, output: str) -> float:
    """Run one job into ``output`` with the surffin this process imports; return its CPU seconds."""
    import cv2
    import dask.array  # noqa: F401  (a worker has these imported after its first jobs)
    import scipy.optimize  # noqa: F401
    import sklearn.neighbors  # noqa: F401

    import surffin.pipeline.analyses  # noqa: F401  (the workers' preload)
    from surffin.io.campaign import read_campaign
    from surffin.method.stages import labels_stage
    from surffin.pipeline.parameters import label_parameters
    from surffin.pipeline.run import run_stage, run_training
    from surffin.pipeline.workflow import Plan

    cv2.setNumThreads(1)
    config = {**yaml.safe_load((THIS_TREE / "config" / "config.yaml").read_text()), "processed": processed}
    plan = Plan(read_campaign(campaign, check_views=False), config)
    start = time.process_time()
    if job == "training":
        run_training(
            output,
            specimens=plan.specimen_settings(),
            max_per_class=config["classify"]["max_training_samples"],
        )
    else:
        stores = {"features": plan.output("features", scene), "training": plan.output("training")}
        run_stage(
            labels_stage,
            output,
            stores=stores,
            params=label_parameters(config),
            chunks=config["chunks"],
            scheduler=config["scheduler"],
        )
    return time.process_time() - start


def files(root: Path) -> dict[str, bytes]:
    """Every file of a store by its relative path."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def main():
    """Run the jobs of both checkouts in turn and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--campaign", required=True, help="the campaign the processed folder is of")
    parser.add_argument("--processed", required=True, help="a finished run's processed folder (read only)")
    parser.add_argument("--other", type=Path, help="the checkout to compare with (required)")
    parser.add_argument("--scene", default="T1", help="the scene the labels job classifies")
    parser.add_argument("--rounds", type=int, default=7, help="runs of each job per checkout")
    parser.add_argument("--child", choices=JOBS, help=argparse.SUPPRESS)
    parser.add_argument("--output", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(run_job(args.child, args.campaign, args.processed, args.scene, args.output))
        return
    if args.other is None:
        parser.error("--other is required")
    checkouts = {"other": args.other.resolve(), "this": THIS_TREE}
    with tempfile.TemporaryDirectory() as tmp:
        print(f"{'job':10s} {'other s':>8s} {'this s':>8s} {'ratio':>6s}  stores")
        for job in JOBS:
            seconds = {name: [] for name in checkouts}
            for round_ in range(args.rounds):
                for name in sorted(checkouts, reverse=bool(round_ % 2)):
                    arguments = ["--child", job, "--output", f"{tmp}/{job}-{name}.zarr"]
                    arguments += ["--campaign", args.campaign, "--processed", args.processed, "--scene", args.scene]
                    seconds[name].append(float(run_in_tree(checkouts[name], __file__, *arguments).split()[-1]))
            other, this = (statistics.median(seconds[name]) for name in checkouts)
            same = files(Path(tmp, f"{job}-other.zarr")) == files(Path(tmp, f"{job}-this.zarr"))
            print(f"{job:10s} {other:8.3f} {this:8.3f} {other / this:6.3f}  {'identical' if same else 'DIFFER'}")


if __name__ == "__main__":
    main()
