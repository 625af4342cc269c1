"""The camera's intensity noise, measured on the calibration wall, as a function of intensity.

The variability feature (method step 5) is a local standard deviation of the
reflectance: the surface's texture plus the camera's noise. The noise's share
grows as the return weakens (farther, darker, more oblique), so the same finish
seen from farther off looks rougher. :class:`NoiseStatistics` measures the
relative noise variance ``var(I) / I^2`` against intensity from the wall views
the calibration reads anyway; :func:`relative_noise` looks it up per pixel, and
:func:`surffin.method.features.variability` subtracts it.

Measurement: after the calibration fit, a subset of the wall views is read
again and flat-fielded, ``q = I / (f(d, theta) cos(theta))`` with the fitted
instrument function, which takes out each pixel's fixed gain pattern. The wall
is flat and Lambertian, so ``q`` is the wall's reflectance (times a constant)
and its noise; every pixel whose 3 x 3 neighbourhood is valid gives
``r = q / mean_3x3(q) - 1`` (a linear trend cancels in the symmetric mean). For
independent pixels of relative variance ``s^2``, ``var(r) = (8/9) s^2``;
``r^2 * 9/8`` is summed per bin (quarter octaves) of the local mean intensity.
Texture of the wall at the pixel scale would add to it (an overestimate, the
same for every item); spatially correlated noise would be underestimated.
"""

from __future__ import annotations

import cv2
import numpy as np
import xarray as xr

__all__ = ["NOISE_EDGES", "NOISE_VIEWS", "MIN_SAMPLES", "NoiseStatistics", "relative_noise"]

#: Edges of the intensity bins (counts): quarter octaves from 2^-8 to 2^24.
NOISE_EDGES = 2.0 ** np.arange(-8.0, 24.001, 0.25)
#: Wall views read again for the noise model (spread over the wall set).
NOISE_VIEWS = 16
#: Fewest residuals of a bin whose variance is used.
MIN_SAMPLES = 200
# var(I - mean_3x3 I) = (1 - 1/9) var(I) for independent pixels.
_BOX_FACTOR = 9.0 / 8.0


def _box_mean(image: np.ndarray) -> np.ndarray:
    """Mean over each pixel's 3 x 3 neighbourhood (zero outside the image)."""
    box = np.full(3, 1.0 / 3.0)
    return cv2.sepFilter2D(image, cv2.CV_64F, box, box, borderType=cv2.BORDER_CONSTANT)


class NoiseStatistics:
    """Squared relative residuals of the wall views per intensity bin, accumulated view by view."""

    def __init__(self) -> None:
        self.count = np.zeros(NOISE_EDGES.size - 1)
        self.total = np.zeros(NOISE_EDGES.size - 1)

    def add(self, intensity: np.ndarray, flat: np.ndarray, valid: np.ndarray) -> NoiseStatistics:
        """Add one (H, W) wall view: its intensity and its flat-fielded image.

        Only pixels whose 3 x 3 neighbours are all valid, finite and positive count.

        Returns
        -------
        NoiseStatistics
            ``self``, updated.
        """
        intensity = np.asarray(intensity, dtype=np.float64)
        flat = np.asarray(flat, dtype=np.float64)
        ok = np.asarray(valid, dtype=bool) & np.isfinite(intensity) & np.isfinite(flat) & (intensity > 0) & (flat > 0)
        full = _box_mean(ok.astype(np.float64)) > 1.0 - 1e-9
        level = _box_mean(np.where(ok, intensity, 0.0))[full]
        flat = np.where(ok, flat, 0.0)
        squared = (flat[full] / _box_mean(flat)[full] - 1.0) ** 2 * _BOX_FACTOR
        index = np.searchsorted(NOISE_EDGES, level, side="right") - 1
        inside = (index >= 0) & (index < self.count.size)
        self.count += np.bincount(index[inside], minlength=self.count.size)
        self.total += np.bincount(index[inside], weights=squared[inside], minlength=self.count.size)
        return self

    def dataset(self) -> xr.Dataset:
        """Return the model: ``noise_variance`` (relative, NaN where a bin has too few samples) per ``noise_intensity``.

        ``noise_intensity`` is the bin's geometric centre (counts); ``noise_samples`` the residuals in it.
        """
        with np.errstate(invalid="ignore", divide="ignore"):
            variance = np.where(self.count >= MIN_SAMPLES, self.total / self.count, np.nan)
        centre = np.sqrt(NOISE_EDGES[:-1] * NOISE_EDGES[1:])
        coords = {"noise_intensity": ("noise_bin", centre, {"units": "counts"})}
        return xr.Dataset(
            {
                "noise_variance": (
                    "noise_bin",
                    variance,
                    {"units": "1", "long_name": "relative intensity noise variance var(I)/I^2, wall views"},
                ),
                "noise_samples": ("noise_bin", self.count.astype(np.int64), {"long_name": "wall residuals per bin"}),
            },
            coords=coords,
        )


def relative_noise(intensity: xr.DataArray, model: xr.Dataset) -> xr.DataArray:
    """Relative noise standard deviation of each pixel, from its intensity and the wall's noise model.

    Parameters
    ----------
    intensity : DataArray
        Counts, any dims; lazy input stays lazy.
    model : Dataset
        With ``noise_variance`` and ``noise_intensity`` (:meth:`NoiseStatistics.dataset`;
        a calibration store holds them).

    Returns
    -------
    DataArray of float32
        ``sqrt(var(I)/I^2)`` interpolated in log intensity between the measured
        bins and held constant beyond them; NaN where the intensity is not
        positive.

    Raises
    ------
    ValueError
        The model has no measured bin.
    """
    variance = model["noise_variance"].values
    measured = np.isfinite(variance)
    if not measured.any():
        raise ValueError(
            "the calibration's noise model has no intensity bin with enough wall residuals; "
            "the wall views need valid 3x3 neighbourhoods"
        )
    levels = np.log(model["noise_intensity"].values[measured])
    values = np.sqrt(variance[measured])

    def lookup(counts: np.ndarray) -> np.ndarray:
        with np.errstate(invalid="ignore", divide="ignore"):
            logs = np.log(np.where(counts > 0, counts, np.nan))
        out = np.interp(np.nan_to_num(logs, nan=levels[0]), levels, values)
        return np.where(np.isfinite(logs), out, np.nan).astype(np.float32)

    out = xr.apply_ufunc(lookup, intensity, dask="parallelized", output_dtypes=[np.float32])
    return out.assign_attrs(units="1", long_name="relative intensity noise (standard deviation), wall noise model")
