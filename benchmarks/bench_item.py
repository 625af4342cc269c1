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
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import xarray as xr

# benchmarks/: this folder is on sys.path when run as a script
from _paper import paper_campaign
from bench_chunks import CONFIG, quiet_logs, run_chain

from surffin.io.campaign import read_truth
from surffin.io.store import open_store
from surffin.method.classify import score, training_set
from surffin.method.stages import labels_stage
from surffin.pipeline import parameters
from surffin.pipeline.run import run_calibration


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


def main():
    """Calibrate, run each item's chain, classify the scene and print the tables."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--campaign", type=Path, help="a rendered paper campaign (truth in <campaign>-truth)")
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--threads", type=int, default=2, help="dask threads of each stage")
    args = parser.parse_args()
    quiet_logs()
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
