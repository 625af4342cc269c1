"""One item from view files to features: time per stage, and accuracy against the truth.

Run by hand: ``python benchmarks/bench_item.py [--campaign DIR] [--repeat 5] [--threads 2]``.
Without ``--campaign`` it renders the ``paper`` preset into a temporary folder.
The calibration is fitted once (its cost is per camera, not per item; see
``bench_calibration.py``). Each item's chain runs as the workflow's jobs run it
(``bench_chunks.run_chain``: each stage opens its input stores, computes and writes
its store) with the workflow's configuration. Prints, per stage, the median wall
time over repeats in this process (the machine is shared: compare stages, not
absolute times), and, per item, the median relative error of R0 and n against the
simulator's truth on the specimen interiors (roi pixels; the scene's labelled
pixels) and the scene's accuracy before and after the label filter (the
configuration's training cap and label parameters).

``--stores PROCESSED --baseline TREE`` (a workflow's processed stores, a checkout of another revision)
instead times the per-item stages of :data:`STAGES` in memory on the stores' items (``--items``, default
all): each stage runs on the inputs and with the parameters its store records, in a process of each tree
in turn (``--repeat`` rounds after a warm-up call per item), and prints the median CPU seconds per item of
each tree, their ratio, and whether the outputs of the two are identical (``xarray.testing.assert_identical``).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import xarray as xr

# benchmarks/: this folder is on sys.path when run as a script
from _paper import paper_campaign
from _trees import THIS_TREE, run_in_tree
from bench_chunks import CONFIG, quiet_logs, run_chain

from surffin.io.campaign import read_truth
from surffin.io.store import open_store, write_store
from surffin.method.classify import score, training_set
from surffin.method.stages import features_stage, labels_stage, reflectance_stage
from surffin.pipeline import parameters
from surffin.pipeline.run import run_calibration

#: The stages ``--stores`` times, by the name of the store they write.
STAGES = {"reflectance": reflectance_stage, "features": features_stage}


def chain(camp, name, folder, calibration, repeat, threads):
    """Run one item's chain ``repeat`` times; returns its features (computed) and the median seconds per stage."""
    runs = [run_chain(camp, name, folder, calibration, threads=threads) for _ in range(repeat)]
    times = {stage: float(np.median([seconds[stage] for _, seconds in runs])) for stage in runs[0][1]}
    return open_store(runs[-1][0]["features"]).compute(), times


def interior(truth: xr.Dataset, item) -> xr.DataArray:
    """Return the item's truth pixels that carry a label (label >= 0), within its roi."""
    mask = truth["label"] >= 0
    if item.roi is not None:
        in_roi = (
            (truth.y >= item.roi.y[0])
            & (truth.y < item.roi.y[1])
            & (truth.x >= item.roi.x[0])
            & (truth.x < item.roi.x[1])
        )
        mask = mask & in_roi
    return mask


def time_stages(processed: Path, items: list[str], outputs: Path | None) -> dict:
    """Time each stage of :data:`STAGES` on each item in this process; CPU seconds by stage and item.

    The inputs are read into memory first, as a job reads an item that fits in one chunk; the stage
    runs once untimed (imports, caches), then once timed. With ``outputs``, the stages' outputs are
    written there as stores (``<stage>/<item>.zarr``).
    """
    seconds, results = {}, {}
    for stage, function in STAGES.items():
        for item in items:
            written = open_store(processed / stage / f"{item}.zarr")
            inputs = {name: open_store(path).load() for name, path in written.attrs["surffin_inputs"].items()}
            results[stage, item] = function(**inputs, **written.attrs["surffin_parameters"])
            start = time.process_time()
            function(**inputs, **written.attrs["surffin_parameters"])
            seconds.setdefault(stage, {})[item] = time.process_time() - start
    for (stage, item), ds in results.items() if outputs is not None else ():
        write_store(ds, outputs / stage / f"{item}.zarr")
    return seconds


def compare_trees(processed: Path, baseline: Path, items: list[str], repeat: int) -> None:
    """Print the CPU seconds per item of each stage, ``baseline``'s tree against this one, and if they agree."""
    trees = {"old": baseline, "new": THIS_TREE}
    seconds = {label: {stage: [] for stage in STAGES} for label in trees}
    with tempfile.TemporaryDirectory() as tmp:
        for round_ in range(repeat):
            for label, tree in trees.items():
                outputs = Path(tmp, label) if round_ == 0 else None
                arguments = ["--stores", str(processed), "--time-only", "--items", *items]
                arguments += ["--outputs", str(outputs)] if outputs else []
                runs = json.loads(run_in_tree(tree, __file__, *arguments))
                for stage, by_item in runs.items():
                    seconds[label][stage].append(sum(by_item.values()) / len(by_item))
        results = {
            label: {
                (stage, item): open_store(Path(tmp, label, stage, f"{item}.zarr")).load()
                for stage in STAGES
                for item in items
            }
            for label in trees
        }
    print(f"{len(items)} items of {processed}, CPU s per item, medians of {repeat} alternating rounds")
    print(f"{'stage':14s}{'old':>9s}{'new':>9s}{'new/old':>9s}  outputs")
    for stage in STAGES:
        different = []
        for item in items:
            try:
                xr.testing.assert_identical(results["old"][stage, item], results["new"][stage, item])
            except AssertionError:
                different.append(item)
        old, new = (float(np.median(seconds[label][stage])) for label in trees)
        agree = f"differ for {different}" if different else "identical"
        print(f"{stage:14s}{old:9.4f}{new:9.4f}{new / old:9.2f}  {agree}")


def main():
    """Calibrate, run each item's chain, classify the scene and print the tables."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--campaign", type=Path, help="a rendered paper campaign (truth in <campaign>-truth)")
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--threads", type=int, default=2, help="dask threads of each stage")
    parser.add_argument("--stores", type=Path, help="a workflow's processed stores: time the stages of STAGES")
    parser.add_argument("--baseline", type=Path, help="with --stores: the tree of the revision to compare with")
    parser.add_argument("--items", nargs="+", help="with --stores: the items (default: all)")
    parser.add_argument("--time-only", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--outputs", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    quiet_logs()
    if args.stores:
        items = args.items or sorted(path.stem for path in (args.stores / "features").glob("*.zarr"))
        if args.time_only:
            print(json.dumps(time_stages(args.stores, items, args.outputs)))
        else:
            compare_trees(args.stores, args.baseline, items, args.repeat)
        return
    with paper_campaign(args.campaign) as (camp, truth_dir), tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        calibration = run_calibration(
            camp.path, Path(tmp, "calibration.zarr"), params=parameters.calibration_parameters(CONFIG)
        )
        print(
            f"calibration ({len(camp.calibration.wall)} wall views, full sensor): {time.perf_counter() - start:.2f} s\n"
        )
        features, all_times = {}, {}
        for name in camp.items:
            features[name], all_times[name] = chain(camp, name, tmp, calibration, args.repeat, args.threads)
        stages = list(next(iter(all_times.values())))
        crop = camp.crop
        print(
            f"median seconds per stage (inputs opened, computed, store written), per item "
            f"({crop.shape[0]}x{crop.shape[1]} crop), threads {args.threads}"
        )
        print(f"{'item':6s}" + "".join(f"{stage:>14s}" for stage in stages) + f"{'total':>10s}{'compute':>10s}")
        for name, times in all_times.items():
            compute = sum(t for stage, t in times.items() if stage != "ingest")
            print(
                f"{name:6s}"
                + "".join(f"{times[s]:14.3f}" for s in stages)
                + f"{sum(times.values()):10.3f}{compute:10.3f}"
            )
        print("\nfeatures vs truth (median relative error, %; interiors)")
        print(f"{'item':6s}{'R0':>8s}{'n':>8s}{'R0 bias':>9s}{'n bias':>8s}{'pixels':>8s}")
        for name, feats in features.items():
            truth = xr.open_zarr(truth_dir / f"{name}.zarr").sel(y=feats.y, x=feats.x).compute()
            mask = interior(truth, camp.items[name])
            rel = {key: ((feats[key] - truth[key]) / truth[key]).where(mask) for key in ("R0", "n")}
            print(
                f"{name:6s}{100 * float(np.abs(rel['R0']).median()):8.2f}{100 * float(np.abs(rel['n']).median()):8.2f}"
                f"{100 * float(rel['R0'].median()):9.2f}{100 * float(rel['n'].median()):8.2f}{int(mask.sum()):8d}"
            )
        training = training_set(
            {n: (features[n], it.cls, it.roi) for n, it in camp.specimens.items()},
            max_per_class=CONFIG["classify"]["max_training_samples"],
        )
        for name, item in camp.scenes.items():
            labels = labels_stage(features[name], training, **parameters.label_parameters(CONFIG))
            truth_label, truth_classes = read_truth(item.truth, width=camp.camera.width, height=camp.camera.height)
            accuracy = {
                var: score(labels[var], truth_label, truth_classes, training.attrs["classes"])["accuracy"]
                for var in ("label", "label_filtered")
            }
            print(
                f"\nscene {name}: accuracy {accuracy['label']:.4f} before, "
                f"{accuracy['label_filtered']:.4f} after the label filter"
            )


if __name__ == "__main__":
    main()
