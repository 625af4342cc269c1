"""Calibration diagnostics as the paper reports them (section 3.3, Table 2), and repeatability.

From a calibration store (:func:`surffin.method.calibration.calibrate`), over the campaign's crop, beside the
paper's numbers (:data:`surffin.paper.CALIBRATION`) and the truth's own (``<campaign>-truth/instrument.zarr``):

- fit quality: mean R^2 over the fitted pixels;
- each coefficient's variability across the image, in %: ``plain``, ``100 std / |mean|`` (the coefficient of
  variation: how the paper's "variability in % over the whole image" reads), and ``robust``,
  ``100 * 1.4826 MAD / |median|`` (the same for a normal distribution, but blind to the few poorly constrained
  pixels that inflate the plain one). The paper's gauge is not stated; E = 1 here and in the truth, so A..D carry E's;
- the coefficients' Pearson correlation across pixels: it mixes their true spatial patterns with the fits'
  estimation errors, which are strongly correlated between C and D (paper: C-D -0.99);
- the feature spread on the wall: R0, n fitted per sensor pixel over the calibrated wall views (the wall is
  uniform and Lambertian: one law per pixel), std and robust spread across pixels. Each wall set is analysed
  with each calibration; ``views_in_fit`` (from the store's checksums) counts the views it was fitted to: on
  those it has absorbed their noise (in-sample, as in the paper), so only other views give an honest spread.

Repeatability, against a calibration of a repeat acquisition: relative differences of the coefficients, of k, f
and k f over the observed (d, theta) range, and of the reflectance and R0, n of the wall views and specimens
(:func:`process_specimens`); the truth is compared the same way. A relative difference is
``(a - b) / ((a + b) / 2)`` in %, but ``(a - b) / |mean|`` with the image mean for the coefficients (C and D
come near zero where their noise is large). The paper does not say which statistic its numbers are: each is
summarised by median |.| (headline), mean (systematic part), std and 95th percentile of |.|.
:func:`calibration_report` gathers it all, :mod:`surffin.report.diagnostics` draws it, and
:func:`surffin.pipeline.analyses.run_calibration_diagnostics` is the workflow's job.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import xarray as xr

from surffin.errors import StoreError
from surffin.grid import Roi
from surffin.io.files import write_text
from surffin.method.calibration import (
    TERMS,
    calibration_diagnostics,
    correction_factor,
    instrument_function,
    observe_view,
    with_reflectance,
)
from surffin.method.scattering import DEFAULT_MIN_SPREAD, fit_scattering_arrays
from surffin.paper import CALIBRATION as PAPER_CALIBRATION

if TYPE_CHECKING:
    from surffin.io.campaign import Campaign

__all__ = [
    "variability",
    "spread",
    "relative_difference",
    "coefficients",
    "coefficient_statistics",
    "observed_grid",
    "compare_calibrations",
    "wall_features",
    "SPECIMEN_STORES",
    "process_specimens",
    "representative_specimens",
    "CalibrationReport",
    "calibration_report",
    "write_report",
]

log = logging.getLogger("surffin")

# Scale factor of the median absolute deviation to a normal standard deviation.
_MAD_SIGMA = 1.4826
# Percentiles of the wall observations' distance and AOI that bound the (d, theta) grid, and its size.
_GRID_PERCENTILES = (1, 99)
_GRID_SIZE = 7
# Pixels whose instrument functions on the grid are compared at a time (a few MB of temporaries).
_GRID_BLOCK = 4096
# What multiplies eq. 5's f in a calibration (its residual correction) or an instrument truth (its systematics).
_FACTORS = ("correction", "systematic")
# Variables of the specimens compared between calibrations.
_SPECIMEN_VARIABLES = ("reflectance", "R0", "n", "R0_fit", "n_fit")
#: The stores of a specimen that :func:`process_specimens` reads, by name: the stage that writes each.
SPECIMEN_STORES = {"ingest": "ingest", "aoi": "aoi", "registered": "registration", "features": "features"}


def _plain(value):
    """``value`` with numpy types as Python ones and non-finite floats as None (strict JSON)."""
    if isinstance(value, Mapping):
        return {str(key): _plain(item) for key, item in value.items()}
    if isinstance(value, list | tuple | np.ndarray):
        return [_plain(item) for item in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def _format(value: float | None) -> str:
    """Format a number for the log (``n/a`` for None)."""
    return "n/a" if value is None else f"{value:.4g}"


def _robust_std(values: np.ndarray, axis=None) -> np.ndarray:
    """1.4826 times the median absolute deviation (a normal standard deviation), NaN-aware."""
    median = np.nanmedian(values, axis=axis, keepdims=True)
    return _MAD_SIGMA * np.nanmedian(np.abs(values - median), axis=axis)


def variability(values) -> dict[str, np.ndarray]:
    """Relative spread in % of each row of ``values``, ignoring NaN.

    Parameters
    ----------
    values : (k, n) array_like
        k quantities (e.g. the coefficients A..E) over n pixels.

    Returns
    -------
    dict
        ``plain``: ``100 std / |mean|``; ``robust``: ``100 * 1.4826 MAD /
        |median|``; each (k,) ndarray (inf or NaN where the mean or median is 0).
    """
    values = np.asarray(values, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        return {
            "plain": 100.0 * np.nanstd(values, axis=1) / np.abs(np.nanmean(values, axis=1)),
            "robust": 100.0 * _robust_std(values, axis=1) / np.abs(np.nanmedian(values, axis=1)),
        }


def spread(values) -> dict[str, float | int | None]:
    """Mean, standard deviation, median and robust standard deviation of the finite values.

    Returns
    -------
    dict
        ``n_pixels``, ``mean``, ``std``, ``median``, ``robust_std`` (1.4826
        MAD) and ``relative_std`` (std / |mean|); None without a finite value.
    """
    values = np.asarray(values, dtype=np.float64)
    values = values[np.isfinite(values)]
    if values.size == 0:
        return {"n_pixels": 0, "mean": None, "std": None, "median": None, "robust_std": None, "relative_std": None}
    mean, std = float(values.mean()), float(values.std())
    return {
        "n_pixels": int(values.size),
        "mean": mean,
        "std": std,
        "median": float(np.median(values)),
        "robust_std": float(_robust_std(values)),
        "relative_std": std / abs(mean) if mean else None,
    }


def relative_difference(a, b, scale: float | None = None) -> dict[str, float | int | None]:
    """Summary of the relative differences ``(a - b) / ((a + b) / 2)``, in %, where both are finite.

    Parameters
    ----------
    a, b : array_like
        Two estimates of the same quantities (broadcast against each other).
    scale : float, optional
        Divide by ``|scale|`` instead of each pair's mean: for quantities
        whose values may come near zero (a coefficient that is small against
        its spread), relative to their size over the image.

    Returns
    -------
    dict
        ``n`` (pairs), ``median_abs_percent`` (the headline),
        ``mean_percent`` (the systematic part), ``std_percent``,
        ``p95_abs_percent``; None without a finite pair.
    """
    return _summary(_relative(a, b, scale))


def _relative(a, b, scale: float | None = None) -> np.ndarray:
    """Return the relative differences of :func:`relative_difference`, in %, flattened (NaN or inf where undefined)."""
    a, b = np.asarray(a), np.asarray(b)
    # in float64, without float64 copies of the inputs and in place where possible: the wall's reflectances
    # are ~10^7 pairs
    d = np.subtract(a, b, dtype=np.float64).ravel()
    with np.errstate(divide="ignore", invalid="ignore"):
        if scale is None:
            d /= np.add(a, b, dtype=np.float64).ravel()
            d *= 200.0
        else:
            d *= 100.0 / abs(scale)
    return d


def _summary(d: np.ndarray) -> dict[str, float | int | None]:
    """Summarise the finite relative differences in ``d`` (flat float64, overwritten) as :func:`relative_difference`."""
    finite = np.isfinite(d)
    if not finite.all():
        d = d[finite]
    if d.size == 0:
        return {"n": 0, "median_abs_percent": None, "mean_percent": None, "std_percent": None, "p95_abs_percent": None}
    mean, std = float(d.mean()), float(d.std())
    np.abs(d, out=d)
    return {
        "n": int(d.size),
        "median_abs_percent": float(np.median(d, overwrite_input=True)),
        "mean_percent": mean,
        "std_percent": std,
        "p95_abs_percent": float(np.percentile(d, 95, overwrite_input=True)),
    }


def coefficients(ds: xr.Dataset, region: Roi | None) -> np.ndarray:
    """Return the coefficients A..E of a calibration's pixels, as a matrix.

    Parameters
    ----------
    ds : Dataset
        A calibration store, or the simulator's instrument truth (``coef`` (term, y, x)).
    region : Roi or None
        Sensor pixels to take; None: all pixels of the store.

    Returns
    -------
    (5, pixels) ndarray of float64
        One row per term, the pixels row-major.
    """
    coef = ds["coef"].transpose("term", "y", "x")
    if region is not None:
        coef = coef.isel(y=slice(*region.y), x=slice(*region.x))
    return np.asarray(coef.values, dtype=np.float64).reshape(len(TERMS), -1)


def coefficient_statistics(calibration: xr.Dataset, region: Roi | None = None) -> dict:
    """Fit quality, variability and correlation of the coefficients across the pixels of ``region``.

    Parameters
    ----------
    calibration : Dataset
        A calibration store (``coef``, ``r2``, ``status``) on the full sensor.
    region : Roi, optional
        Sensor pixels to cover (the campaign's crop); default: all.

    Returns
    -------
    dict
        ``fit``: ``mean_r2`` (paper 0.98), ``median_r2``, ``n_fitted``,
        ``n_pixels`` and ``status_counts`` over the region, ``sensor_mean_r2``
        over the whole sensor; ``variability_percent``: ``plain`` and
        ``robust`` (:func:`variability` of the fitted pixels), term -> %;
        ``correlation``: ``terms`` (those that vary) and ``matrix`` (Pearson,
        across the fitted pixels).
    """
    ds = calibration[["coef", "r2", "status"]].load()
    local = ds if region is None else ds.isel(y=slice(*region.y), x=slice(*region.x))
    table = calibration_diagnostics(local)
    fitted = (local["status"] == 0).values.ravel()
    spreads = variability(coefficients(local, None)[:, fitted])
    return {
        "fit": {
            **{key: table[key] for key in ("mean_r2", "median_r2", "n_fitted", "n_pixels", "status_counts")},
            "sensor_mean_r2": float(ds["r2"].values[ds["status"].values == 0].mean()),
        },
        "variability_percent": {kind: dict(zip(TERMS, values)) for kind, values in spreads.items()},
        "correlation": {"terms": table["correlation_terms"], "matrix": table["correlation"]},
    }


def observed_grid(calibration: xr.Dataset) -> tuple[np.ndarray, np.ndarray]:
    """Return a (distance, AOI) grid over the central 98 % of a calibration's wall observations (``wall_obs``).

    Returns
    -------
    distance, aoi : (7, 7) ndarray
        Metres and radians.

    """
    obs = calibration["wall_obs"]
    axes = [
        np.linspace(*np.nanpercentile(obs.sel(quantity=quantity).values, _GRID_PERCENTILES), _GRID_SIZE)
        for quantity in ("distance", "aoi")
    ]
    return tuple(np.meshgrid(*axes, indexing="ij"))


def compare_calibrations(first: xr.Dataset, second: xr.Dataset, grid, region: Roi | None = None) -> dict:
    """Relative differences of two calibrations of one sensor (:func:`relative_difference`, first vs second).

    Parameters
    ----------
    first, second : Dataset
        ``coef`` (term, y, x) in the gauge E = 1 and attr ``scale_k``: two
        calibration stores, or one and the simulator's instrument truth.
    grid : (distance, aoi) pair of array_like
        Where f and k f are compared: metres and radians, broadcasting together.
    region : Roi, optional
        Sensor pixels to cover; default: all.

    Returns
    -------
    dict
        ``n_pixels`` (fitted in both); ``coefficients`` (A..D -> summary of
        the differences relative to the term's mean over the pixels and both
        calibrations, ``|a1 - a2| / |mean|``: C and D are small against their
        estimation noise on some pixels; E is 1 in both); ``scale_k`` (both, and their difference in %);
        ``instrument_function`` (f over those pixels and the grid) with
        ``median_pixel_max_abs_percent`` (median over pixels of the largest
        |difference| on the grid); ``calibration`` (k f, the whole
        calibration: the reflectance of the same data differs as much, with
        the opposite sign).
    """
    a, b = coefficients(first, region), coefficients(second, region)
    both = np.isfinite(a).all(axis=0) & np.isfinite(b).all(axis=0)
    a, b = a[:, both, None], b[:, both, None]
    ka, kb = float(first.attrs["scale_k"]), float(second.attrs["scale_k"])
    distance, aoi = (np.ravel(part) for part in np.broadcast_arrays(*grid))
    # f and k f pixel block by pixel block: their temporaries stay small; the differences are those of the
    # whole (pixel, grid) arrays, in the same order
    # the instrument is f c: c the calibration's residual correction, or the truth's rendered systematics
    ca, cb = (
        next((np.asarray(correction_factor(ds[name], distance, aoi)) for name in _FACTORS if name in ds), 1.0)
        for ds in (first, second)
    )
    pixels, points = a.shape[1], distance.size
    f_differences, kf_differences, worst = np.empty(pixels * points), np.empty(pixels * points), np.empty(pixels)
    for start in range(0, pixels, _GRID_BLOCK):
        block, flat = slice(start, start + _GRID_BLOCK), slice(start * points, (start + _GRID_BLOCK) * points)
        fa = instrument_function(a[:, block], distance, aoi) * ca
        fb = instrument_function(b[:, block], distance, aoi) * cb
        f_differences[flat], kf_differences[flat] = _relative(fa, fb), _relative(ka * fa, kb * fb)
        largest = np.subtract(fa, fb)  # |200 (fa - fb) / (fa + fb)|, in place
        largest *= 200.0
        with np.errstate(divide="ignore", invalid="ignore"):
            largest /= np.add(fa, fb)
        worst[block] = np.abs(largest, out=largest).max(axis=1)
    return {
        "n_pixels": int(both.sum()),
        "coefficients": {
            term: relative_difference(a[index], b[index], 0.5 * (a[index].mean() + b[index].mean()))
            for index, term in enumerate(TERMS[:4])
        },
        "scale_k": {"first": ka, "second": kb, "difference_percent": 200.0 * (ka - kb) / (ka + kb)},
        "instrument_function": {
            **_summary(f_differences),
            "median_pixel_max_abs_percent": float(np.median(worst)) if worst.size else None,
        },
        "calibration": _summary(kf_differences),
    }


def _truth_statistics(truth: xr.Dataset, region: Roi | None) -> dict:
    """Variability and correlation of the true coefficients (gauge E = 1) across the region."""
    coef = coefficients(truth, region)
    varying = [index for index in range(len(TERMS)) if np.std(coef[index]) > 0]
    return {
        "variability_percent": {kind: dict(zip(TERMS, values)) for kind, values in variability(coef).items()},
        "correlation": {"terms": [TERMS[index] for index in varying], "matrix": np.corrcoef(coef[varying])},
    }


def _calibration_aoi(calibration: xr.Dataset, path) -> dict:
    """Return the AOI parameters (window, jump, max_window) a calibration store was fitted with (its provenance)."""
    parameters = calibration.attrs.get("surffin_parameters", {})
    missing = [key for key in ("window", "jump", "max_window") if key not in parameters]
    if missing:
        raise StoreError(
            f"{path}: the calibration store does not record its AOI parameters {missing} (surffin_parameters); "
            f"refit it with this surffin"
        )
    return {
        "window": int(parameters["window"]),
        "jump": float(parameters["jump"]),
        "max_window": int(parameters["max_window"]),
    }


#: Sensor rows fitted at a time by :func:`wall_features`, which bounds its memory.
FIT_BAND_ROWS = 64


def wall_features(
    campaign: Campaign,
    views: Sequence[str | os.PathLike],
    calibrations: Mapping[str, xr.Dataset],
    *,
    aoi: Mapping,
    min_views: int = 2,
    min_spread: float = DEFAULT_MIN_SPREAD,
) -> tuple[xr.Dataset, xr.Dataset]:
    """Calibrated reflectance of wall views with each calibration, and R0, n fitted per sensor pixel over them.

    Each view is read and its AOI and distance computed over the campaign's crop,
    as the calibration computes them on the full sensor
    (:func:`surffin.method.calibration.observe_view`). A sensor pixel sees the same uniform wall in every view,
    so its reflectances over the views follow one scattering law, fitted by
    :func:`surffin.method.scattering.fit_scattering_arrays`.

    Parameters
    ----------
    campaign : Campaign
    views : sequence of path-like
        Wall view files.
    calibrations : mapping of str to Dataset
        Name -> calibration (``coef`` (term, y, x) on the full sensor, attr ``scale_k``).
    aoi : mapping
        AOI parameters ``window``, ``jump``, ``max_window`` (those of the calibration).
    min_views, min_spread
        Of :func:`~surffin.method.scattering.fit_scattering_arrays`.

    Returns
    -------
    observed : Dataset
        ``reflectance`` (calibration, view, y, x), ``aoi`` (view, y, x,
        radians), float32, NaN where unusable.
    fits : Dataset
        ``R0``, ``n`` (calibration, y, x).
    """
    rows, columns = campaign.crop.slices
    names = list(calibrations)
    coefs = [calibrations[name]["coef"].transpose("term", "y", "x").values[:, rows, columns] for name in names]
    scales = [float(calibrations[name].attrs["scale_k"]) for name in names]
    corrections = [calibrations[name].get("correction") for name in names]
    shape = (len(views), *campaign.crop.shape)
    reflectance = np.empty((len(names), *shape), dtype=np.float32)
    angles = np.empty(shape, dtype=np.float32)
    for index, path in enumerate(views):
        view = observe_view(campaign, path, aoi, campaign.crop)
        values = np.stack([view.intensity, view.distance, view.aoi])
        values[:, ~view.valid] = np.nan
        angles[index] = values[2]
        for which, (coef, scale, correction) in enumerate(zip(coefs, scales, corrections)):
            reflectance[which, index] = with_reflectance(values, coef, scale, axis=0, correction=correction)[3]
    coords = {
        "calibration": names,
        "view": [Path(path).stem for path in views],
        "y": np.arange(*campaign.crop.y),
        "x": np.arange(*campaign.crop.x),
    }
    observed = xr.Dataset(
        {
            "reflectance": (("calibration", "view", "y", "x"), reflectance, {"units": "1"}),
            "aoi": (("view", "y", "x"), angles, {"units": "rad"}),
        },
        coords=coords,
    )
    # band by band of rows: the fit's float64 working copies of every view are then one band's
    fitted = {name: np.empty((len(names), *shape[1:])) for name in ("R0", "n")}
    for start in range(0, shape[1], FIT_BAND_ROWS):
        band = slice(start, start + FIT_BAND_ROWS)
        theta = np.moveaxis(angles[:, band], 0, -1)
        for which in range(len(names)):
            fit = fit_scattering_arrays(
                np.moveaxis(reflectance[which, :, band], 0, -1), theta, min_views=min_views, min_spread=min_spread
            )
            for name, values in fitted.items():
                values[which, band] = fit[name]
    dims = ("calibration", "y", "x")
    fits = xr.Dataset({name: (dims, values) for name, values in fitted.items()}, {dim: coords[dim] for dim in dims})
    return observed, fits


def representative_specimens(campaign: Campaign) -> list[str]:
    """Return the first specimen of each class, in campaign order: those the diagnostics reprocess.

    One per class keeps the diagnostics' cost and memory independent of the
    number of specimens while still covering every class's range of features.
    """
    first = {}
    for name, item in campaign.specimens.items():
        first.setdefault(item.cls, name)
    return list(first.values())


def _with_calibration(
    first: Mapping[str, xr.Dataset], calibration: xr.Dataset, roi: Roi | None, params: Mapping
) -> dict[str, xr.Dataset]:
    """Register and fit a specimen's views with another calibration, from its stores with the first one.

    The item chain after the AOI (:func:`surffin.method.stages.process_item`),
    but the views are warped by the registration maps of ``first["registered"]``:
    :func:`~surffin.method.stages.registration_stage` makes them from the
    ingest alone, so they are those it would make again; with a roi, they cover
    the roi and the margin its features read
    (:func:`~surffin.method.features.feature_window`).

    Parameters
    ----------
    first : mapping of str to Dataset
        ``ingest``, ``aoi`` and ``registered`` (``map_x``, ``map_y``) of the specimen.
    calibration : Dataset
    roi : Roi or None
        The specimen's.
    params : mapping
        Stage parameters; :func:`~surffin.method.stages.features_stage` takes its own.

    Returns
    -------
    dict
        ``registered`` and ``features``, on the grid of ``first["registered"]``.
    """
    from surffin.method.registration import register
    from surffin.method.stages import ITEM_CHAIN, features_stage, reflectance_stage

    ingest, aoi, maps = first["ingest"], first["aoi"], first["registered"][["map_x", "map_y"]]
    reflectance = reflectance_stage(ingest, aoi, calibration).compute()
    views = xr.Dataset({"reflectance": reflectance["reflectance"], "aoi": aoi["aoi"]}).compute()
    registered = register(views, maps.compute())
    step = next(step for step in ITEM_CHAIN if step.function is features_stage)
    keywords = {key: params[key] for key in step.keywords if key in params}
    features = features_stage(registered, reflectance, aoi, roi=roi, **keywords).compute()
    return {"registered": registered, "features": features}


def process_specimens(
    campaign: Campaign,
    calibrations: Mapping[str, xr.Dataset],
    params: Mapping | None = None,
    stores: Mapping[str, Mapping[str, str | os.PathLike]] | None = None,
) -> dict[str, dict[str, xr.Dataset]]:
    """Process the :func:`representative_specimens` with each calibration, in memory, or read them from their stores.

    A specimen goes through :func:`surffin.method.stages.process_item` with
    the first calibration, unless it is in ``stores``: the workflow's stores,
    which it processed with that calibration, are then read instead. The
    reflectance, registration and features with each other calibration are
    computed from that first run's ingest, AOI and registration maps, which
    do not depend on the calibration.

    Parameters
    ----------
    campaign : Campaign
    calibrations : mapping of str to Dataset
        Name -> calibration; the first is the one ``stores`` were processed with.
    params : mapping, optional
        ``method`` (registration) and the stage parameters of
        :func:`~surffin.method.stages.process_item` (``window``, ``jump``, ``size``,
        ``variability_size``, ``min_views``, ``min_spread``).
    stores : mapping, optional
        Specimen -> :data:`SPECIMEN_STORES` name -> path of its store;
        specimens not in it are processed from their view files.

    Returns
    -------
    dict
        Specimen -> calibration name -> Dataset over the specimen's roi (the
        whole crop without one): ``reflectance`` (view, y, x) registered onto
        the reference view, the features ``R0``, ``n`` (smoothed) and the
        unsmoothed fits ``R0_fit``, ``n_fit`` (y, x).
    """
    from surffin.io.ingest import ingest_item
    from surffin.io.store import open_store
    from surffin.method.features import select_roi
    from surffin.method.stages import process_item

    params, stores = dict(params or {}), dict(stores or {})
    (first, calibration), *others = calibrations.items()
    out = {}
    for name in representative_specimens(campaign):
        item = campaign.specimens[name]
        if name in stores:
            # without dask (an item's stores are small): the ingest and AOI read once, for each other calibration
            run = {
                key: open_store(stores[name][key], stage=stage, chunks=None) for key, stage in SPECIMEN_STORES.items()
            }
            run.update({key: run[key].load() for key in ("ingest", "aoi")})
        else:
            ingest = ingest_item(campaign, name)
            run = {"ingest": ingest, **process_item(ingest, calibration, roi=item.roi, **params)}
        runs = {first: run, **{which: _with_calibration(run, other, item.roi, params) for which, other in others}}
        out[name] = {}
        for which, done in runs.items():
            both = xr.merge(
                [done["registered"][["reflectance"]], done["features"][["R0", "n", "R0_fit", "n_fit"]]],
                compat="override",
                combine_attrs="drop",
            )
            out[name][which] = (both if item.roi is None else select_roi(both, item.roi)).compute()
        log.info("diagnostics: specimen %s processed with each calibration (%s)", name, ", ".join(calibrations))
    return out


def _specimen_differences(processed: Mapping[str, Mapping[str, xr.Dataset]], first: str, second: str) -> dict:
    """Relative differences of the specimens' reflectance and features, pooled and per specimen."""
    pooled = {name: ([], []) for name in _SPECIMEN_VARIABLES}
    items = {}
    for item, runs in processed.items():
        items[item] = {}
        for name in _SPECIMEN_VARIABLES:
            a, b = runs[first][name].values.ravel(), runs[second][name].values.ravel()
            pooled[name][0].append(a)
            pooled[name][1].append(b)
            items[item][name] = relative_difference(a, b)
    return {
        **{
            name: relative_difference(np.concatenate(a or [np.empty(0)]), np.concatenate(b or [np.empty(0)]))
            for name, (a, b) in pooled.items()
        },
        "items": items,
    }


# --- the whole report -----------------------------------------------------------------------------


def _repeat_reason(campaign: Campaign, repeat_folders: Mapping[str, str] | None) -> str:
    """Why there is no repeatability part."""
    if repeat_folders is None:
        return "turned off: no repeat calibration folders configured (calibration_repeat: null)"
    if campaign.calibration is None:
        return f"{campaign.path} has no calibration section (the reference panel's reflectance and roi)"
    missing = sorted(folder for folder in repeat_folders.values() if not (campaign.root / folder).is_dir())
    if missing:
        return f"the campaign {campaign.root} has no repeat calibration set (no folders {missing})"
    return "no repeat calibration store given"


def _wall_sets(campaign: Campaign, calibrations: Mapping[str, xr.Dataset]) -> dict[str, tuple[Path, ...]]:
    """Wall folder (relative) -> view files: the campaign's calibration wall and the calibrations' own walls."""
    from surffin.io.viewfile import list_views

    sets = {}
    if campaign.calibration is not None:
        wall = campaign.calibration.wall
        sets[str(wall[0].parent.relative_to(campaign.root))] = wall
    for calibration in calibrations.values():
        folder = (calibration.attrs.get("calibration_set") or {}).get("wall")
        if folder is not None and folder not in sets and (campaign.root / folder).is_dir():
            sets[folder] = tuple(list_views(campaign.root / folder))
    return sets


def _wall_report(camp: Campaign, calibrations: Mapping[str, xr.Dataset], item_params: Mapping, aoi: Mapping):
    """Feature spread of every wall set with every calibration, and the wall repeatability of two calibrations."""
    from surffin.io.ingest import describe_file

    spreads, repeatability = [], []
    fit_options = {key: item_params[key] for key in ("min_views", "min_spread") if key in item_params}
    for folder, views in _wall_sets(camp, calibrations).items():
        described = {str(Path(path).relative_to(camp.root)): describe_file(path) for path in views}
        observed, fits = wall_features(camp, views, calibrations, aoi=aoi, **fit_options)
        for name, calibration in calibrations.items():
            inputs = calibration.attrs.get("surffin_inputs", {})
            in_fit = sum(inputs.get(relative) == description for relative, description in described.items())
            fit = fits.sel(calibration=name)
            spreads.append(
                {
                    "calibration": name,
                    "wall": folder,
                    "views": len(views),
                    "views_in_fit": in_fit,
                    "R0": spread(fit["R0"].values),
                    "n": spread(fit["n"].values),
                }
            )
            log.info(
                "diagnostics: wall %s with %s (%d of %d views in its fit): std of R0 %s, of n %s",
                folder,
                name,
                in_fit,
                len(views),
                _format(spreads[-1]["R0"]["std"]),
                _format(spreads[-1]["n"]["std"]),
            )
        if len(calibrations) == 2:
            pairs = {"reflectance": observed["reflectance"], "R0": fits["R0"], "n": fits["n"]}
            differences = {
                name: relative_difference(*both.transpose("calibration", ...)) for name, both in pairs.items()
            }
            repeatability.append({"wall": folder, **differences})
    return spreads, repeatability


class CalibrationReport(NamedTuple):
    """The calibration diagnostics of a campaign (:func:`calibration_report`) and what their figures draw.

    Attributes
    ----------
    report : dict
        The diagnostics, as written by :func:`write_report`.
    correlations : dict
        Panel title -> ``{"terms", "matrix"}``: the correlation matrices of each
        calibration, of the truth (when given) and of the paper.
    calibrations : dict of str to Dataset
        ``first`` and, with a repeat, ``repeat``: the calibrations (``coef``, ``r2``, ``status``, ``wall_obs``).
    specimens : dict or None
        :func:`process_specimens` with both calibrations; None without a repeat.
    region : Roi
        The sensor pixels covered (the campaign's crop).
    """

    report: dict
    correlations: dict
    calibrations: dict
    specimens: dict | None
    region: Roi


def calibration_report(
    camp: Campaign,
    *,
    calibration: str | os.PathLike,
    repeat: str | os.PathLike | None = None,
    repeat_folders: Mapping[str, str] | None = None,
    item_params: Mapping | None = None,
    specimen_stores: Mapping[str, Mapping[str, str | os.PathLike]] | None = None,
    instrument_truth: str | os.PathLike | None = None,
) -> CalibrationReport:
    """Compute the calibration diagnostics of a campaign, in memory.

    The workflow's job, which checks the stores against the campaign's camera
    first and writes the JSON and the figures, is
    :func:`surffin.pipeline.analyses.run_calibration_diagnostics`.

    Parameters
    ----------
    camp : Campaign
        The campaign: its wall views (wall features) and specimens
        (repeatability of their reflectance and features).
    calibration : path-like
        The calibration store.
    repeat : path-like, optional
        A second calibration store of the same camera, fitted to a repeat
        acquisition (:func:`surffin.pipeline.run.run_calibration` with
        ``folders``); without it the repeatability part is left out, and the
        report (``repeatability.reason``) and the log say why.
    repeat_folders : mapping, optional
        The configured ``{"wall", "reference"}`` folders of the repeat set,
        used only to explain a missing ``repeat``.
    item_params : mapping, optional
        Registration ``method`` and the stage parameters of the specimens
        (:func:`process_specimens`); ``min_views`` and ``min_spread`` also
        serve the wall feature fits.
    specimen_stores : mapping, optional
        The stores of the representative specimens processed with
        ``calibration`` (:func:`process_specimens`' ``stores``): read instead
        of processing them again.
    instrument_truth : path-like, optional
        The simulator's ``instrument.zarr``: each calibration is compared with it.

    Returns
    -------
    CalibrationReport
        Its ``report`` has the sections ``calibrations`` (per store:
        :func:`coefficient_statistics`, ``scale_k``, ``calibration_set``),
        ``wall_features`` (per wall set and calibration: :func:`spread` of R0
        and n, ``views_in_fit``), ``repeatability`` (``available``,
        ``reason``; :func:`compare_calibrations`, ``wall`` and ``specimens``
        relative differences), ``truth`` (when given) and ``paper``
        (:data:`surffin.paper.CALIBRATION`).
    """
    from surffin.io.store import open_store

    item_params = dict(item_params or {})
    stores = {"first": calibration, **({} if repeat is None else {"repeat": repeat})}
    calibrations = {}
    for name, path in stores.items():
        ds = open_store(path, stage="calibration", chunks=None)
        if "wall_obs" not in ds:
            raise StoreError(
                f"{path}: the calibration store keeps no wall observations (wall_obs); refit it with this surffin"
            )
        # what the diagnostics read: the fit, its wall observations and the residual correction (the reflectance's c)
        calibrations[name] = ds[
            ["coef", "r2", "status", "wall_obs", *(["correction"] if "correction" in ds else [])]
        ].load()
    aoi = _calibration_aoi(calibrations["first"], calibration)
    region = camp.crop
    report = {
        "campaign": str(camp.root),
        "region": {"name": "crop", "y": list(region.y), "x": list(region.x)},
        "inputs": {
            name: None if path is None else str(path)
            for name, path in (("calibration", calibration), ("repeat", repeat), ("instrument_truth", instrument_truth))
        },
        "calibrations": {},
    }
    for name, cal in calibrations.items():
        stats = coefficient_statistics(cal, region)
        report["calibrations"][name] = {
            "store": str(stores[name]),
            "calibration_set": cal.attrs.get("calibration_set"),
            "scale_k": float(cal.attrs["scale_k"]),
            **stats,
        }
        log.info(
            "diagnostics: %s: mean R2 %.4f over the crop; variability %% plain %s, robust %s",
            name,
            stats["fit"]["mean_r2"],
            _plain(stats["variability_percent"]["plain"]),
            _plain(stats["variability_percent"]["robust"]),
        )
    spreads, wall_repeatability = _wall_report(camp, calibrations, item_params, aoi)
    report["wall_features"] = spreads
    grid = observed_grid(calibrations["first"])
    tables = {f"{name} calibration, crop": report["calibrations"][name]["correlation"] for name in calibrations}
    if instrument_truth is not None:
        truth = open_store(instrument_truth, chunks=None).load()
        report["truth"] = {
            **_truth_statistics(truth, region),
            **{name: compare_calibrations(cal, truth, grid, region) for name, cal in calibrations.items()},
        }
        tables["simulator truth, crop"] = report["truth"]["correlation"]
    tables["paper Table 2"] = PAPER_CALIBRATION["correlation"]
    processed = None
    if repeat is None:
        reason = _repeat_reason(camp, repeat_folders)
        log.info("diagnostics: no repeatability: %s", reason)
        report["repeatability"] = {"available": False, "reason": reason}
    else:
        processed = process_specimens(camp, calibrations, item_params, specimen_stores)
        report["repeatability"] = {
            "available": True,
            "reason": None,
            **compare_calibrations(calibrations["first"], calibrations["repeat"], grid, region),
            "wall": wall_repeatability,
            "specimens": _specimen_differences(processed, "first", "repeat"),
        }
        summary = report["repeatability"]
        log.info(
            "diagnostics: repeatability (median |relative difference|, %%): coefficients %s, k f %s, specimens' "
            "reflectance %s, R0 %s, n %s",
            {term: _format(value["median_abs_percent"]) for term, value in summary["coefficients"].items()},
            *(
                _format(part["median_abs_percent"])
                for part in (
                    summary["calibration"],
                    *(summary["specimens"][name] for name in ("reflectance", "R0", "n")),
                )
            ),
        )
    report["paper"] = PAPER_CALIBRATION
    return CalibrationReport(report, tables, calibrations, processed, region)


def write_report(report: Mapping, output_json: str | os.PathLike) -> Path:
    """Write a :func:`calibration_report`'s ``report`` as strict JSON (numpy numbers as Python ones, NaN as null).

    Parameters
    ----------
    report : mapping
        The report.
    output_json : path-like
        Written atomically, its folder made.

    Returns
    -------
    Path
        ``output_json``.
    """
    output = write_text(output_json, json.dumps(_plain(report), indent=2, allow_nan=False) + "\n")
    log.info("diagnostics: wrote %s", output)
    return output
