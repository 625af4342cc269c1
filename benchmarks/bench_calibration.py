"""Speed and accuracy of the radiometric calibration (surffin.method.calibration) on the paper campaign.

Run by hand: ``python benchmarks/bench_calibration.py [--campaign DIR] [--views N] [--repeat N]
[--against OLD.py]``.

The campaign: ``--campaign`` (a rendered ``paper`` preset with its truth beside it in
``<DIR>-truth``), by default ``/tmp/clone/data/raw`` when it exists, else the paper preset
rendered by ``surffin.simulate_campaign`` into a temporary directory.

Table 1, time of a calibration fit of ``--views`` wall views over the full 640x480 sensor,
per stage: view reading, AOI (``surffin.method.geometry``), accumulation of the sufficient
statistics, and the fit; the per-view stages are medians over views and repeats times the
number of views, the fit a median over repeats. Then ``calibrate`` end to end (all wall
views but the held-out one, the reference panel, provenance checksums), with its residual
correction (the default: the wall views are read twice) and without. As a reference in the
same process: ``scipy.optimize.least_squares`` per pixel on the raw observations of a sample
of pixels, extrapolated to the sensor, and the ratio; and how far the two fits differ.

Table 2, the paper's figures beside surffin's on this campaign (paper section 3.3, Table 2):
mean R^2, per-parameter variability across the image, the C-D correlation; also for the
truth in the same gauge E = 1 (the paper's gauge is not stated, so its E variability has no
counterpart). Then the accuracy against the truth: k, and the reflectance of a held-out wall
view (not in the fit, through the calibration's residual correction) against rho_wall cos(theta)
with theta from the view's pose, and the AOI error of that view (the estimated AOI enters the
fit and the reflectance).

With ``--against OLD.py`` (a copy of an earlier ``surffin/method/calibration.py``), only this:
the CPU time of ``calibrate`` on the campaign (all its wall views) and of its parts
``fit_calibration`` and ``fit_correction``, medians of ``--repeat`` runs of each version
alternately in this process, their ratios, and how far the two calibrations differ.
"""

from __future__ import annotations

import argparse
import importlib.util
import tempfile
import time
from pathlib import Path

import numpy as np
import xarray as xr
from scipy.optimize import least_squares

import surffin
import surffin.method.calibration
from surffin.method.calibration import (
    TERMS,
    WallStatistics,
    calibrate,
    calibration_diagnostics,
    fit_calibration,
    instrument_function,
    reflectance,
)
from surffin.method.geometry import DEFAULT_WINDOW, frame_angle_of_incidence
from surffin.paper import CORRELATION, MEAN_R2, VARIABILITY_PERCENT

DEFAULT_CAMPAIGN = Path("/tmp/clone/data/raw")
HELD_OUT = "w050"


def campaign_dir(path: Path | None) -> Path:
    """Return ``path``, else :data:`DEFAULT_CAMPAIGN` if it holds a campaign, else a newly rendered ``paper`` preset."""
    if path is not None:
        return path
    if (DEFAULT_CAMPAIGN / "campaign.yaml").is_file():
        return DEFAULT_CAMPAIGN
    target = Path(tempfile.mkdtemp(prefix="surffin-bench-")) / "campaign"
    print(f"rendering the paper preset into {target} ...")
    surffin.simulate_campaign(target, preset="paper")
    return target


def true_aoi(view) -> np.ndarray:
    """AOI (H, W) of a wall view from its pose: the wall is the world plane Z = 0."""
    normal = view.pose[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    rays = view.xyz / np.linalg.norm(view.xyz, axis=-1, keepdims=True)
    return np.arccos(np.minimum(np.abs(rays @ normal), 1.0))


def timed(function, *args):
    """Call ``function(*args)``; return its result and the seconds it took."""
    start = time.perf_counter()
    out = function(*args)
    return out, time.perf_counter() - start


def stage_times(camp, paths, repeat, sample):
    """Median seconds per view of reading, AOI and accumulation; the statistics; the sample's raw data.

    Returns
    -------
    t_read, t_aoi, t_add : float
    stats : WallStatistics
        Of the last run.
    raw : (4, view, sample) ndarray
        Intensity, distance, AOI and validity of the sample pixels in every view.
    """
    reads, aois, adds, raw = [], [], [], []
    for run in range(repeat):
        stats = WallStatistics((camp.camera.height, camp.camera.width))
        for path in paths:
            view, t_read = timed(camp.read_view, path)
            (aoi, distance), t_aoi = timed(frame_angle_of_incidence, view.xyz, DEFAULT_WINDOW)
            _, t_add = timed(stats.add, view.intensity, distance, aoi, view.valid)
            reads.append(t_read)
            aois.append(t_aoi)
            adds.append(t_add)
            if run == 0:
                raw.append(np.stack([view.intensity[sample], distance[sample], aoi[sample], view.valid[sample]]))
    return np.median(reads), np.median(aois), np.median(adds), stats, np.stack(raw, axis=1)


def scipy_reference(raw: np.ndarray, start) -> tuple[np.ndarray, float]:
    """least_squares per sample pixel on its raw observations; coefficients (4, n) and seconds per pixel."""
    intensity, distance, aoi, valid = raw
    out = np.full((4, intensity.shape[1]), np.nan)
    begin = time.perf_counter()
    for k in range(intensity.shape[1]):
        use = (valid[:, k] > 0) & np.isfinite(aoi[:, k]) & np.isfinite(distance[:, k])
        d, theta = distance[use, k], aoi[use, k]
        target = intensity[use, k] / np.cos(theta)

        def residual(p, d=d, theta=theta, target=target):
            return instrument_function(np.append(p, 1.0), d, theta) - target

        out[:, k] = least_squares(residual, start, method="lm", x_scale="jac").x
    return out, (time.perf_counter() - begin) / intensity.shape[1]


def cpu_parts(module, camp) -> tuple[dict[str, float], xr.Dataset]:
    """CPU seconds of ``module.calibrate(camp)`` and of its calls of its parts; the calibration.

    ``module`` is a version of :mod:`surffin.method.calibration`; its ``fit_calibration`` and
    ``fit_correction`` are wrapped for the run to add up their CPU time.
    """
    parts = ("fit_calibration", "fit_correction")
    seconds = dict.fromkeys(parts, 0.0)
    originals = {name: getattr(module, name) for name in parts}

    def clocked(name):
        def call(*args, **kwargs):
            start = time.process_time()
            try:
                return originals[name](*args, **kwargs)
            finally:
                seconds[name] += time.process_time() - start

        return call

    try:
        for name in parts:
            setattr(module, name, clocked(name))
        start = time.process_time()
        ds = module.calibrate(camp)
        seconds = {"calibrate": time.process_time() - start, **seconds}
    finally:
        for name, function in originals.items():
            setattr(module, name, function)
    return seconds, ds


def compare_versions(camp, old_path: Path, repeat: int) -> None:
    """Print the CPU time of ``calibrate`` and its parts, this version against ``old_path``, and the differences."""
    spec = importlib.util.spec_from_file_location("surffin_calibration_old", old_path)
    old = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(old)
    times = {"old": [], "new": []}
    results = {}
    for _ in range(repeat):
        for label, module in (("old", old), ("new", surffin.method.calibration)):
            seconds, results[label] = cpu_parts(module, camp)
            times[label].append(seconds)
    median = {label: {key: np.median([run[key] for run in runs]) for key in runs[0]} for label, runs in times.items()}
    print(f"\ncampaign {camp.path}: {len(camp.calibration.wall)} wall views, CPU s, medians of {repeat} runs\n")
    row("part", "old s", "new s", "old / new")
    for name, before in median["old"].items():
        after = median["new"][name]
        row(name, f"{before:.2f}", f"{after:.2f}", f"{before / after:.2f}x")
    before, after = results["old"], results["new"]
    fitted = before.status.values == 0
    print()
    row("status codes equal", "", "", str(bool(np.array_equal(before.status.values, after.status.values))))
    print("max relative difference, new against old:")
    for name, a, b in (
        ("coef (converged pixels)", before.coef.values[:, fitted], after.coef.values[:, fitted]),
        ("r2", before.r2.values, after.r2.values),
        ("correction", before.correction.values, after.correction.values),
        ("noise_variance", before.noise_variance.values, after.noise_variance.values),
        ("scale_k", before.attrs["scale_k"], after.attrs["scale_k"]),
    ):
        with np.errstate(invalid="ignore", divide="ignore"):
            relative = np.abs(np.asarray(b) / np.asarray(a) - 1.0)
        row(f"  {name}", "", "", f"{np.nanmax(relative):.1e}")


def row(label, *cells, width=14):
    """Print one table row: ``label``, then the cells right-aligned in columns of ``width``."""
    print(f"{label:<44}" + "".join(f"{cell:>{width}}" for cell in cells))


def held_out_reflectance(camp, ds, rho_wall):
    """Return the errors of the calibrated reflectance and of the AOI on the held-out wall view.

    Parameters
    ----------
    camp : Campaign
    ds : Dataset
        A calibration store (``coef``, ``scale_k``) fitted without the held-out view.
    rho_wall : float
        The wall's true reflectance.

    Returns
    -------
    error : ndarray
        ``R / (rho_wall cos(theta)) - 1`` over the finite pixels, theta the true AOI (from the view's pose).
    aoi_error : ndarray
        Estimated minus true AOI, degrees, over the finite pixels.
    """
    (path,) = [path for path in camp.calibration.wall if path.stem == HELD_OUT]
    view = camp.read_view(path)
    aoi, distance = frame_angle_of_incidence(view.xyz, DEFAULT_WINDOW)
    dims = ("view", "y", "x")
    coords = {"view": [HELD_OUT], "y": np.arange(camp.camera.height), "x": np.arange(camp.camera.width)}

    def cube(array):
        return xr.DataArray(array[None], dims=dims, coords=coords)

    intensity = np.where(view.valid, view.intensity, np.nan)
    R = reflectance(
        cube(intensity), cube(distance), cube(aoi), ds.coef, ds.attrs["scale_k"], ds.get("correction")
    ).values[0]
    truth = true_aoi(view)
    error = R / (rho_wall * np.cos(truth)) - 1.0
    aoi_error = np.rad2deg(aoi - truth)
    return error[np.isfinite(error)], aoi_error[np.isfinite(aoi_error)]


def main() -> None:
    """Parse the command line, time and check the calibration, and print the tables."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--campaign", type=Path, default=None)
    parser.add_argument("--views", type=int, default=100)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--sample", type=int, default=300, help="pixels fitted by scipy least_squares")
    parser.add_argument("--against", type=Path, default=None, help="an earlier calibration.py to time against")
    args = parser.parse_args()

    directory = campaign_dir(args.campaign)
    camp = surffin.read_campaign(directory)
    if args.against is not None:
        compare_versions(camp, args.against, args.repeat)
        return
    truth = xr.open_zarr(directory.with_name(directory.name + "-truth") / "instrument.zarr").compute()
    height, width = camp.camera.height, camp.camera.width
    paths = [path for path in camp.calibration.wall if path.stem != HELD_OUT][: args.views]
    rng = np.random.default_rng(0)
    sample = tuple(rng.integers(0, n, args.sample) for n in (height, width))

    t_read, t_aoi, t_add, stats, raw = stage_times(camp, paths, args.repeat, sample)
    fits = [timed(fit_calibration, stats) for _ in range(args.repeat)]
    ds_fit, t_fit = fits[-1][0], float(np.median([t for _, t in fits]))
    ends = [timed(lambda: calibrate(camp, exclude=[HELD_OUT])) for _ in range(args.repeat)]
    ds, t_end = ends[-1][0], float(np.median([t for _, t in ends]))
    plain = [timed(lambda: calibrate(camp, exclude=[HELD_OUT], residual_correction=False)) for _ in range(args.repeat)]
    t_plain = float(np.median([t for _, t in plain]))
    typical = np.nanmedian(ds_fit.coef.values[:4].reshape(4, -1), axis=1)
    reference, per_pixel = scipy_reference(raw, typical)
    ours = ds_fit.coef.values[:4][(slice(None), *sample)]
    n_views, n_pixels = len(paths), height * width

    print(f"\ncampaign {directory}: {len(camp.calibration.wall)} wall views, sensor {width}x{height}")
    print(f"Table 1: calibration fit of {n_views} wall views, {n_pixels} pixels, medians of {args.repeat} runs\n")
    row("stage", "per view ms", "total s")
    row("read view files", f"{1e3 * t_read:.1f}", f"{n_views * t_read:.2f}")
    row("AOI and distance (surffin.method.geometry)", f"{1e3 * t_aoi:.1f}", f"{n_views * t_aoi:.2f}")
    row("accumulate sufficient statistics", f"{1e3 * t_add:.1f}", f"{n_views * t_add:.2f}")
    row("fit (all pixels)", "", f"{t_fit:.2f}")
    total = n_views * (t_read + t_aoi + t_add) + t_fit
    row("sum (target <= 10 s)", "", f"{total:.2f}")
    row(f"calibrate() end to end ({len(camp.calibration.wall) - 1} wall + reference)", "", f"{t_end:.2f}")
    row("calibrate(residual_correction=False) end to end", "", f"{t_plain:.2f}")
    scipy_total = per_pixel * n_pixels
    print()
    row("fit rate", "pixels/s", "sensor s")
    row("surffin fit_calibration", f"{n_pixels / t_fit:,.0f}", f"{t_fit:.2f}")
    row(f"scipy least_squares loop ({args.sample} px, extrapolated)", f"{1 / per_pixel:,.0f}", f"{scipy_total:.0f}")
    row("ratio", "", f"{scipy_total / t_fit:.0f}x")
    f_ours = instrument_function(np.vstack([ours, np.ones((1, ours.shape[1]))]), raw[1], raw[2])
    f_ref = instrument_function(np.vstack([reference, np.ones((1, ours.shape[1]))]), raw[1], raw[2])
    ok = np.isfinite(f_ours / f_ref)
    row("max |f_surffin / f_scipy - 1| on the sample", "", f"{np.max(np.abs(f_ours / f_ref - 1)[ok]):.1e}")

    diagnostics = calibration_diagnostics(ds)
    everywhere = np.zeros((height, width), dtype=np.int8)
    truth_diag = calibration_diagnostics(
        xr.Dataset({"coef": truth.coef, "r2": (("y", "x"), everywhere + 1.0), "status": (("y", "x"), everywhere)})
    )
    cd = diagnostics["correlation_terms"].index("C"), diagnostics["correlation_terms"].index("D")
    truth_cd = truth_diag["correlation_terms"].index("C"), truth_diag["correlation_terms"].index("D")
    print("\nTable 2: calibration diagnostics (surffin fit, all wall views but the held-out one)\n")
    row("quantity", "paper", "surffin", "truth (E=1)")
    row("mean R^2", f"{MEAN_R2:.2f}", f"{diagnostics['mean_r2']:.4f}", "")
    for term in TERMS:
        row(
            f"variability {term} (std/|mean|, %)",
            f"{VARIABILITY_PERCENT[term]:.2f}",
            f"{diagnostics['variability_percent'][term]:.2f}",
            f"{truth_diag['variability_percent'][term]:.2f}",
        )
    row(
        "correlation C-D across pixels",
        f"{CORRELATION['matrix'][TERMS.index('C')][TERMS.index('D')]:.2f}",
        f"{diagnostics['correlation'][cd[0]][cd[1]]:.3f}",
        f"{truth_diag['correlation'][truth_cd[0]][truth_cd[1]]:.3f}",
    )
    row("pixels fitted", "", f"{diagnostics['n_fitted']}/{diagnostics['n_pixels']}")
    fitted = ds.status.values == 0
    relative = (ds.coef.values - truth.coef.values) / np.abs(truth.coef.values)
    for k, term in enumerate(TERMS[:4]):
        row(f"coefficient {term}: median |relative error|", "", f"{np.median(np.abs(relative[k][fitted])):.3f}")
        row(f"coefficient {term}: median relative error", "", f"{np.median(relative[k][fitted]):+.3f}")

    error, aoi_error = held_out_reflectance(camp, ds, truth.attrs["rho_wall"])
    print("\naccuracy against the truth\n")
    row("scale_k (truth)", "", f"{ds.attrs['scale_k']:.5f}", f"{truth.attrs['scale_k']:.5f}")
    row("scale_k relative error", "", f"{ds.attrs['scale_k'] / truth.attrs['scale_k'] - 1:+.2e}")
    row("reference ratio spread (1.4826 MAD / r)", "", f"{ds.attrs['reference']['relative_spread']:.4f}")
    row(f"held-out {HELD_OUT}: median |R / (rho cos) - 1|", "", f"{np.median(np.abs(error)):.4f}")
    row(f"held-out {HELD_OUT}: median R / (rho cos) - 1", "", f"{np.median(error):+.4f}")
    row(f"held-out {HELD_OUT}: 95th pct |R / (rho cos) - 1|", "", f"{np.percentile(np.abs(error), 95):.4f}")
    row(f"held-out {HELD_OUT}: median AOI error (deg)", "", f"{np.median(aoi_error):+.3f}")


if __name__ == "__main__":
    main()
