"""Scattering fit speed: surffin's kernel against what users have today, and the features stage per item.

Run by hand: ``python benchmarks/bench_scattering.py [--pixels 153600] [--repeat 5]
[--campaign DIR] [--calibration STORE] [--items S1 T1]``.
First table: pixel fits per second (median of repeats) for surffin (one thread, and
through dask with 2 threads), a scipy ``curve_fit`` loop and
``xarray.DataArray.curvefit`` on the same data, with ratios against surffin.
The references run on a sample of pixels and are extrapolated per pixel.
Second table: seconds per item (wall and CPU, median of repeats, dask's synchronous
scheduler) of :func:`~surffin.method.stages.features_stage` on numpy- and on
dask-backed inputs (as ``run_stage`` passes them for an item within one chunk and a
larger one) and of two of its parts on the item's registered views, the fit kernel and
the residual correlation, with their shares of the stage's CPU time (on a shared machine
the wall times swing with the load, the CPU times much less). The inputs come from the
item's chain (``bench_chunks.run_chain``) on the campaign (default: the ``paper`` preset
rendered into a temporary folder) with the calibration store (default: fitted first, ~1 min).
"""

from __future__ import annotations

import argparse
import tempfile
import time
import warnings
from pathlib import Path

import dask
import numpy as np
import xarray as xr
from _paper import paper_campaign  # benchmarks/_paper.py: this folder is on sys.path when run as a script
from bench_chunks import CONFIG, chain_parameters, quiet_logs, run_chain
from scipy.optimize import curve_fit

from surffin.io.store import open_store
from surffin.method.features import DEFAULT_SIZE, residual_correlation
from surffin.method.scattering import fit_scattering, fit_scattering_arrays, scattering_model
from surffin.method.stages import ITEM_CHAIN, features_stage
from surffin.pipeline import parameters
from surffin.pipeline.run import run_calibration


def data(npix, nview=5, seed=0):
    """Pixels with 5 views over 0-40 deg AOI, plaster-like truth and 2 % noise."""
    rng = np.random.default_rng(seed)
    theta = np.abs(np.deg2rad(np.linspace(0, 40, nview)) + rng.normal(0, np.deg2rad(2), (npix, nview)))
    r0 = rng.uniform(0.75, 0.95, npix)[:, None]
    n = rng.uniform(0.9, 1.3, npix)[:, None]
    return scattering_model(theta, r0, n) + rng.normal(0, 0.02, (npix, nview)), theta


def median_time(func, repeat):
    """Return the median seconds of ``repeat`` calls of ``func``."""
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        func()
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def timed(func):
    """Call ``func``; return its wall and CPU seconds."""
    wall, cpu = time.perf_counter(), time.process_time()
    func()
    return time.perf_counter() - wall, time.process_time() - cpu


def model(theta, r0, n):
    """Evaluate R0 cos((2 - 1/n) theta)^n: the scattering model as the references fit it."""
    return r0 * np.cos((2 - 1 / n) * theta) ** n


def scipy_loop(r, theta):
    """Fit every pixel by its own scipy ``curve_fit`` call, skipping the fits that fail."""
    for ri, ti in zip(r, theta):
        try:
            curve_fit(model, ti, ri, p0=(ri.max(), 1.0))
        except RuntimeError:
            pass


def as_cube(a, side):
    """Reshape (pixel, view) data into a (view, y, x) DataArray of ``side`` rows."""
    npix, nview = a.shape
    return xr.DataArray(a.T.reshape(nview, side, npix // side), dims=("view", "y", "x"))


def main():
    """Parse the command line, time every method on the same data and print the rates."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pixels", type=int, default=320 * 480)
    parser.add_argument("--sample", type=int, default=2000, help="pixels fitted by the slow references")
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--campaign", type=Path, help="a rendered paper campaign (default: render one)")
    parser.add_argument("--calibration", type=Path, help="its calibration store (default: fit one)")
    parser.add_argument("--items", nargs="+", default=["S1", "T1"], help="items whose features stage is timed")
    args = parser.parse_args()
    r, theta = data(args.pixels)
    rows = []

    t = median_time(lambda: fit_scattering_arrays(r, theta), args.repeat)
    rows.append(("surffin kernel, 1 thread", args.pixels, t))
    side = 320
    rc = as_cube(r, side).chunk({"view": -1, "y": 80, "x": -1})
    tc = as_cube(theta, side).chunk({"view": -1, "y": 80, "x": -1})
    with dask.config.set(scheduler="threads", num_workers=2):
        t = median_time(lambda: fit_scattering(rc, tc).compute(), args.repeat)
    rows.append(("surffin fit_scattering, dask 2 threads", args.pixels, t))

    rs, ts = r[: args.sample], theta[: args.sample]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t = median_time(lambda: scipy_loop(rs, ts), max(1, args.repeat // 2))
        rows.append(("scipy curve_fit loop", args.sample, t))
        side = 40
        rcube = as_cube(rs[: side * (args.sample // side)], side).chunk({"view": -1, "y": 10})
        tcube = as_cube(ts[: side * (args.sample // side)], side).chunk({"view": -1, "y": 10})
        with dask.config.set(scheduler="threads", num_workers=2):
            t = median_time(
                lambda: rcube.curvefit(tcube, model, reduce_dims="view", p0={"r0": 0.8, "n": 1.0}).compute(),
                max(1, args.repeat // 2),
            )
        rows.append(("xarray curvefit, dask 2 threads", rcube.size // rcube.sizes["view"], t))

    reference = rows[0][1] / rows[0][2]
    print(f"{'method':42s} {'pixels':>8s} {'median s':>9s} {'fits/s':>12s} {'surffin 1-thread / this':>24s}")
    for name, npix, seconds in rows:
        rate = npix / seconds
        print(f"{name:42s} {npix:8d} {seconds:9.3f} {rate:12,.0f} {reference / rate:24.1f}")
    print()
    stage_table(args)


def stage_table(args):
    """Time the features stage and the fit kernel on each item's registered views; print their table."""
    quiet_logs()
    step = next(step for step in ITEM_CHAIN if step.function is features_stage)
    with paper_campaign(args.campaign) as (camp, _), tempfile.TemporaryDirectory() as tmp:
        calibration = args.calibration or run_calibration(
            camp.path, Path(tmp, "calibration.zarr"), params=parameters.calibration_parameters(CONFIG)
        )
        print(f"features stage per item, dask synchronous scheduler, median of {args.repeat}")
        print(f"{'item':6s} {'what':28s} {'wall s':>8s} {'CPU s':>8s} {'share of stage (CPU)':>21s}")
        for name in args.items:
            stores, _ = run_chain(camp, name, tmp, calibration, scheduler="synchronous")
            params = chain_parameters(CONFIG, camp.items[name])
            params = {key: params[key] for key in step.keywords if key in params}
            lazy = {key: open_store(stores[key]) for key in step.inputs}
            loaded = {key: ds.load() for key, ds in lazy.items()}
            registered = loaded["registered"]
            views = [registered[key].transpose("y", "x", "view").values for key in ("reflectance", "aoi")]
            fit = fit_scattering(registered["reflectance"], registered["aoi"])
            runs = {
                "stage, numpy-backed inputs": lambda: features_stage(**loaded, **params).compute(),
                "stage, dask-backed inputs": lambda: features_stage(**lazy, **params).compute(),
                "fit kernel": lambda: fit_scattering_arrays(*views),
                "residual correlation": lambda: residual_correlation(
                    registered["reflectance"], registered["aoi"], fit, max_lag=params.get("size", DEFAULT_SIZE) - 1
                ),
            }
            times = {what: [] for what in runs}
            with dask.config.set(scheduler="synchronous"):
                for what, func in runs.items():  # warm-up, not counted
                    func()
                for _ in range(args.repeat):  # interleaved, so that the machine's load falls on all alike
                    for what, func in runs.items():
                        times[what].append(timed(func))
            stage_cpu = np.median([cpu for _, cpu in times["stage, numpy-backed inputs"]])
            for what, values in times.items():
                wall, cpu = np.median(values, axis=0)
                print(f"{name:6s} {what:28s} {wall:8.3f} {cpu:8.3f} {cpu / stage_cpu:21.2f}")


if __name__ == "__main__":
    main()
