"""One item from view files to features: time per stage, and accuracy against the truth.

Run by hand: ``python benchmarks/bench_item.py [--campaign DIR] [--repeat 5]``.
Without ``--campaign`` it renders the ``paper`` preset into a temporary folder.
The calibration is fitted once (its cost is per camera, not per item; see
``bench_calibration.py``). Prints, per stage, the median wall time over repeats
in this process (the machine is shared: compare stages, not absolute times),
and, per item, the median relative error of R0 and n against the simulator's
truth on the specimen interiors (roi pixels; the scene's labelled pixels) and
the scene's accuracy before and after the label filter.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import dask
import numpy as np
import xarray as xr

from surffin.method.calibration import calibrate
from surffin.io.campaign import read_truth
from surffin.method.classify import score, training_set
from surffin.io.ingest import ingest_item
from surffin.method.stages import aoi_stage, features_stage, labels_stage, reflectance_stage, registration_stage

from _paper import paper_campaign  # benchmarks/_paper.py: this folder is on sys.path when run as a script


def timed(func, repeat):
    times, result = [], None
    for _ in range(repeat):
        start = time.perf_counter()
        result = func()
        times.append(time.perf_counter() - start)
    return result, float(np.median(times))


def chain(camp, name, calibration, repeat):
    """Run the stages of one item, each timed; returns features and stage times."""
    item = camp.items[name]
    times = {}
    ingest, times["read views (ingest)"] = timed(lambda: ingest_item(camp, name), repeat)
    aoi, times["aoi"] = timed(lambda: aoi_stage(ingest).compute(), repeat)
    refl, times["reflectance"] = timed(lambda: reflectance_stage(ingest, aoi, calibration).compute(), repeat)
    registered, times["registration"] = timed(lambda: registration_stage(ingest, aoi, refl, roi=item.roi), repeat)
    feats, times["fit + features"] = timed(lambda: features_stage(registered, refl, aoi, roi=item.roi).compute(), repeat)
    return feats, times


def interior(truth: xr.Dataset, item) -> xr.DataArray:
    mask = truth["label"] >= 0
    if item.roi is not None:
        in_roi = (truth.y >= item.roi.y[0]) & (truth.y < item.roi.y[1]) & (truth.x >= item.roi.x[0]) & (truth.x < item.roi.x[1])
        mask = mask & in_roi
    return mask


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--campaign", type=Path, help="a rendered paper campaign (truth in <campaign>-truth)")
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    with paper_campaign(args.campaign) as (camp, truth_dir):
        with dask.config.set(scheduler="threads", num_workers=2):
            start = time.perf_counter()
            calibration = calibrate(camp)
            print(f"calibration ({len(camp.calibration.wall)} wall views, full sensor): {time.perf_counter() - start:.2f} s\n")
            features, all_times = {}, {}
            for name in camp.items:
                features[name], all_times[name] = chain(camp, name, calibration, args.repeat)
        stages = list(next(iter(all_times.values())))
        print("median seconds per stage, per item (5 views, 320x480 crop)")
        print(f"{'item':6s}" + "".join(f"{stage:>22s}" for stage in stages) + f"{'total':>10s}{'compute':>10s}")
        for name, times in all_times.items():
            compute = sum(t for stage, t in times.items() if stage != "read views (ingest)")
            print(f"{name:6s}" + "".join(f"{times[s]:22.3f}" for s in stages) + f"{sum(times.values()):10.3f}{compute:10.3f}")
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
        training = training_set({n: (features[n], it.cls, it.roi) for n, it in camp.specimens.items()})
        for name, item in camp.scenes.items():
            labels = labels_stage(features[name], training)
            truth_label, truth_classes = read_truth(item.truth, width=camp.camera.width, height=camp.camera.height)
            accuracy = {
                var: score(labels[var], truth_label, truth_classes, training.attrs["classes"])["accuracy"]
                for var in ("label", "label_filtered")
            }
            print(f"\nscene {name}: accuracy {accuracy['label']:.4f} before, {accuracy['label_filtered']:.4f} after the label filter")


if __name__ == "__main__":
    main()
