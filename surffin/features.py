"""Feature images of an item: smoothed R0 and n, and the reflectance variability (method step 5).

All three features are neighbourhood operations on (y, x) images that ignore
missing (NaN) pixels:

- :func:`smooth`: Gaussian smoothing by normalised convolution,
  ``G * (v m) / G * m`` with ``m`` the mask of finite pixels. The paper uses a
  "Gaussian filter of size 7 x 7" without a sigma; the kernel here is
  ``size x size`` with OpenCV's rule for a size without a sigma (that of
  ``cv2.getGaussianKernel(size, 0)``) ``sigma = 0.3 ((size - 1) / 2 - 1) + 0.8``,
  1.4 px for 7 x 7, so that the kernel ends at about 2.1 sigma. Unlike
  ``getGaussianKernel``, the weights are always the sampled Gaussian
  (OpenCV substitutes fixed binomial-like tables for sizes up to 7). A pixel
  keeps a value only if it was finite itself (holes are not filled) and the
  finite pixels of its window carry at least ``min_weight`` of the kernel
  mass; pixels outside the image carry none, so the borders are normalised
  like the holes.
- :func:`local_std`: standard deviation over the finite pixels of a
  ``size x size`` box, from box sums of the count, ``v - c`` and
  ``(v - c)^2``, in float64 and centred on the mean ``c`` of the image (of the
  chunk, with its halo, under dask) so that the sum of squares does not
  cancel: the relative error of the variance is about
  ``1e-16 (mu - c)^2 / sigma^2`` with ``mu`` the window's mean. The default is
  the unbiased variance (``ddof=1``): windows near holes and borders hold
  fewer pixels, and the biased estimate would shrink with the count, making
  the feature depend on the pattern of missing pixels.
- :func:`variability`: :func:`local_std` of ``R / cos(theta)`` (Lambert
  correction) of one view on its own pixel grid. Resampling a view onto the
  reference grid averages neighbouring pixels and lowers their spread, so the
  variability is computed before the warp and warped afterwards (METHOD.md).

Under dask every operation runs chunk by chunk with ``dask.array.map_overlap``:
each chunk gets a halo of ``size // 2`` pixels from its neighbours and NaN
outside the image, which the kernels treat exactly like the zero border they
use on a whole image, so the result equals the numpy path for any chunking
to rounding (a few ulp: OpenCV's vectorised and scalar loops round
differently, and :func:`local_std` centres each chunk on its own mean).
"""

from __future__ import annotations

import math
import numbers

import cv2
import numpy as np
import xarray as xr

from surffin.campaign import Roi

__all__ = [
    "DEFAULT_SIZE",
    "DEFAULT_MIN_FRACTION",
    "QUALITY",
    "gaussian_sigma",
    "smooth",
    "local_std",
    "select_roi",
    "most_perpendicular_view",
    "variability",
    "features",
]

#: Default window side, pixels: the paper's 7 x 7 (about 5 x 5 mm at its specimens).
DEFAULT_SIZE = 7
#: Default minimum share of a window that must be valid: of the Gaussian kernel's mass for
#: :func:`smooth`, of the window's pixels for :func:`local_std`.
DEFAULT_MIN_FRACTION = 0.25
#: Per-pixel quality variables of a scattering fit passed through by :func:`features`.
QUALITY = ("R0_sigma", "n_sigma", "rms", "n_views", "status")


def _check_size(size) -> int:
    if isinstance(size, bool) or not isinstance(size, numbers.Integral) or size < 1 or size % 2 == 0:
        raise ValueError(f"size must be an odd positive integer (window side, pixels), got {size!r}")
    return int(size)


def _check_grid(arr, name: str, dims=("y", "x")) -> None:
    if not isinstance(arr, xr.DataArray):
        raise TypeError(f"{name} must be an xarray.DataArray with dims {dims}, got {type(arr).__name__}")
    if set(arr.dims) != set(dims):
        raise ValueError(f"{name} must have dims {dims}, got {arr.dims}")


def gaussian_sigma(size: int) -> float:
    """Standard deviation, pixels, of the Gaussian kernel of side ``size`` (OpenCV's rule).

    ``sigma = 0.3 ((size - 1) / 2 - 1) + 0.8``; 1.4 px for ``size = 7``.
    """
    return 0.3 * ((_check_size(size) - 1) / 2 - 1) + 0.8


def _gaussian_weights(size: int, sigma: float) -> np.ndarray:
    """Normalised 1-D Gaussian weights (size,) float64, centred."""
    offsets = np.arange(size) - (size - 1) / 2
    weights = np.exp(-0.5 * (offsets / sigma) ** 2)
    return weights / weights.sum()


def _correlate(image: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Separable correlation (H, W) float64 with ``weights`` along both axes, zero outside the image."""
    return cv2.sepFilter2D(image, cv2.CV_64F, weights, weights, borderType=cv2.BORDER_CONSTANT)


def _smooth_image(image: np.ndarray, weights: np.ndarray, min_weight: float) -> np.ndarray:
    """Normalised convolution (H, W) float64 of one image; NaN = missing (module docstring)."""
    valid = np.isfinite(image)
    numerator = _correlate(np.where(valid, image, 0.0), weights)
    mass = _correlate(valid.astype(np.float64), weights)
    out = np.full(image.shape, np.nan)
    np.divide(numerator, mass, out=out, where=valid & (mass >= min_weight))
    return out


def _local_std_image(image: np.ndarray, size: int, ddof: int, min_count: int) -> np.ndarray:
    """Standard deviation (H, W) float64 over the finite pixels of each ``size x size`` box."""
    valid = np.isfinite(image)
    centre = image[valid].mean() if valid.any() else 0.0
    values = np.where(valid, image - centre, 0.0)
    ones = np.ones(size)
    count = _correlate(valid.astype(np.float64), ones)
    total = _correlate(values, ones)
    squares = _correlate(values * values, ones)
    out = np.full(image.shape, np.nan)
    keep = valid & (count >= max(min_count, ddof + 1))
    np.divide(squares - total * total / np.where(keep, count, 1.0), count - ddof, out=out, where=keep)
    return np.sqrt(np.maximum(out, 0.0))


def _per_image(data: np.ndarray, kernel, out_dtype, **kwargs) -> np.ndarray:
    """``kernel`` applied to every (y, x) image of ``data`` (..., y, x), into an array of ``out_dtype``."""
    out = np.empty(data.shape, dtype=out_dtype)
    if data.size:
        for index in np.ndindex(data.shape[:-2]):
            out[index] = kernel(data[index], **kwargs)
    return out


def _over_images(data, kernel, radius: int, boundary, dtype, **kwargs):
    """:func:`_per_image` on a numpy array, or lazily on a dask array with a halo of ``radius``.

    ``boundary`` is the value outside the image that the kernel treats as missing
    (NaN for measurements, -1 for labels), so a chunk's halo beyond the image
    border changes nothing.
    """
    if isinstance(data, np.ndarray):
        return _per_image(data, kernel, dtype, **kwargs)
    import dask.array as da

    image_axes = (data.ndim - 2, data.ndim - 1)
    # an image axis no longer than the halo is taken whole; one in a single chunk needs no halo
    data = data.rechunk({axis: -1 for axis in image_axes if data.shape[axis] <= radius})
    halo = [axis for axis in image_axes if len(data.chunks[axis]) > 1]
    depth = {axis: radius if axis in halo else 0 for axis in range(data.ndim)}
    bounds = {axis: boundary if axis in halo else "none" for axis in range(data.ndim)}
    return da.map_overlap(
        _per_image,
        data,
        depth=depth,
        boundary=bounds,
        dtype=dtype,
        meta=np.empty((0,) * data.ndim, dtype=dtype),
        kernel=kernel,
        out_dtype=dtype,
        **kwargs,
    )


def _image_filter(arr: xr.DataArray, kernel, radius: int, boundary, dtype, **kwargs) -> xr.DataArray:
    """Apply an image kernel over the (y, x) plane of ``arr``, any other dims looped, lazily on dask."""
    out = xr.apply_ufunc(
        _over_images,
        arr,
        input_core_dims=[["y", "x"]],
        output_core_dims=[["y", "x"]],
        kwargs={"kernel": kernel, "radius": radius, "boundary": boundary, "dtype": dtype, **kwargs},
        dask="allowed",
        keep_attrs=False,
    )
    return out.transpose(*arr.dims)


def _as_float(arr: xr.DataArray, name: str) -> xr.DataArray:
    if not {"y", "x"} <= set(arr.dims):
        raise ValueError(f"{name} must have dims (..., y, x), got {arr.dims}")
    return arr.astype(np.float64)


def smooth(
    da: xr.DataArray,
    size: int = DEFAULT_SIZE,
    *,
    sigma: float | None = None,
    min_weight: float = DEFAULT_MIN_FRACTION,
) -> xr.DataArray:
    """NaN-aware Gaussian smoothing by normalised convolution.

    Parameters
    ----------
    da : (..., y, x) DataArray
        Image(s); NaN marks a missing pixel. Dims other than y, x are looped over.
    size : int, default 7
        Odd side of the square kernel, pixels.
    sigma : float, optional
        Standard deviation of the Gaussian, pixels; default :func:`gaussian_sigma` of ``size``.
    min_weight : float, default 0.25
        Minimum share of the (unit) kernel mass that the finite pixels of a
        window must carry; below it the pixel is NaN.

    Returns
    -------
    (..., y, x) DataArray of float64
        ``G * (v m) / G * m``; NaN where ``da`` is NaN or the window is too
        empty. Same units as ``da``; attrs ``smoothing_size``,
        ``smoothing_sigma``. Lazy on dask input.
    """
    size = _check_size(size)
    sigma = gaussian_sigma(size) if sigma is None else float(sigma)
    if not sigma > 0:
        raise ValueError(f"sigma must be positive (pixels), got {sigma!r}")
    if not 0 < min_weight <= 1:
        raise ValueError(f"min_weight must be in (0, 1] (share of the kernel mass), got {min_weight!r}")
    out = _image_filter(
        _as_float(da, "da"),
        _smooth_image,
        size // 2,
        np.nan,
        np.float64,
        weights=_gaussian_weights(size, sigma),
        min_weight=float(min_weight),
    )
    out.attrs = {**da.attrs, "smoothing_size": size, "smoothing_sigma": sigma}
    return out


def local_std(
    da: xr.DataArray,
    size: int = DEFAULT_SIZE,
    *,
    ddof: int = 1,
    min_count: int | None = None,
) -> xr.DataArray:
    """NaN-aware standard deviation over the ``size x size`` box around each pixel.

    Parameters
    ----------
    da : (..., y, x) DataArray
        Image(s); NaN marks a missing pixel. Dims other than y, x are looped over.
    size : int, default 7
        Odd side of the box, pixels.
    ddof : int, default 1
        Delta degrees of freedom: the variance divides by ``count - ddof``
        (1: unbiased variance, 0: the biased ``np.nanstd`` default).
    min_count : int, optional
        Minimum number of finite pixels in the box (and always more than
        ``ddof``); default ``ceil(0.25 size^2)``, 13 for 7 x 7.

    Returns
    -------
    (..., y, x) DataArray of float64
        Local standard deviation, same units as ``da``; NaN where ``da`` is NaN
        or the box holds too few finite pixels. Attrs ``window_size``, ``ddof``,
        ``min_count``. Lazy on dask input.
    """
    size = _check_size(size)
    if min_count is None:
        min_count = math.ceil(DEFAULT_MIN_FRACTION * size * size)
    for name, value in (("ddof", ddof), ("min_count", min_count)):
        if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 0:
            raise ValueError(f"{name} must be a non-negative integer, got {value!r}")
    out = _image_filter(
        _as_float(da, "da"),
        _local_std_image,
        size // 2,
        np.nan,
        np.float64,
        size=size,
        ddof=int(ddof),
        min_count=int(min_count),
    )
    out.attrs = {
        **({"units": da.attrs["units"]} if "units" in da.attrs else {}),
        "long_name": f"local standard deviation over {size}x{size} pixels",
        "window_size": size,
        "ddof": int(ddof),
        "min_count": int(min_count),
    }
    return out


def select_roi(obj: xr.DataArray | xr.Dataset, roi: Roi) -> xr.DataArray | xr.Dataset:
    """The pixels of ``obj`` inside ``roi``, selected by their sensor coordinates.

    Parameters
    ----------
    obj : DataArray or Dataset with integer sensor coordinates ``y``, ``x``
    roi : Roi
        Half-open sensor ranges.

    Raises
    ------
    ValueError
        The roi holds no pixel of ``obj``.
    """
    index = {}
    for dim, (start, stop) in (("y", roi.y), ("x", roi.x)):
        coord = obj[dim].values
        index[dim] = np.flatnonzero((coord >= start) & (coord < stop))
        if index[dim].size == 0:
            span = f"{coord.min()}..{coord.max()}" if coord.size else "empty"
            raise ValueError(f"roi {roi} holds no pixel of the grid ({dim} = {span})")
    return obj.isel(index)


def most_perpendicular_view(aoi: xr.DataArray, region: Roi | None = None):
    """The view that sees the surface closest to normal incidence.

    Parameters
    ----------
    aoi : (view, y, x) DataArray, radians
        Angle of incidence of each view; NaN = missing.
    region : Roi, optional
        Sensor pixels to judge by (the item's roi); default all pixels.

    Returns
    -------
    view label
        The ``view`` coordinate value (view file stem) of the view with the
        smallest median AOI over the finite pixels of ``region``.

    Raises
    ------
    ValueError
        No view has a finite AOI in the region.
    """
    _check_grid(aoi, "aoi", ("view", "y", "x"))
    part = aoi if region is None else select_roi(aoi, region)
    values = part.transpose("view", "y", "x").values.reshape(part.sizes["view"], -1)
    finite = np.isfinite(values)
    medians = np.array([np.median(row[ok]) if ok.any() else np.inf for row, ok in zip(values, finite)])
    if not np.isfinite(medians).any():
        where = "anywhere" if region is None else f"in {region}"
        raise ValueError(f"no view has a finite angle of incidence {where}")
    return aoi["view"][int(np.argmin(medians))].item()


def variability(
    reflectance: xr.DataArray,
    aoi: xr.DataArray,
    size: int = DEFAULT_SIZE,
    *,
    ddof: int = 1,
    min_count: int | None = None,
) -> xr.DataArray:
    """Spatial reflectance variability of one view: local std of ``R / cos(theta)``.

    Parameters
    ----------
    reflectance : (y, x) DataArray
        Reflectance of one view (the most perpendicular one, see
        :func:`most_perpendicular_view`) on that view's own pixel grid; NaN = missing.
    aoi : (y, x) DataArray, radians
        Angle of incidence of the same view on the same grid.
    size, ddof, min_count
        As for :func:`local_std`.

    Returns
    -------
    (y, x) DataArray of float64
        Local standard deviation of the Lambert-corrected reflectance, units
        ``"1"``; NaN where either input is missing or the AOI is >= 90 deg.
        Warp it onto the reference grid afterwards, not before (module docstring).
    """
    _check_grid(reflectance, "reflectance")
    _check_grid(aoi, "aoi")
    try:
        reflectance, aoi = xr.align(reflectance, aoi, join="exact")
    except ValueError as exc:
        raise ValueError(f"variability: reflectance and aoi must be on the same (y, x) grid ({exc})") from exc
    cosine = np.cos(aoi.astype(np.float64))
    corrected = (reflectance / cosine).where(cosine > 0)
    out = local_std(corrected, size, ddof=ddof, min_count=min_count)
    out.attrs.update(
        units="1",
        long_name=f"spatial reflectance variability: local standard deviation of R / cos(AOI), {size}x{size} pixels",
    )
    return out


def features(
    fit: xr.Dataset,
    variability: xr.DataArray,
    *,
    size: int = DEFAULT_SIZE,
    sigma: float | None = None,
    min_weight: float = DEFAULT_MIN_FRACTION,
) -> xr.Dataset:
    """The classification features of an item on its reference grid.

    Parameters
    ----------
    fit : Dataset
        Output of :func:`surffin.scattering.fit_scattering`: ``R0``, ``n`` and
        the per-pixel quality (y, x).
    variability : (y, x) DataArray
        Output of :func:`variability`, already warped onto the grid of ``fit``.
    size, sigma, min_weight
        Smoothing of R0 and n, as for :func:`smooth`.

    Returns
    -------
    Dataset (y, x)
        ``R0``, ``n`` (smoothed), ``variability`` (the features); ``R0_fit``,
        ``n_fit`` (unsmoothed) and the quality variables of :data:`QUALITY`
        present in ``fit``. Attrs ``smoothing_size``, ``smoothing_sigma``,
        ``min_weight``. Lazy on dask input.
    """
    missing = [name for name in ("R0", "n") if name not in fit]
    if missing:
        raise ValueError(f"features: fit lacks {missing}; pass the Dataset of fit_scattering")
    _check_grid(variability, "variability")
    try:
        xr.align(fit, variability, join="exact")
    except ValueError as exc:
        raise ValueError(f"features: variability is not on the grid of the fit ({exc}); warp it first") from exc
    smoothed = {
        name: smooth(fit[name], size, sigma=sigma, min_weight=min_weight).assign_attrs(
            units="1", long_name=f"{long_name} (Gaussian-smoothed {size}x{size})"
        )
        for name, long_name in (("R0", "reflectance at normal incidence"), ("n", "scattering coefficient"))
    }
    sigma = smoothed["R0"].attrs["smoothing_sigma"]
    ds = xr.Dataset(
        {
            **smoothed,
            "variability": variability.assign_attrs(
                units="1", long_name=variability.attrs.get("long_name", "spatial reflectance variability")
            ),
            "R0_fit": fit["R0"],
            "n_fit": fit["n"],
            **{name: fit[name] for name in QUALITY if name in fit},
        }
    )
    ds.attrs = {"smoothing_size": size, "smoothing_sigma": sigma, "min_weight": float(min_weight)}
    return ds
