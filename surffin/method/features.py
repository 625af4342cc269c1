"""Feature images of an item (method step 5): smoothed R0 and n, their uncertainties, the variability.

All features are neighbourhood operations on (y, x) images that ignore missing
(NaN) pixels and treat the image border like a hole:

- :func:`smooth`: Gaussian smoothing by normalised convolution, the paper's
  "Gaussian filter of size 7 x 7" with OpenCV's sigma for that size.
- :func:`smooth_uncertainty`: the standard uncertainty of the smoothed R0 and n,
  propagated from the fit's per-pixel uncertainties with the spatial correlation
  of the fit's residuals: the errors of neighbouring pixels (AOI, registration,
  calibration) are neither independent nor fully correlated (``docs/performance.md``).
- :func:`local_std`: standard deviation over the finite pixels of a box, from
  centred float64 box sums; unbiased by default, so that it does not depend on
  the pattern of missing pixels.
- :func:`variability`: :func:`local_std` of ``R / cos(theta)`` (Lambert
  correction) of one view on its own pixel grid. Resampling a view onto the
  reference grid averages neighbouring pixels and lowers their spread, so the
  variability is computed before the warp and warped afterwards (METHOD.md).

Under dask every operation runs chunk by chunk with ``dask.array.map_overlap``:
each chunk gets a halo of ``size // 2`` pixels from its neighbours and NaN outside
the image, which the kernels treat exactly like the zero border they use on a
whole image, so the result equals the numpy path for any chunking to rounding (a
few ulp: OpenCV's vectorised and scalar loops round differently, and
:func:`local_std` centres each chunk on its own mean).
"""

from __future__ import annotations

import math
import numbers

import cv2
import numpy as np
import xarray as xr

from surffin.grid import Roi

__all__ = [
    "DEFAULT_SIZE",
    "DEFAULT_MIN_FRACTION",
    "QUALITY",
    "UNCERTAINTY",
    "check_size",
    "check_grid",
    "image_filter",
    "gaussian_sigma",
    "smooth",
    "smooth_uncertainty",
    "residual_correlation",
    "variance_inflation",
    "local_std",
    "select_roi",
    "feature_window",
    "views_by_incidence",
    "first_available",
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
#: Smoothed feature -> the fit's standard uncertainty it is propagated from (:func:`features`).
UNCERTAINTY = {"R0": "R0_sigma", "n": "n_sigma"}
# Residuals beyond this many robust standard deviations are outliers in residual_correlation.
_RESIDUAL_CLIP = 5.0


def check_size(size) -> int:
    """Check a window side: an odd positive integer.

    Parameters
    ----------
    size : int
        Window side, pixels.

    Returns
    -------
    int

    Raises
    ------
    ValueError
        ``size`` is not an odd positive integer.
    """
    if isinstance(size, bool) or not isinstance(size, numbers.Integral) or size < 1 or size % 2 == 0:
        raise ValueError(f"size must be an odd positive integer (window side, pixels), got {size!r}")
    return int(size)


def check_grid(arr, name: str, dims=("y", "x")) -> None:
    """Check that an argument is a DataArray over exactly the dims ``dims`` (in any order).

    Parameters
    ----------
    arr : object
        The argument.
    name : str
        Its name, for the error message.
    dims : tuple of str
        The dims it must have.

    Raises
    ------
    TypeError
        ``arr`` is not a DataArray.
    ValueError
        Its dims are not ``dims``.
    """
    if not isinstance(arr, xr.DataArray):
        raise TypeError(f"{name} must be an xarray.DataArray with dims {dims}, got {type(arr).__name__}")
    if set(arr.dims) != set(dims):
        raise ValueError(f"{name} must have dims {dims}, got {arr.dims}")


def gaussian_sigma(size: int) -> float:
    """Compute the standard deviation, pixels, of the Gaussian kernel of side ``size`` (OpenCV's rule).

    ``sigma = 0.3 ((size - 1) / 2 - 1) + 0.8``; 1.4 px for ``size = 7``.
    """
    return 0.3 * ((check_size(size) - 1) / 2 - 1) + 0.8


def _smoothing(size, sigma, min_weight=None) -> tuple[int, float, np.ndarray]:
    """Return a smoothing's checked window side, Gaussian sigma (default: :func:`gaussian_sigma`) and 1-D weights."""
    size = check_size(size)
    sigma = gaussian_sigma(size) if sigma is None else float(sigma)
    if not sigma > 0:
        raise ValueError(f"sigma must be positive (pixels), got {sigma!r}")
    if min_weight is not None and not 0 < min_weight <= 1:
        raise ValueError(f"min_weight must be in (0, 1] (share of the kernel mass), got {min_weight!r}")
    return size, sigma, _gaussian_weights(size, sigma)


def _gaussian_weights(size: int, sigma: float) -> np.ndarray:
    """Normalised 1-D Gaussian weights (size,) float64, centred."""
    offsets = np.arange(size) - (size - 1) / 2
    weights = np.exp(-0.5 * (offsets / sigma) ** 2)
    return weights / weights.sum()


def _correlate(image: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Separable correlation (H, W) float64 with ``weights`` along both axes, zero outside the image."""
    return cv2.sepFilter2D(image, cv2.CV_64F, weights, weights, borderType=cv2.BORDER_CONSTANT)


def _smooth_image(image: np.ndarray, weights: np.ndarray, min_weight: float) -> np.ndarray:
    """Normalised convolution (H, W) float64 of one image; NaN = missing (:func:`smooth`)."""
    valid = np.isfinite(image)
    numerator = _correlate(np.where(valid, image, 0.0), weights)
    mass = _correlate(valid.astype(np.float64), weights)
    out = np.full(image.shape, np.nan)
    np.divide(numerator, mass, out=out, where=valid & (mass >= min_weight))
    return out


def _local_std_image(
    image: np.ndarray,
    noise: np.ndarray | None = None,
    *,
    size: int,
    ddof: int,
    min_count: int,
    region: tuple[slice, slice] | None = None,
) -> np.ndarray:
    """Compute the standard deviation (H, W) float64 over the finite pixels of each ``size x size`` box.

    With ``noise`` (a variance image), the box's mean noise variance is taken
    out of the variance first; a pixel without a noise variance is missing.
    With ``region`` (row and column slices, their start before their stop in the
    image), only its pixels get a value, the whole image's to the bit, NaN elsewhere:
    the image is centred as a whole, and the box sums, which read nothing
    outside a box, run on the region and the ``size // 2`` pixels around it.
    """
    valid = np.isfinite(image)
    if noise is not None:
        valid &= np.isfinite(noise)
    centre = image[valid].mean() if valid.any() else 0.0
    if region is None:
        return _box_std(image, noise, valid, centre, size=size, ddof=ddof, min_count=min_count)
    out = np.full(image.shape, np.nan)
    around = tuple(slice(max(part.start - size // 2, 0), part.stop + size // 2) for part in region)
    inner = tuple(slice(part.start - big.start, part.stop - big.start) for part, big in zip(region, around))
    part_noise = None if noise is None else noise[around]
    box = _box_std(image[around], part_noise, valid[around], centre, size=size, ddof=ddof, min_count=min_count)
    out[region] = box[inner]
    return out


def _box_std(
    image: np.ndarray,
    noise: np.ndarray | None,
    valid: np.ndarray,
    centre: float,
    *,
    size: int,
    ddof: int,
    min_count: int,
) -> np.ndarray:
    """:func:`_local_std_image` of the pixels ``valid`` of ``image`` centred on ``centre``."""
    values = image - centre
    np.copyto(values, 0.0, where=~valid)
    ones = np.ones(size)
    count = _correlate(valid.astype(np.float64), ones)
    total = _correlate(values, ones)
    squares = _correlate(np.multiply(values, values, out=values), ones)
    keep = count >= max(min_count, ddof + 1)
    keep &= valid
    safe = np.where(keep, count, 1.0)
    # variance = (squares - total^2 / safe) / (count - ddof), in place
    variance = squares
    total *= total
    variance -= np.divide(total, safe, out=total)
    count -= ddof
    np.copyto(count, 1.0, where=~keep)
    variance /= count
    if noise is not None:
        mean_noise = _correlate(np.where(valid, noise, 0.0), ones)
        variance -= np.divide(mean_noise, safe, out=mean_noise)
    np.sqrt(np.maximum(variance, 0.0, out=variance), out=variance)
    np.copyto(variance, np.nan, where=~keep)
    return variance


def _variability_image(
    reflectance: np.ndarray,
    aoi: np.ndarray,
    relative_noise: np.ndarray | None = None,
    *,
    region: tuple[slice, slice] | None = None,
    **kwargs,
) -> np.ndarray:
    """:func:`_local_std_image` (H, W) of the Lambert-corrected reflectance ``R / cos(aoi)`` (:func:`variability`).

    With ``relative_noise``, the variance of the corrected reflectance's noise is taken out.
    An empty ``region`` is all NaN, computed from nothing.
    """
    if region is not None and any(part.start >= part.stop for part in region):
        return np.full(reflectance.shape, np.nan)
    cosine = aoi.astype(np.float64)
    np.cos(cosine, out=cosine)
    corrected = reflectance / cosine
    np.copyto(corrected, np.nan, where=~(cosine > 0))
    variance = None
    if relative_noise is not None:
        variance = np.multiply(corrected, relative_noise)
        np.square(variance, out=variance)
    return _local_std_image(corrected, variance, region=region, **kwargs)


def _per_image(*data: np.ndarray, kernel, out_dtype, **kwargs) -> np.ndarray:
    """``kernel`` applied to every (y, x) image of the arrays ``data`` (..., y, x) of one shape.

    The kernel takes one image of each array, in order, and returns one image
    of ``out_dtype``.
    """
    out = np.empty(data[0].shape, dtype=out_dtype)
    if data[0].size:
        for index in np.ndindex(data[0].shape[:-2]):
            out[index] = kernel(*(part[index] for part in data), **kwargs)
    return out


def _over_images(*data, kernel, radius: int, boundary, dtype, **kwargs):
    """:func:`_per_image` on numpy arrays, or lazily on dask arrays with a halo of ``radius``.

    ``boundary`` is the value outside the image that the kernel treats as missing
    (NaN for measurements, -1 for labels), so a chunk's halo beyond the image
    border changes nothing. Several dask arrays are cut into the chunks of the first.
    """
    if all(isinstance(part, np.ndarray) for part in data):
        return _per_image(*data, kernel=kernel, out_dtype=dtype, **kwargs)
    import dask.array as da

    first = da.asarray(data[0])
    image_axes = (first.ndim - 2, first.ndim - 1)
    # an image axis no longer than the halo is taken whole; one in a single chunk needs no halo
    first = first.rechunk({axis: -1 for axis in image_axes if first.shape[axis] <= radius})
    data = [first, *(da.asarray(part).rechunk(first.chunks) for part in data[1:])]
    halo = [axis for axis in image_axes if len(first.chunks[axis]) > 1]
    depth = {axis: radius if axis in halo else 0 for axis in range(first.ndim)}
    bounds = {axis: boundary if axis in halo else "none" for axis in range(first.ndim)}
    return da.map_overlap(
        _per_image,
        *data,
        depth=depth,
        boundary=bounds,
        dtype=dtype,
        meta=np.empty((0,) * first.ndim, dtype=dtype),
        kernel=kernel,
        out_dtype=dtype,
        **kwargs,
    )


def image_filter(arr, kernel, radius: int, boundary, dtype, **kwargs) -> xr.DataArray:
    """Apply an image kernel over the (y, x) plane, any other dims looped, lazily on dask.

    Parameters
    ----------
    arr : DataArray or sequence of DataArray
        One DataArray, or several on one grid whose images the kernel takes together.
    kernel : callable
        ``kernel(*images, **kwargs)`` -> one (y, x) image, on numpy arrays: one
        image of each input, in order.
    radius : int
        Pixels of the neighbourhood the kernel reads around a pixel (the halo of dask chunks).
    boundary : scalar
        The value outside the image that the kernel treats as missing (NaN for
        measurements, -1 for labels), so a chunk's halo beyond the border changes nothing.
    dtype : dtype
        Of the result.
    **kwargs
        Passed to ``kernel``.

    Returns
    -------
    DataArray
        With the dims of the (first) input; lazy when it is.
    """
    arrays = [arr] if isinstance(arr, xr.DataArray) else list(arr)
    out = xr.apply_ufunc(
        _over_images,
        *arrays,
        input_core_dims=[["y", "x"]] * len(arrays),
        output_core_dims=[["y", "x"]],
        kwargs={"kernel": kernel, "radius": radius, "boundary": boundary, "dtype": dtype, **kwargs},
        dask="allowed",
        keep_attrs=False,
    )
    return out.transpose(*arrays[0].dims)


def _as_float(arr: xr.DataArray, name: str) -> xr.DataArray:
    if not {"y", "x"} <= set(arr.dims):
        raise ValueError(f"{name} must have dims (..., y, x), got {arr.dims}")
    return arr.astype(np.float64, copy=False)


def smooth(
    da: xr.DataArray,
    size: int = DEFAULT_SIZE,
    *,
    sigma: float | None = None,
    min_weight: float = DEFAULT_MIN_FRACTION,
) -> xr.DataArray:
    """NaN-aware Gaussian smoothing by normalised convolution.

    ``G * (v m) / G * m`` with ``m`` the mask of finite pixels. The paper uses a
    "Gaussian filter of size 7 x 7" without a sigma; the kernel here is
    ``size x size`` with OpenCV's rule for a size without a sigma (that of
    ``cv2.getGaussianKernel(size, 0)``, :func:`gaussian_sigma`), 1.4 px for
    7 x 7, so that the kernel ends at about 2.1 sigma. Unlike
    ``getGaussianKernel``, the weights are always the sampled Gaussian (OpenCV
    substitutes fixed binomial-like tables for sizes up to 7). A pixel keeps a
    value only if it was finite itself (holes are not filled) and the finite
    pixels of its window carry at least ``min_weight`` of the kernel mass;
    pixels outside the image carry none, so the borders are normalised like
    the holes.

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
    size, sigma, weights = _smoothing(size, sigma, min_weight)
    out = image_filter(
        _as_float(da, "da"),
        _smooth_image,
        size // 2,
        np.nan,
        np.float64,
        weights=weights,
        min_weight=float(min_weight),
    )
    out.attrs = {**da.attrs, "smoothing_size": size, "smoothing_sigma": sigma}
    return out


def _uncertainty_image(
    value: np.ndarray, uncertainty: np.ndarray, weights: np.ndarray, min_weight: float, inflation: float
) -> np.ndarray:
    """Compute the standard uncertainty (H, W) float64 of the normalised convolution of ``value``.

    See :func:`smooth_uncertainty`.
    """
    valid = np.isfinite(value)
    known = valid & np.isfinite(uncertainty)
    squares = weights * weights
    mass = _correlate(valid.astype(np.float64), weights)
    known_mass = _correlate(known.astype(np.float64), weights)
    known_squares = _correlate(known.astype(np.float64), squares)
    sigma = np.where(known, uncertainty, 0.0)
    keep = valid & (mass >= min_weight) & (known_mass > 0)
    out = np.full(value.shape, np.nan)
    # fully correlated errors: the weighted mean uncertainty of the pixels whose uncertainty is known
    np.divide(_correlate(sigma, weights), known_mass, out=out, where=keep)
    if math.isfinite(inflation):
        # independent errors: sqrt(sum w^2 s^2) / sum w, with the w^2-weighted mean variance of the
        # known pixels standing in for the unknown ones; scaled by sqrt(inflation), at most the bound
        variance = np.zeros(value.shape)
        np.divide(_correlate(sigma * sigma, squares), known_squares, out=variance, where=keep)
        independent = np.full(value.shape, np.nan)
        np.divide(
            np.sqrt(inflation * variance * _correlate(valid.astype(np.float64), squares)),
            mass,
            out=independent,
            where=keep,
        )
        np.minimum(out, independent, out=out, where=keep)
    return out


def smooth_uncertainty(
    da: xr.DataArray,
    uncertainty: xr.DataArray,
    size: int = DEFAULT_SIZE,
    *,
    sigma: float | None = None,
    min_weight: float = DEFAULT_MIN_FRACTION,
    inflation: float = math.inf,
) -> xr.DataArray:
    """Propagate per-pixel uncertainties to the standard uncertainty of :func:`smooth` of ``da``.

    Parameters
    ----------
    da : (..., y, x) DataArray
        The image that is smoothed; NaN marks a missing pixel.
    uncertainty : (..., y, x) DataArray
        Standard uncertainty (>= 0) of each pixel of ``da``, same units; NaN
        where unknown (e.g. a fit without residual degrees of freedom).
    size, sigma, min_weight
        The smoothing, as for :func:`smooth`.
    inflation : float, default inf
        Variance inflation factor F of the kernel for the spatial correlation
        of the pixels' errors (:func:`variance_inflation`): 1 for independent
        errors, ``inf`` for the fully correlated bound.

    Returns
    -------
    (..., y, x) DataArray of float64
        ``min(sqrt(F sum w_i^2 s_i^2) / sum w_i, sum w_i s_i / sum w_i)`` over
        the finite pixels i of each window, with the weighted mean variance
        (mean uncertainty) of the pixels whose uncertainty is known standing in
        for those whose is not; NaN where :func:`smooth` is NaN or no pixel of
        the window has a known uncertainty. Attrs ``smoothing_size``,
        ``smoothing_sigma`` and ``inflation`` (when finite). Lazy on dask input.

    Notes
    -----
    The smoothed value is ``sum w_i v_i / sum w_i`` over the finite pixels i of
    the window, and the fit gives each pixel a standard uncertainty s_i
    (``R0_sigma``, ``n_sigma``: the fit covariance scaled by the residual
    variance). With independent errors the smoothed value's uncertainty would be
    ``sqrt(sum w_i^2 s_i^2) / sum w_i``; with fully correlated errors it is
    ``sum w_i s_i / sum w_i``. Neither holds: the AOI comes from overlapping
    plane-fit windows (15 x 15 px), registration interpolates, the calibration
    is spatially smooth. Between the two, with a correlation rho(d) of the
    errors of two pixels d apart, the variance is F times the independent one
    (:func:`variance_inflation`; 1 for independent errors, 23.6 for fully
    correlated ones under the 7 x 7 kernel). :func:`features` measures rho on
    the item itself, as the spatial correlation of the fit's residuals pooled
    over the views (:func:`residual_correlation`): the residuals are the part
    of the per-view errors the fit does not absorb and share their spatial
    structure. The uncertainty is ``sqrt(F sum w_i^2 s_i^2) / sum w_i``, at most
    the fully correlated bound. F is computed for the full kernel and used near
    holes and borders too.

    The s_i^2 of a 5-view fit have only 3 degrees of freedom (alone, s_i covers
    like Student's t with its pixel's m - 2 degrees of freedom, m views, not
    like a normal); the window pools them (a pixel fitted from 2 views, whose
    s_i is unknown, takes the window's mean variance) into about 37 degrees of
    freedom under the 7 x 7 kernel, so the smoothed uncertainty covers nearly
    like a normal (exact variances would give 0.676 and 0.947 within 1 and 2).

    On the paper preset the residual correlation comes closest to the measured
    errors, where independent errors understate the uncertainty and the fully
    correlated bound overstates it. The residuals give one F for R0 and n that
    lies between those of their true errors, so n's uncertainty is slightly
    understated (``docs/performance.md``).
    """
    size, sigma, weights = _smoothing(size, sigma, min_weight)
    if not inflation > 0:
        raise ValueError(
            f"inflation must be positive (1: independent errors, inf: fully correlated), got {inflation!r}"
        )
    try:
        da, uncertainty = xr.align(_as_float(da, "da"), _as_float(uncertainty, "uncertainty"), join="exact", copy=False)
    except ValueError as exc:
        raise ValueError(f"smooth_uncertainty: da and uncertainty must be on one grid ({exc})") from exc
    out = image_filter(
        (da, uncertainty.transpose(*da.dims)),
        _uncertainty_image,
        size // 2,
        np.nan,
        np.float64,
        weights=weights,
        min_weight=float(min_weight),
        inflation=float(inflation),
    )
    out.attrs = {
        **({"units": uncertainty.attrs["units"]} if "units" in uncertainty.attrs else {}),
        "smoothing_size": size,
        "smoothing_sigma": sigma,
        **({"inflation": float(inflation)} if math.isfinite(inflation) else {}),
    }
    return out


def _median(values: np.ndarray) -> np.float64:
    """``np.median`` of a non-empty 1-D array of finite values, to the bit; reorders ``values`` in place.

    One selection of the upper middle value, the lower one being the largest below it:
    ``np.median`` partitions for both and again for a NaN check, ten times slower.
    """
    half = values.size // 2
    values.partition(half)
    if values.size % 2:
        return values[half]
    return (values[:half].max() + values[half]) / 2


def residual_correlation(
    reflectance: xr.DataArray, aoi: xr.DataArray, fit: xr.Dataset, max_lag: int = DEFAULT_SIZE - 1
) -> xr.DataArray:
    """Spatial correlation of the scattering fit's residuals, pooled over the views.

    Residuals ``R - R0 cos((2 - 1/n) theta)^n`` of the pixels fitted with
    residual degrees of freedom (status 0, more than two views); those farther
    than 5 robust standard deviations (1.4826 MAD) from their view's median are
    left out. The correlation is not centred: an error shared by all pixels is
    a correlated error.

    Parameters
    ----------
    reflectance, aoi : (view, y, x) DataArray
        The registered views the fit was made from (aoi in radians).
    fit : Dataset (y, x)
        Output of :func:`surffin.method.scattering.fit_scattering` (``R0``, ``n``,
        ``status``, ``n_views``).
    max_lag : int, default 6
        Largest lag, pixels, along y and x.

    Returns
    -------
    (lag_y, lag_x) DataArray of float64
        ``sum r(p) r(p + d) / N(d)`` over pixel pairs and views, divided by its
        value at lag 0, for lags -max_lag..max_lag; NaN without residuals (no
        pixel fitted from more than two views) and at lags without a pixel
        pair. Attr ``n_residuals``. Computed eagerly.
    """
    import scipy.fft

    from surffin.method.scattering import scattering_model

    if isinstance(max_lag, bool) or not isinstance(max_lag, numbers.Integral) or max_lag < 0:
        raise ValueError(f"max_lag must be a non-negative integer (pixels), got {max_lag!r}")
    check_grid(reflectance, "reflectance", ("view", "y", "x"))
    check_grid(aoi, "aoi", ("view", "y", "x"))
    missing = [name for name in ("R0", "n", "status", "n_views") if name not in fit]
    if missing:
        raise ValueError(f"residual_correlation: fit lacks {missing}; pass the Dataset of fit_scattering")
    try:
        reflectance, aoi, fit = xr.align(reflectance, aoi, fit, join="exact", copy=False)
    except ValueError as exc:
        raise ValueError(f"residual_correlation: the views and the fit must be on one grid ({exc})") from exc
    order = ("view", "y", "x")
    r = np.asarray(reflectance.transpose(*order).values, dtype=np.float64)
    theta = np.asarray(aoi.transpose(*order).values, dtype=np.float64)
    image = fit[["R0", "n", "status", "n_views"]].transpose("y", "x").compute()
    usable = (image["status"].values == 0) & (image["n_views"].values > 2)
    with np.errstate(invalid="ignore"):
        residual = scattering_model(theta, image["R0"].values[None], image["n"].values[None])
        np.subtract(r, residual, out=residual)
    # circular autocorrelation by FFT; max_lag zeros of padding keep the wrap-around out of the lags kept
    shape = [scipy.fft.next_fast_len(length + max_lag, real=True) for length in residual.shape[1:]]
    lags = np.arange(-max_lag, max_lag + 1)
    index = np.ix_(lags % shape[0], lags % shape[1])

    def autocorrelation(images):
        """Sum over ``images`` (image, y, x), zero-padded to ``shape``, of their autocorrelations at the lags kept."""
        if not len(images):
            return np.zeros((lags.size, lags.size))
        spectrum = scipy.fft.rfft2(images)
        power = (spectrum.real * spectrum.real + spectrum.imag * spectrum.imag).sum(axis=0)
        return scipy.fft.irfft2(power, shape)[index]

    # the kept residuals and their masks, written straight into the zero padding
    kept, masks = np.zeros((2, len(residual), *shape))
    height, width = residual.shape[1:]
    count = 0
    for view in residual:
        ok = usable & np.isfinite(view)
        if not ok.any():
            continue
        median = _median(view[ok])
        deviation = view[ok] - median
        spread = 1.4826 * _median(np.abs(deviation, out=deviation))
        ok &= np.abs(view - median) <= _RESIDUAL_CLIP * spread
        np.copyto(kept[count, :height, :width], view, where=ok)
        masks[count, :height, :width] = ok
        count += 1
    numerator = autocorrelation(kept[:count])
    pairs = np.round(autocorrelation(masks[:count]))
    centre = (max_lag, max_lag)
    covariance = np.full_like(numerator, np.nan)
    np.divide(numerator, pairs, out=covariance, where=pairs > 0)
    correlation = covariance / covariance[centre] if covariance[centre] > 0 else np.full_like(covariance, np.nan)
    return xr.DataArray(
        correlation,
        dims=("lag_y", "lag_x"),
        coords={"lag_y": lags, "lag_x": lags},
        attrs={
            "units": "1",
            "long_name": "spatial correlation of the scattering fit's residuals, pooled over the views",
            "n_residuals": int(pairs[centre]),
        },
    )


def variance_inflation(correlation: xr.DataArray, size: int = DEFAULT_SIZE, *, sigma: float | None = None) -> float:
    """Variance inflation factor of the smoothing kernel for spatially correlated errors.

    ``F = sum_ij w_i w_j rho(i - j) / sum_i w_i^2`` over the pixels of a full
    kernel: the variance of the smoothed value is F times that of independent
    errors, and ``(sum w)^2 / (F sum w^2)`` is the effective number of
    independent pixels in the window. F is 1 for independent errors and
    ``(sum w)^2 / sum w^2`` (23.6 for 7 x 7) for fully correlated ones.

    Parameters
    ----------
    correlation : (lag_y, lag_x) DataArray
        Correlation of the errors of two pixels at each lag (e.g.
        :func:`residual_correlation`), covering lags ``-(size - 1)..size - 1``.
    size, sigma
        The smoothing kernel, as for :func:`smooth`.

    Returns
    -------
    float
        F; NaN where ``correlation`` is.
    """
    size, sigma, weights = _smoothing(size, sigma)
    reach = size - 1
    check_grid(correlation, "correlation", ("lag_y", "lag_x"))
    lags = np.arange(-reach, reach + 1)
    try:
        rho = correlation.sel(lag_y=lags, lag_x=lags).transpose("lag_y", "lag_x").values
    except KeyError as exc:
        raise ValueError(f"correlation must cover lags -{reach}..{reach} for a {size}x{size} kernel ({exc})") from exc
    # The kernel is separable, and so is its autocorrelation (what scipy.signal.correlate2d
    # of the kernel with itself gives; importing scipy.signal costs a job ~1 s).
    autocorrelation = np.correlate(weights, weights, mode="full")
    kernel = np.outer(weights, weights)
    return float((np.outer(autocorrelation, autocorrelation) * rho).sum() / (kernel * kernel).sum())


def local_std(
    da: xr.DataArray,
    size: int = DEFAULT_SIZE,
    *,
    ddof: int = 1,
    min_count: int | None = None,
    noise_variance: xr.DataArray | None = None,
) -> xr.DataArray:
    """NaN-aware standard deviation over the ``size x size`` box around each pixel.

    Computed from box sums of the count, ``v - c`` and ``(v - c)^2``, in float64
    and centred on the mean ``c`` of the image (of the chunk, with its halo,
    under dask) so that the sum of squares does not cancel: the relative error
    of the variance is about ``1e-16 (mu - c)^2 / sigma^2`` with ``mu`` the
    window's mean. The default is the unbiased variance (``ddof=1``): windows
    near holes and borders hold fewer pixels, and the biased estimate would
    shrink with the count, making the feature depend on the pattern of missing
    pixels.

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
    noise_variance : DataArray, optional
        Variance of each pixel's noise, on the grid of ``da``: the box's mean
        is subtracted from its variance (clipped at 0), which leaves the
        spread of the signal under the noise. Pixels without it count as missing.

    Returns
    -------
    (..., y, x) DataArray of float64
        Local standard deviation, same units as ``da``; NaN where ``da`` is NaN
        or the box holds too few finite pixels. Attrs ``window_size``, ``ddof``,
        ``min_count``, ``noise_corrected``. Lazy on dask input.
    """
    size, ddof, min_count = _std_window(size, ddof, min_count)
    images = _as_float(da, "da")
    if noise_variance is not None:
        try:
            images = list(xr.align(images, _as_float(noise_variance, "noise_variance"), join="exact", copy=False))
        except ValueError as exc:
            raise ValueError(f"local_std: da and noise_variance must be on the same grid ({exc})") from exc
    out = image_filter(
        images, _local_std_image, size // 2, np.nan, np.float64, size=size, ddof=ddof, min_count=min_count
    )
    out.attrs = {
        **({"units": da.attrs["units"]} if "units" in da.attrs else {}),
        "long_name": f"local standard deviation over {size}x{size} pixels",
        **_std_attrs(size, ddof, min_count, noise_variance is not None),
    }
    return out


def _std_window(size, ddof, min_count) -> tuple[int, int, int]:
    """Check the window arguments of :func:`local_std`; return ``size``, ``ddof``, ``min_count`` (or its default)."""
    size = check_size(size)
    if min_count is None:
        min_count = math.ceil(DEFAULT_MIN_FRACTION * size * size)
    for name, value in (("ddof", ddof), ("min_count", min_count)):
        if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 0:
            raise ValueError(f"{name} must be a non-negative integer, got {value!r}")
    return size, int(ddof), int(min_count)


def _std_attrs(size: int, ddof: int, min_count: int, noise_corrected: bool) -> dict:
    """Attrs of a :func:`local_std` result that describe its window."""
    return {"window_size": size, "ddof": ddof, "min_count": min_count, "noise_corrected": int(noise_corrected)}


def select_roi(obj: xr.DataArray | xr.Dataset, roi: Roi) -> xr.DataArray | xr.Dataset:
    """Select the pixels of ``obj`` inside ``roi`` by their sensor coordinates.

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
        inside = np.flatnonzero((coord >= start) & (coord < stop))
        if inside.size == 0:
            span = f"{coord.min()}..{coord.max()}" if coord.size else "empty"
            raise ValueError(f"roi {roi} holds no pixel of the grid ({dim} = {span})")
        # a run of positions is a slice: on dask arrays a slice is a view, a list of positions a shuffle
        contiguous = inside[-1] - inside[0] + 1 == inside.size
        index[dim] = slice(inside[0], inside[-1] + 1) if contiguous else inside
    return obj.isel(index)


def feature_window(roi: Roi, size: int, grid: Roi) -> Roi:
    """Return the reference pixels that :func:`features` of the pixels in ``roi`` read: ``roi`` and ``size // 2`` more.

    The fit is per pixel and the variability per view, on that view's own grid, warped pixel by pixel; the
    smoothing of R0 and n and the propagation of their uncertainties read ``size // 2`` pixels around each
    pixel and treat the grid's border like a hole. On this window, clipped to the item's ``grid``, every
    pixel of ``roi`` sees what it sees on the whole grid.

    Parameters
    ----------
    roi : Roi
        The pixels whose features are wanted (a specimen's roi).
    size : int
        Side of the smoothing window, pixels (:func:`smooth`).
    grid : Roi
        The item's whole reference grid (its crop).

    Raises
    ------
    ValueError
        ``roi`` does not overlap ``grid``.
    """
    return roi.grown(check_size(size) // 2).clip(grid)


def views_by_incidence(aoi: xr.DataArray, region: Roi | None = None) -> list:
    """Order the views from the one that sees the surface closest to normal incidence to the most oblique.

    Parameters
    ----------
    aoi : (view, y, x) DataArray, radians
        Angle of incidence of each view; NaN = missing.
    region : Roi, optional
        Sensor pixels to judge by (the item's roi); default all pixels.

    Returns
    -------
    list of view labels
        The ``view`` coordinate values (view file stems) in the order of their
        median AOI over the finite pixels of ``region``; views with no finite
        AOI there come last, in their own order.

    Raises
    ------
    ValueError
        No view has a finite AOI in the region.
    """
    check_grid(aoi, "aoi", ("view", "y", "x"))
    part = aoi if region is None else select_roi(aoi, region)
    values = part.transpose("view", "y", "x").values.reshape(part.sizes["view"], -1)
    finite = np.isfinite(values)
    medians = np.array([_median(row[ok]) if ok.any() else np.inf for row, ok in zip(values, finite)])
    if not np.isfinite(medians).any():
        where = "anywhere" if region is None else f"in {region}"
        raise ValueError(f"no view has a finite angle of incidence {where}")
    return [aoi["view"][int(index)].item() for index in np.argsort(medians, kind="stable")]


def first_available(data: xr.DataArray) -> tuple[xr.DataArray, xr.DataArray]:
    """Per pixel, the value of the first view (in ``view`` order) that has one.

    Parameters
    ----------
    data : (view, y, x) DataArray
        NaN = missing.

    Returns
    -------
    values : (y, x) DataArray
        NaN where no view has a value; attrs of ``data``.
    source : (y, x) DataArray of int16
        Position along ``view`` of the view each value comes from, -1 where none.
    """
    check_grid(data, "data", ("view", "y", "x"))
    data = data.transpose("view", "y", "x")
    values = data.isel(view=-1, drop=True)
    source = xr.where(np.isfinite(values), data.sizes["view"] - 1, -1).astype(np.int16)
    for index in range(data.sizes["view"] - 2, -1, -1):
        image = data.isel(view=index, drop=True)
        found = np.isfinite(image)
        values = image.where(found, values)
        source = source.where(~found, index).astype(np.int16)
    return values.assign_attrs(data.attrs), source


def variability(
    reflectance: xr.DataArray,
    aoi: xr.DataArray,
    size: int = DEFAULT_SIZE,
    *,
    ddof: int = 1,
    min_count: int | None = None,
    relative_noise: xr.DataArray | None = None,
    region: Roi | None = None,
) -> xr.DataArray:
    """Spatial reflectance variability of one view: local std of ``R / cos(theta)``.

    Parameters
    ----------
    reflectance : (y, x) DataArray
        Reflectance of one view on that view's own pixel grid; NaN = missing.
    aoi : (y, x) DataArray, radians
        Angle of incidence of the same view on the same grid.
    size, ddof, min_count
        As for :func:`local_std`.
    relative_noise : (y, x) DataArray, optional
        Relative noise standard deviation of each pixel's reflectance (the
        reflectance store's ``reflectance_noise``). Its variance is taken out
        (:func:`local_std`'s ``noise_variance``), so that the feature measures
        the surface, not how weak its return was: without it the same finish
        seen from farther off looks rougher.
    region : Roi, optional
        The pixels wanted, by their sensor coordinates (the grid's ``y`` and ``x``,
        increasing); the others are NaN. In memory, only the boxes of those are
        summed, and their values are the whole grid's to the bit.

    Returns
    -------
    (y, x) DataArray of float64
        Local standard deviation of the Lambert-corrected reflectance, units
        ``"1"``; NaN where either input is missing or the AOI is >= 90 deg.
        Warp it onto the reference grid afterwards, not before (module docstring).
    """
    check_grid(reflectance, "reflectance")
    check_grid(aoi, "aoi")
    try:
        extra = [] if relative_noise is None else [relative_noise]
        reflectance, aoi, *noise = xr.align(reflectance, aoi, *extra, join="exact", copy=False)
    except ValueError as exc:
        raise ValueError(
            f"variability: reflectance, aoi and relative_noise must be on the same (y, x) grid ({exc})"
        ) from exc
    size, ddof, min_count = _std_window(size, ddof, min_count)
    images = [reflectance, aoi, *noise]
    lazy = any(image.chunks for image in images)
    part = {}
    if region is not None and not lazy:
        spans = ((reflectance[dim].values, bounds) for dim, bounds in (("y", region.y), ("x", region.x)))
        part["region"] = tuple(slice(*(int(i) for i in np.searchsorted(coord, bounds))) for coord, bounds in spans)
    out = image_filter(
        images, _variability_image, size // 2, np.nan, np.float64, size=size, ddof=ddof, min_count=min_count, **part
    )
    if region is not None and lazy:  # computed chunk by chunk on the whole grid
        rows = (out["y"] >= region.y[0]) & (out["y"] < region.y[1])
        out = out.where(rows & (out["x"] >= region.x[0]) & (out["x"] < region.x[1]))
    out.attrs = {
        "units": "1",
        "long_name": f"spatial reflectance variability: local standard deviation of R / cos(AOI), {size}x{size} pixels"
        + (", camera noise taken out" if noise else ""),
        **_std_attrs(size, ddof, min_count, bool(noise)),
    }
    return out


def features(
    fit: xr.Dataset,
    variability: xr.DataArray,
    *,
    size: int = DEFAULT_SIZE,
    sigma: float | None = None,
    min_weight: float = DEFAULT_MIN_FRACTION,
    error_correlation: xr.DataArray | None = None,
) -> xr.Dataset:
    """Compute the classification features of an item on its reference grid, with their uncertainties.

    Parameters
    ----------
    fit : Dataset
        Output of :func:`surffin.method.scattering.fit_scattering`: ``R0``, ``n``,
        ``R0_sigma``, ``n_sigma`` and the per-pixel quality (y, x).
    variability : (y, x) DataArray
        Output of :func:`variability`, already warped onto the grid of ``fit``.
    size, sigma, min_weight
        Smoothing of R0 and n, as for :func:`smooth`.
    error_correlation : (lag_y, lag_x) DataArray, optional
        Spatial correlation of the fit's errors (:func:`residual_correlation`
        of the views the fit was made from), for the propagation of
        ``R0_sigma`` and ``n_sigma`` (:func:`smooth_uncertainty`). Without it, or when it
        is NaN (no residuals), the uncertainties are the fully correlated bound.

    Returns
    -------
    Dataset (y, x)
        ``R0``, ``n`` (smoothed), ``variability`` (the features);
        ``R0_uncertainty``, ``n_uncertainty`` (standard uncertainties of the
        smoothed R0 and n, :func:`smooth_uncertainty`); ``R0_fit``, ``n_fit``
        (unsmoothed) and the quality variables of :data:`QUALITY` present in
        ``fit``. Attrs ``smoothing_size``, ``smoothing_sigma``, ``min_weight``,
        ``uncertainty_propagation`` and, for correlated errors,
        ``uncertainty_inflation`` (F of :func:`variance_inflation`) and
        ``uncertainty_effective_pixels``. Lazy on dask input.
    """
    missing = [name for name in ("R0", "n", *UNCERTAINTY.values()) if name not in fit]
    if missing:
        raise ValueError(f"features: fit lacks {missing}; pass the Dataset of fit_scattering")
    check_grid(variability, "variability")
    try:
        xr.align(fit, variability, join="exact", copy=False)
    except ValueError as exc:
        raise ValueError(f"features: variability is not on the grid of the fit ({exc}); warp it first") from exc
    size, sigma, weights = _smoothing(size, sigma, min_weight)
    inflation = math.inf if error_correlation is None else variance_inflation(error_correlation, size, sigma=sigma)
    propagation = {"uncertainty_propagation": "fully correlated errors (upper bound)"}
    if math.isfinite(inflation):
        propagation = {
            "uncertainty_propagation": "spatially correlated errors, correlation of the fit residuals",
            "uncertainty_inflation": inflation,
            # (sum w)^2 / (F sum w^2), the 2-D weights summing to 1
            "uncertainty_effective_pixels": 1.0 / (inflation * float((weights * weights).sum()) ** 2),
        }
    else:
        inflation = math.inf  # NaN: no residuals to measure the correlation by
    long_names = {"R0": "reflectance at normal incidence", "n": "scattering coefficient"}
    smoothed, uncertainties = {}, {}
    for name, long_name in long_names.items():
        smoothed[name] = smooth(fit[name], size, sigma=sigma, min_weight=min_weight).assign_attrs(
            units="1", long_name=f"{long_name} (Gaussian-smoothed {size}x{size})"
        )
        uncertainties[f"{name}_uncertainty"] = smooth_uncertainty(
            fit[name], fit[UNCERTAINTY[name]], size, sigma=sigma, min_weight=min_weight, inflation=inflation
        ).assign_attrs(
            units="1",
            long_name=f"standard uncertainty of the smoothed {name}, propagated from {UNCERTAINTY[name]}",
        )
    ds = xr.Dataset(
        {
            **smoothed,
            "variability": variability.assign_attrs(
                units="1", long_name=variability.attrs.get("long_name", "spatial reflectance variability")
            ),
            **uncertainties,
            "R0_fit": fit["R0"],
            "n_fit": fit["n"],
            **{name: fit[name] for name in QUALITY if name in fit},
        }
    )
    ds.attrs = {"smoothing_size": size, "smoothing_sigma": sigma, "min_weight": float(min_weight), **propagation}
    return ds
