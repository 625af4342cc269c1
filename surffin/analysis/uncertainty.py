"""Calibration check of the reported uncertainties against a known truth.

A standard uncertainty u is calibrated when the true error e of the value it
belongs to lies within ``|e| <= u`` for 68.3 % of the pixels and within
``|e| <= 2u`` for 95.4 % (normal errors). :func:`coverage` measures both
fractions, per parameter, for an item whose truth is known (the synthetic
camera writes it, :mod:`surffin.simulate.truth`):

- the smoothed features ``R0``, ``n`` with ``R0_uncertainty``,
  ``n_uncertainty`` (:func:`surffin.method.features.features`). Their true value is
  the truth smoothed the same way (the same kernel over the pixels the fit
  used): smoothing averages the surface's texture too, and that averaging is
  the feature's definition, not an error of the measurement. The window
  pools the variances of its pixels (3 degrees of freedom each at 5 views)
  into about 37 degrees of freedom (7 x 7 kernel), so even exact variances
  would cover 67.6 % and 94.7 % (Student's t), a point below the normal;
- or (``unsmoothed=True``) the per-pixel fit ``R0_fit``, ``n_fit`` with
  ``R0_sigma``, ``n_sigma`` against the pixel's truth. That sigma comes from
  the residual variance with ``m - 2`` degrees of freedom (m views), so even a
  correct one covers like Student's t, not like a normal: 60.9 % and 86.1 %
  within 1 and 2 sigma for 5 views. The expected fractions returned are those
  of t, averaged over the pixels.

``benchmarks/bench_uncertainty.py`` runs the check over the paper preset.
"""

from __future__ import annotations

import math

import numpy as np
import xarray as xr

from surffin.method.features import UNCERTAINTY, smooth

__all__ = ["PARAMETERS", "NORMAL_COVERAGE", "coverage"]

#: Parameters whose uncertainties are checked.
PARAMETERS = tuple(UNCERTAINTY)
#: Share of normal errors within 1 and 2 standard deviations.
NORMAL_COVERAGE = (math.erf(1 / math.sqrt(2)), math.erf(2 / math.sqrt(2)))


def _on_grid(da: xr.DataArray, grid: xr.Dataset, what: str) -> np.ndarray:
    """Return the values (y, x) of ``da`` at the sensor pixels of ``grid``."""
    try:
        values = da.sel(y=grid["y"].values, x=grid["x"].values)
    except KeyError as exc:
        raise ValueError(f"{what} does not cover the pixels of the features ({exc})") from exc
    return np.asarray(values.transpose("y", "x").values)


def _student_coverage(dof: np.ndarray) -> tuple[float, float]:
    """Mean share of Student's t with ``dof`` (per pixel) within 1 and 2."""
    from scipy import stats

    return tuple(float(np.mean(2 * stats.t.cdf(k, dof) - 1)) for k in (1, 2))


def coverage(
    features: xr.Dataset, truth: xr.Dataset, *, mask: xr.DataArray | None = None, unsmoothed: bool = False
) -> dict:
    """Share of pixels whose true error lies within 1 and 2 reported standard uncertainties.

    Parameters
    ----------
    features : Dataset (y, x)
        A features store (:func:`surffin.method.features.features`): ``R0``, ``n``,
        ``R0_uncertainty``, ``n_uncertainty``, ``R0_fit``, ``n_fit`` and attrs
        ``smoothing_size``, ``smoothing_sigma``, ``min_weight``; with
        ``unsmoothed``: ``R0_fit``, ``n_fit``, ``R0_sigma``, ``n_sigma``,
        ``n_views``.
    truth : Dataset
        ``R0`` and ``n`` on (y, x) with sensor coordinates covering those of
        ``features`` (e.g. a truth store of the synthetic camera).
    mask : (y, x) DataArray of bool, optional
        The pixels to score (e.g. away from the edges of surfaces, whose
        windows mix surfaces); default all. Selected by sensor coordinates.
    unsmoothed : bool, default False
        Check the per-pixel fit and its ``<name>_sigma`` instead of the
        smoothed features.

    Returns
    -------
    dict (JSON-serialisable)
        Parameter name -> ``n_pixels`` (scored: mask, and estimate,
        uncertainty and truth finite), ``within_1``, ``within_2`` (shares of
        them with ``|error| <= 1`` and ``2`` uncertainties; None without
        pixels), ``expected_1``, ``expected_2`` (those of a calibrated
        uncertainty: :data:`NORMAL_COVERAGE`, or Student's t with
        ``n_views - 2`` degrees of freedom for the unsmoothed fit) and
        ``z_scale``: 1.4826 times the median of ``|error| / uncertainty``,
        about 1 for calibrated normal errors (the factor by which the
        uncertainty is too small).
    """
    suffix = "_sigma" if unsmoothed else "_uncertainty"
    required = [f"{name}_fit" for name in PARAMETERS] + [name + suffix for name in PARAMETERS]
    required += ["n_views"] if unsmoothed else list(PARAMETERS)
    missing = [name for name in required if name not in features]
    if missing:
        raise ValueError(f"coverage: features lack {missing}; pass a features store of this surffin")
    missing = [name for name in PARAMETERS if name not in truth]
    if missing:
        raise ValueError(f"coverage: truth lacks {missing}; it needs {list(PARAMETERS)} on (y, x)")
    scored = np.ones((features.sizes["y"], features.sizes["x"]), dtype=bool)
    if mask is not None:
        scored = _on_grid(mask, features, "mask").astype(bool)
    result = {}
    for name in PARAMETERS:
        fit = features[f"{name}_fit"].transpose("y", "x").astype(np.float64).compute()
        reference = _on_grid(truth[name], features, "truth").astype(np.float64)
        if unsmoothed:
            estimate = fit.values
        else:
            estimate = features[name].transpose("y", "x").values
            attrs = features.attrs
            same_pixels = fit.copy(data=np.where(np.isfinite(fit.values), reference, np.nan))
            reference = smooth(
                same_pixels, attrs["smoothing_size"], sigma=attrs["smoothing_sigma"], min_weight=attrs["min_weight"]
            ).values
        uncertainty = np.asarray(features[name + suffix].transpose("y", "x").values, dtype=np.float64)
        error = np.asarray(estimate, dtype=np.float64) - reference
        ok = scored & np.isfinite(error) & np.isfinite(uncertainty)
        result[name] = {"n_pixels": int(ok.sum())}
        if not ok.any():
            result[name].update(dict.fromkeys(("within_1", "within_2", "expected_1", "expected_2", "z_scale")))
            continue
        error, uncertainty = np.abs(error[ok]), uncertainty[ok]
        if unsmoothed:
            expected = _student_coverage(features["n_views"].transpose("y", "x").values[ok].astype(np.float64) - 2)
        else:
            expected = NORMAL_COVERAGE
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(error > 0, error / uncertainty, 0.0)
        result[name].update(
            within_1=float(np.mean(error <= uncertainty)),
            within_2=float(np.mean(error <= 2 * uncertainty)),
            expected_1=expected[0],
            expected_2=expected[1],
            z_scale=float(1.4826 * np.median(z)),
        )
    return result
