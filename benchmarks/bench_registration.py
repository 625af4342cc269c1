"""Accuracy and speed of co-registration (surffin.method.registration) on a synthetic paper campaign.

Run by hand: ``python benchmarks/bench_registration.py [--campaign DIR] [--truth DIR]``. Without ``--campaign`` it
renders the ``paper`` preset (seed 0) into a temporary folder. The error of a map is measured against the
simulator's truth (``<campaign>-truth/<item>.zarr``, ``u_ref``/``v_ref``) with
:func:`surffin.method.registration.registration_error`: for each reference pixel, the distance in the reference
image between the pixel and the true position of the point its map sends it to.

Table 1, per item and method: median error (pixels) per non-reference view over all mapped pixels, and over the
specimen top faces (truth ``label`` >= 0: the surface that is classified), the mapped share of the reference grid,
and the time of :func:`registration_maps`. Methods: ``poses`` (default: the reference range averaged over 9 x 9
pixels of one surface), ``poses raw`` (``smooth=1``: the error the 0.9 mm depth noise of the reference point
induces), ``homography`` (SIFT, the whole image) and, for specimens, ``homography roi`` (reference keypoints on the
campaign's specimen roi only).

Table 2, the keypoint detectors of the homography method on every item: keypoints per view, matches after the ratio
test and homography inliers (means over non-reference views), inlier reprojection rms, median error (all mapped
pixels / specimen tops) and time per item. Detectors the installed OpenCV lacks are listed as such (OpenCV 5 moved
AKAZE to opencv-contrib; to measure it, put opencv-contrib-python-headless first on PYTHONPATH).

Table 3, runtime per item: maps by each method and :func:`register` of two (view, y, x) float32 images (stand-ins
for reflectance and AOI). Table 4, the poses method's ``smooth`` window (the default is chosen on it): median and
99th percentile of the error over all items and non-reference views. A wider window averages more depth noise away
(the median falls) but bends the range near depth steps (the tail grows).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import xarray as xr

from surffin.errors import RegistrationError
from surffin.io.campaign import read_campaign
from surffin.io.ingest import ingest_item
from surffin.method.registration import DETECTORS, register, registration_error, registration_maps
from surffin.simulate import simulate_campaign

ALL_DETECTORS = ("sift", "orb", "akaze")


def load(campaign: Path, truth: Path):
    """(item, ingest cube, truth Dataset, roi or None) for every specimen and scene."""
    camp = read_campaign(campaign, require_calibration=False)
    for name, item in camp.items.items():
        ingest = ingest_item(camp, name).load()
        reference = xr.open_zarr(truth / f"{name}.zarr")[["u_ref", "v_ref", "label"]].load()
        roi = {"y": list(item.roi.y), "x": list(item.roi.x)} if item.roi is not None else None
        yield name, ingest, reference, roi


def timed_maps(ingest, **kwargs):
    """Return (maps, seconds) of :func:`registration_maps`, or (the RegistrationError, seconds) when it fails."""
    start = time.perf_counter()
    try:
        maps = registration_maps(ingest, **kwargs)
    except RegistrationError as error:
        return error, time.perf_counter() - start
    return maps, time.perf_counter() - start


def errors(maps, truth):
    """Return the registration error of a map's non-reference views against the truth.

    Returns
    -------
    whole, top : (view,) ndarray
        Median error per non-reference view over all mapped pixels and over specimen tops.
    error : DataArray (view, y, x)
        The error of those views.
    on_top : DataArray (y, x)
        The specimen-top mask.
    """
    error = registration_error(maps, truth["u_ref"], truth["v_ref"]).isel(view=slice(1, None))
    top = truth["label"].sel(y=maps["y"], x=maps["x"]) >= 0
    return error.median(("y", "x")).values, error.where(top).median(("y", "x")).values, error, top


def fmt(values) -> str:
    """Join the values with ``/``, two decimals each."""
    return "/".join(f"{value:.2f}" for value in values)


def accuracy_table(items) -> None:
    """Print Table 1: each item's error, mapped share and time per method, then the pooled medians."""
    print("Table 1: median registration error per non-reference view (pixels), paper preset")
    print(f"{'item':5} {'method':15} {'all mapped pixels':>26} {'specimen tops':>26} {'mapped':>7} {'time s':>7}")
    pooled = {}
    for name, ingest, truth, roi in items:
        runs = {
            "poses": {"method": "poses"},
            "poses raw": {"method": "poses", "smooth": 1},
            "homography": {"method": "homography"},
        }
        if roi is not None:
            runs["homography roi"] = {"method": "homography", "roi": roi}
        for label, kwargs in runs.items():
            maps, seconds = timed_maps(ingest, **kwargs)
            if isinstance(maps, RegistrationError):
                print(f"{name:5} {label:15} failed: {str(maps)[:90]}")
                continue
            whole, top, error, on_top = errors(maps, truth)
            mapped = float(np.isfinite(maps["map_x"].isel(view=slice(1, None))).mean())
            pooled.setdefault(label, []).append((error.values, np.broadcast_to(on_top.values, error.shape)))
            print(f"{name:5} {label:15} {fmt(whole):>26} {fmt(top):>26} {mapped:7.3f} {seconds:7.2f}")
    print("pooled median over the items and views it registered (all mapped pixels / specimen tops):")
    for label, chunks in pooled.items():
        error = np.concatenate([values.ravel() for values, _ in chunks])
        top = np.concatenate([mask.ravel() for _, mask in chunks])
        print(f"  {label:15} {np.nanmedian(error):.3f} / {np.nanmedian(error[top]):.3f} px")


DETECTOR_COLUMNS = {  # statistic: (header, format)
    "keypoints": ("keypoints", "9.0f"),
    "matches": ("matches", "8.0f"),
    "inliers": ("inliers", "8.0f"),
    "rms": ("rms px", "7.2f"),
    "all": ("median err all", "15.2f"),
    "tops": ("tops", "7.2f"),
    "seconds": ("time s", "7.2f"),
}


def detector_row(detector: str, name: str, stats: dict) -> str:
    """Format one row of Table 2: a detector's statistics (:data:`DETECTOR_COLUMNS`) on one item."""
    cells = (f"{stats[key]:{spec}}" for key, (_, spec) in DETECTOR_COLUMNS.items())
    return f"{detector:8} {name:5} " + " ".join(cells)


def detector_table(items) -> None:
    """Print Table 2: each keypoint detector of the homography method on every item, and its means."""
    print("\nTable 2: detectors of the homography method (means over the non-reference views)")
    header = (f"{title:>{spec.split('.')[0]}}" for title, spec in DETECTOR_COLUMNS.values())
    print(f"{'detector':8} {'item':5} " + " ".join(header))
    for detector in ALL_DETECTORS:
        if detector not in DETECTORS:
            print(f"{detector:8} not in this OpenCV ({', '.join(DETECTORS)} are)")
            continue
        rows = []
        for name, ingest, truth, _ in items:
            maps, seconds = timed_maps(ingest, method="homography", detector=detector)
            if isinstance(maps, RegistrationError):
                print(f"{detector:8} {name:5} failed: {str(maps)[:100]}")
                continue
            views = list(maps.attrs["diagnostics"].values())[1:]
            stats = {key: np.mean([view[key] for view in views]) for key in ("keypoints", "matches", "inliers", "rms")}
            whole, top, _, _ = errors(maps, truth)
            rows.append({**stats, "all": np.median(whole), "tops": np.median(top), "seconds": seconds})
            print(detector_row(detector, name, rows[-1]))
        if rows:
            print(detector_row(detector, "mean", {key: np.mean([row[key] for row in rows]) for key in rows[0]}))


def runtime_table(items, repeat: int) -> None:
    """Print Table 3: per item, the best of ``repeat`` times of the maps by each method and of :func:`register`."""
    print(f"\nTable 3: runtime per item (best of {repeat}), seconds")
    print(f"{'item':5} {'views':>5} {'grid':>9} {'maps poses':>10} {'maps homography':>15} {'register':>9}")
    for name, ingest, _, _ in items:
        best = {}
        for _ in range(repeat):
            for method in ("poses", "homography"):
                maps, seconds = timed_maps(ingest, method=method)
                best[method] = min(best.get(method, np.inf), seconds)
            ds = xr.Dataset({"reflectance": ingest["intensity"], "aoi": ingest["xyz"].sel(axis="z")})
            start = time.perf_counter()
            register(ds, maps)
            best["register"] = min(best.get("register", np.inf), time.perf_counter() - start)
        grid = f"{ingest.sizes['y']}x{ingest.sizes['x']}"
        print(
            f"{name:5} {ingest.sizes['view']:5} {grid:>9} {best['poses']:10.2f} {best['homography']:15.2f} "
            f"{best['register']:9.3f}"
        )


def smoothing_table(items, windows=(1, 3, 5, 7, 9, 11, 15)) -> None:
    """Print Table 4: the poses method's error and time per ``smooth`` window, over all items."""
    print("\nTable 4: poses method, reference range averaged over a window (all items, non-reference views)")
    print(f"{'smooth':>6} {'median px':>9} {'p99 px':>7} {'time s':>7}")
    for window in windows:
        chunks, seconds = [], 0.0
        for _, ingest, truth, _ in items:
            maps, elapsed = timed_maps(ingest, method="poses", smooth=window)
            _, _, error, _ = errors(maps, truth)
            chunks.append(error.values[np.isfinite(error.values)])
            seconds += elapsed
        error = np.concatenate(chunks)
        print(f"{window:6d} {np.median(error):9.3f} {np.percentile(error, 99):7.2f} {seconds / len(items):7.2f}")


def main() -> None:
    """Parse the command line, render a campaign unless one is given, and print the four tables."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--campaign", type=Path, help="a rendered paper campaign (default: render one)")
    parser.add_argument("--truth", type=Path, help="its truth folder (default: <campaign>-truth)")
    parser.add_argument("--repeat", type=int, default=3, help="timing repeats of table 3")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as scratch:
        campaign = args.campaign
        if campaign is None:
            campaign = Path(scratch) / "paper"
            simulate_campaign(campaign, preset="paper", seed=0)
        truth = args.truth or campaign.resolve().with_name(campaign.resolve().name + "-truth")
        items = list(load(campaign, truth))
        accuracy_table(items)
        detector_table(items)
        runtime_table(items, args.repeat)
        smoothing_table(items)


if __name__ == "__main__":
    main()
