"""Indicative roughness from the scattering exponent n (paper section 5.3).

The paper finds each specimen's mean n nearly linear in its measured roughness
(rougher plaster scatters more diffusely: lower n). Where reference specimens
carry ``roughness_mm``, :func:`roughness_relation` fits that line as a
classical calibration: ``n = intercept + slope * roughness`` by ordinary least
squares over the specimens (roughness is the controlled, measured quantity; n
is the noisy response), with its coefficient of determination and residual
spread, and a leave-one-out error of the roughness it predicts back for each
specimen. :func:`roughness_map` inverts the line pixel by pixel,
``roughness = (n - intercept) / slope``.

The map is *indicative*: it rests on a handful of specimens of one material,
ignores R0 and the variability, and extrapolates outside the specimens' range
of n (those pixels are marked). It is not a measurement of roughness.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
import xarray as xr

from surffin.errors import SurffinError

__all__ = ["MIN_SPECIMENS", "roughness_relation", "roughness_map"]

#: Specimens with a roughness needed for a relation (two fix a line; three give a residual).
MIN_SPECIMENS = 2


def roughness_relation(
    mean_n: Mapping[str, float], roughness_mm: Mapping[str, float], n_range: Sequence[float] | None = None
) -> dict:
    """Fit ``n = intercept + slope * roughness`` over the specimens.

    Parameters
    ----------
    mean_n : mapping
        Specimen name -> mean smoothed n over its roi.
    roughness_mm : mapping
        Specimen name -> reference roughness, mm (the same names).
    n_range : (low, high), optional
        The values of n the specimens support (e.g. the span of their pixels'
        n); default: from the smallest to the largest mean n.

    Returns
    -------
    dict
        ``intercept``, ``slope`` (per mm), ``r2``, ``residual_std`` (of n; None
        with two specimens), ``roughness_rmse_mm`` (leave-one-out error of the
        predicted roughness; None below three specimens), ``n_range`` (min and
        max of the specimens' mean n), and ``specimens``: per name its mean n,
        roughness, fitted n and leave-one-out roughness.

    Raises
    ------
    SurffinError
        Fewer than :data:`MIN_SPECIMENS` specimens, names that differ, a
        non-finite mean n, or all roughness values equal (no line).
    """
    if set(mean_n) != set(roughness_mm):
        raise SurffinError(
            f"roughness relation: specimens with n {sorted(mean_n)} "
            f"differ from those with a roughness {sorted(roughness_mm)}"
        )
    names = sorted(mean_n)
    if len(names) < MIN_SPECIMENS:
        raise SurffinError(
            f"roughness relation needs at least {MIN_SPECIMENS} specimens with roughness_mm, got {names}"
        )
    n = np.array([mean_n[k] for k in names], dtype=np.float64)
    r = np.array([roughness_mm[k] for k in names], dtype=np.float64)
    if not np.isfinite(n).all():
        raise SurffinError(f"roughness relation: a specimen has no finite mean n: {dict(zip(names, n.tolist()))}")
    if np.ptp(r) == 0:
        raise SurffinError(
            f"roughness relation: all specimens have the same roughness {r[0]} mm; no line can be fitted"
        )
    slope, intercept = _line(r, n)
    fitted = intercept + slope * r
    rss = float(((n - fitted) ** 2).sum())
    tss = float(((n - n.mean()) ** 2).sum())
    loo = [_loo_roughness(r, n, i) for i in range(len(names))] if len(names) >= 3 else [None] * len(names)
    return {
        "model": "n = intercept + slope * roughness_mm",
        "intercept": intercept,
        "slope": slope,
        "r2": 1.0 - rss / tss if tss > 0 else 1.0,
        "residual_std": math.sqrt(rss / (len(names) - 2)) if len(names) > 2 else None,
        "roughness_rmse_mm": float(np.sqrt(np.mean((np.array(loo) - r) ** 2))) if len(names) >= 3 else None,
        "n_range": [float(n.min()), float(n.max())] if n_range is None else [float(v) for v in n_range],
        "specimens": {
            k: {
                "mean_n": float(n[i]),
                "roughness_mm": float(r[i]),
                "fitted_n": float(fitted[i]),
                "loo_roughness_mm": loo[i],
            }
            for i, k in enumerate(names)
        },
    }


def _line(r: np.ndarray, n: np.ndarray) -> tuple[float, float]:
    """Slope and intercept of the least-squares line of n on r."""
    design = np.column_stack([r, np.ones_like(r)])
    (slope, intercept), *_ = np.linalg.lstsq(design, n, rcond=None)
    return float(slope), float(intercept)


def _loo_roughness(r: np.ndarray, n: np.ndarray, i: int) -> float | None:
    """Roughness of specimen ``i`` predicted from the line fitted without it."""
    keep = np.arange(r.size) != i
    if np.ptp(r[keep]) == 0:
        return None
    slope, intercept = _line(r[keep], n[keep])
    return float((n[i] - intercept) / slope)


def roughness_map(n: xr.DataArray, relation: Mapping) -> xr.Dataset:
    """Estimate the indicative roughness of every pixel from its smoothed n.

    Parameters
    ----------
    n : DataArray (y, x)
        Smoothed n of a features store (numpy or dask).
    relation : mapping
        Output of :func:`roughness_relation`.

    Returns
    -------
    Dataset
        ``roughness`` (y, x) mm, NaN where n is; ``extrapolated`` (y, x) bool,
        True where n lies outside the relation's ``n_range`` (the line is
        not supported there).
    """
    if relation["slope"] == 0:
        raise SurffinError("roughness relation has slope 0: n does not depend on roughness, no map can be made")
    low, high = relation["n_range"]
    roughness = (n - relation["intercept"]) / relation["slope"]
    roughness.attrs = {
        "units": "mm",
        "long_name": "indicative roughness from the specimens' linear relation of mean n and roughness",
        "comment": "indicative only: extrapolated outside the specimens' range of n, one material, n alone",
    }
    extrapolated = ((n < low) | (n > high)) & n.notnull()
    extrapolated.attrs = {"long_name": "n outside the range of n the specimens support (roughness extrapolated)"}
    attrs = {"comment": "indicative roughness map (surffin.method.roughness): not a measurement"}
    return xr.Dataset({"roughness": roughness.rename(None), "extrapolated": extrapolated.rename(None)}, attrs=attrs)
