"""Per-pixel fit of the scattering model R(theta) = R0 cos((2 - 1/n) theta)^n (paper eq. 3).

The kernel :func:`fit_scattering_arrays` works on plain numpy arrays, vectorised over
pixels. For fixed n the model is linear in R0, so R0 is eliminated (variable
projection) and the least-squares problem becomes one-dimensional in n:

    F(n) = sum R^2 - (sum R g)^2 / sum g^2,   g = cos(a theta)^n,  a = 2 - 1/n.

A coarse grid over n brackets the global minimum (for n < 0.5 the model has an
alias branch, and n = 0.5 is a stationary point of every pixel: NUMERICS.md);
inside the bracket a safeguarded Newton iteration on F'(n) = 0 with the exact
second derivative converges in a few steps, falling back to bisection whenever
Newton would leave the bracket. cos and log cos come from tan, which numpy
evaluates vectorised and which is accurate at small angles.
"""

from __future__ import annotations

import numpy as np
import xarray as xr

__all__ = [
    "fit_scattering",
    "fit_scattering_arrays",
    "scattering_model",
    "FIT_STATUS",
    "DEFAULT_MIN_SPREAD",
    "N_MAX",
]

#: Default minimum AOI spread (max - min over a pixel's valid views), radians.
DEFAULT_MIN_SPREAD = float(np.deg2rad(10.0))
#: Largest scattering coefficient searched (beyond it the surface is specular at the camera's resolution).
N_MAX = 50.0
_N_MIN = 0.5
# Start grid evenly spaced in a = 2 - 1/n over (0, 2), closed by the upper bound.
_START_GRID = np.append(1.0 / (2.0 - np.array([0.1, 0.35, 0.6, 0.85, 1.1, 1.35, 1.6, 1.85, 1.96])), N_MAX)
_MAX_ITER = 40
# Pixels per block of the fit: at most _BLOCK, and about _BLOCK_VALUES (1 MB of float64) in each (view, pixel)
# working array, which then stays in the cache with many views (20 wall views: 1.3x faster than 16384 pixels).
_BLOCK = 16384
_BLOCK_VALUES = 2**17
_FLOAT_OUTPUTS = ("R0", "n", "R0_sigma", "n_sigma", "rms")
_TOL = 1e-12
# Newton converges quadratically here: after a step below _STEP_TOL n, n is within ~1e-12 n of the optimum.
_STEP_TOL = 1e-6

#: Meaning of the ``status`` codes of a fit.
FIT_STATUS = {
    0: "converged",
    1: "fewer valid views than required",
    2: "AOI spread below the minimum",
    3: "not converged or optimum at the bound of n",
    4: "no positive reflectance fit (R0 <= 0)",
}


def scattering_model(theta, r0, n):
    """R(theta) = R0 cos((2 - 1/n) theta)^n, zero where (2 - 1/n) theta >= pi/2.

    Parameters
    ----------
    theta : array, radians
    r0, n : array or float, broadcastable against ``theta``; n > 0.5

    Returns
    -------
    array
        Reflectance at AOI ``theta``.
    """
    return r0 * _model_g(np.asarray(n, dtype=float), np.asarray(theta, dtype=float))


def _model_g(n, theta):
    """G = cos(a theta)^n, a = 2 - 1/n, zero where a theta >= pi/2 (no return)."""
    angle = (2.0 - 1.0 / n) * theta
    g = np.tan(angle, out=np.empty(np.shape(angle)))  # an array, for the in-place steps, even for scalars
    np.multiply(g, g, out=g)
    np.log1p(g, out=g)
    np.multiply(-0.5 * n, g, out=g)
    np.exp(g, out=g)
    lit = angle < 0.5 * np.pi
    if not lit.all():
        g *= lit
    return g


def _model_terms(n, theta, theta2=None):
    """G = cos(a theta)^n and h = d log g / dn; with ``theta2`` = theta^2 also dh/dn.

    For the fit's own n, at which every view of a pixel is lit (a theta < pi/2):
    no view is masked. n (pixel,), theta and theta2 (view, pixel); returns
    fresh (view, pixel) arrays.
    """
    t = np.multiply(theta, 2.0 - 1.0 / n)
    np.tan(t, out=t)
    t2 = t * t
    minus_log_cos = np.log1p(t2)
    minus_log_cos *= 0.5
    g = np.multiply(minus_log_cos, -n)
    np.exp(g, out=g)
    h = np.multiply(theta, t, out=t)
    h *= -1.0 / n
    h -= minus_log_cos
    if theta2 is None:
        return g, h
    dh = t2
    dh += 1.0
    dh *= theta2
    dh *= -1.0 / (n * n * n)
    return g, h, dh


def _reduced_cost(n, r, theta, w):
    """F(n) of the variable projection, up to the constant sum R^2, at one n for every pixel.

    r, theta, w (view, pixel), n a float. Views that n does not light are not
    masked: the caller discards such n.
    """
    g = np.multiply(theta, 2.0 - 1.0 / n)
    np.tan(g, out=g)
    np.multiply(g, g, out=g)
    np.log1p(g, out=g)
    np.multiply(g, -0.5 * n, out=g)
    np.exp(g, out=g)
    p = np.einsum("vp,vp->p", r, g)
    np.multiply(g, g, out=g)
    q = np.einsum("vp,vp->p", g, w)
    with np.errstate(invalid="ignore", divide="ignore"):
        return -np.where(q > 0, p * p / q, 0.0)


def _derivatives(n, r, theta, theta2, w):
    """First and second derivative of F(n); r, theta, theta2 = theta^2, w (view, pixel), n (pixel,)."""
    g, h, dh = _model_terms(n, theta, theta2)
    rg = np.multiply(r, g)
    g2 = np.multiply(g, g, out=g)
    g2 *= w
    p = rg.sum(axis=0)
    q = g2.sum(axis=0)
    dp = np.einsum("vp,vp->p", rg, h)
    dq = 2.0 * np.einsum("vp,vp->p", g2, h)
    hh = np.multiply(h, h, out=h)
    dh += hh
    d2p = np.einsum("vp,vp->p", rg, dh)
    dh += hh
    d2q = 2.0 * np.einsum("vp,vp->p", g2, dh)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        d1 = -2.0 * p * dp / q + p * p * dq / (q * q)
        d2 = (
            -2.0 * (dp * dp + p * d2p) / q
            + 4.0 * p * dp * dq / (q * q)
            + p * p * d2q / (q * q)
            - 2.0 * p * p * dq * dq / (q * q * q)
        )
    return d1, d2


def _solve_n(r, theta, w):
    """Minimise F(n) per pixel; returns n and a converged flag (pixel,); theta is 0 where w is."""
    npix = r.shape[1]
    # Above n_lit every view of the pixel that has data is lit (a theta < pi/2): beyond it the
    # model returns nothing at the largest angle and F(n) is flat, a false minimum when the
    # data there are small.
    n_lit = _n_lit(theta.max(axis=0))  # theta is 0 where w is
    # a start value that lights no view of the block is not tried (N_MAX never is, n_lit <= N_MAX):
    # the grid increases, so those tried are its first rows
    cost = np.full((_START_GRID.size, npix), np.inf)
    for row, value in zip(cost, _START_GRID[_START_GRID < n_lit.max()]):
        row[:] = _reduced_cost(value, r, theta, w)
    cost[_START_GRID[:, None] >= n_lit] = np.inf
    best = np.argmin(cost, axis=0)
    lo = np.where(best > 0, _START_GRID[np.maximum(best - 1, 0)], _N_MIN)
    hi = np.minimum(_START_GRID[np.minimum(best + 1, _START_GRID.size - 1)], n_lit)
    n = _START_GRID[best].copy()
    converged = np.zeros(npix, dtype=bool)
    # The working set shrinks to the unconverged pixels only once most have
    # converged: gathering them costs more than iterating on a few extra ones.
    idx = np.arange(npix)
    ra, ta, wa, na = r, theta, w, n.copy()
    t2a = theta * theta
    live = np.ones(npix, dtype=bool)
    for _ in range(_MAX_ITER):
        if not live.any():
            break
        d1, d2 = _derivatives(na, ra, ta, t2a, wa)
        rising = d1 > 0
        hi_new = np.where(rising, na, hi)
        lo_new = np.where(rising, lo, na)
        with np.errstate(invalid="ignore", divide="ignore"):
            newton = na - d1 / d2
        ok = (d2 > 0) & (newton >= lo_new) & (newton <= hi_new)
        done = (ok & (np.abs(newton - na) <= _STEP_TOL * na)) | (d1 == 0) | ((hi_new - lo_new) <= _TOL * na)
        na = np.where(live, np.where(ok, newton, 0.5 * (lo_new + hi_new)), na)
        lo, hi = np.where(live, lo_new, lo), np.where(live, hi_new, hi)
        converged[idx[live & done]] = True
        live &= ~done
        if live.sum() < 0.5 * live.size:
            n[idx] = na
            idx, ra, ta, t2a, wa = idx[live], ra[:, live], ta[:, live], t2a[:, live], wa[:, live]
            na, lo, hi, live = na[live], lo[live], hi[live], live[live]
    n[idx] = na
    at_bound = (n <= _START_GRID[0]) | (n >= np.minimum(N_MAX, n_lit))
    return n, converged & ~at_bound


def _n_lit(theta_max):
    """Return the largest n at which a view at ``theta_max`` (radians) is still lit, just below it; N_MAX at most.

    (2 - 1/n) theta < pi/2 holds for every n when theta_max <= pi/4, else for n < 1 / (2 - pi / (2 theta_max)).
    """
    with np.errstate(divide="ignore"):
        limit = 1.0 / (2.0 - np.pi / (2.0 * np.maximum(theta_max, np.pi / 4)))
    return np.minimum(np.where(theta_max > np.pi / 4, limit * (1.0 - 1e-9), N_MAX), N_MAX)


def _fit_pixels(r, theta, w, n_views):
    """Fit a block of pixels that all pass the view and spread checks; arrays (view, pixel)."""
    n, conv = _solve_n(r, theta, w)
    g, h = _model_terms(n, theta)
    g *= w
    q = (g * g).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        r0 = (r * g).sum(axis=0) / q
        resid = (r0 * g - r) * w
        ssr = (resid * resid).sum(axis=0)
        gh = g * g * h
        jtj_01 = r0 * gh.sum(axis=0)
        jtj_11 = r0 * r0 * (gh * h).sum(axis=0)
        det = q * jtj_11 - jtj_01 * jtj_01
        s2 = np.where(n_views > 2, ssr / np.maximum(n_views - 2, 1), np.nan)
        result = {
            "R0": r0,
            "n": n,
            "R0_sigma": np.sqrt(s2 * jtj_11 / det),
            "n_sigma": np.sqrt(s2 * q / det),
            "rms": np.sqrt(ssr / n_views),
        }
    return result, conv, r0 > 0


def _by_view(a) -> np.ndarray:
    """Return a fresh C-contiguous (view, pixel) float64 copy of a (..., view) array.

    One pass when the view axis is the slowest in memory, as in the (view, y, x) cubes
    that :func:`fit_scattering` hands over as (y, x, view).
    """
    a = np.asarray(a)
    return np.array(np.moveaxis(a, -1, 0).reshape(a.shape[-1], -1), dtype=np.float64, order="C")


def fit_scattering_arrays(r, theta, *, min_views=2, min_spread=DEFAULT_MIN_SPREAD):
    """Fit R = R0 cos((2 - 1/n) theta)^n per pixel over the last axis.

    Parameters
    ----------
    r : (..., view) array
        Reflectance; NaN marks a missing observation.
    theta : (..., view) array, radians
        Angle of incidence; NaN marks a missing observation.
    min_views : int
        Fewer valid views give NaN with status 1.
    min_spread : float, radians
        Smaller AOI spread over the valid views gives NaN with status 2.

    Returns
    -------
    dict of (...) arrays
        ``R0``, ``n``, ``R0_sigma``, ``n_sigma`` (standard uncertainties from
        the fit covariance scaled by the residual variance; NaN with fewer
        than 3 views), ``rms`` (residual), ``n_views`` (uint8), ``converged``
        (bool), ``status`` (uint8, see :data:`FIT_STATUS`).
    """
    shape = np.shape(r)[:-1]
    r, theta = _by_view(r), _by_view(theta)
    valid = np.isfinite(r)
    valid &= np.isfinite(theta)
    invalid = ~valid
    np.copyto(r, 0.0, where=invalid)
    np.copyto(theta, 0.0, where=invalid)
    w = valid.astype(np.float64)
    n_views = valid.sum(axis=0)
    with np.errstate(invalid="ignore"):
        spread = np.where(valid, theta, -np.inf).max(axis=0) - np.where(valid, theta, np.inf).min(axis=0)
    status = np.zeros(r.shape[1], dtype=np.uint8)
    status[spread < min_spread] = 2
    status[n_views < min_views] = 1
    fit = np.flatnonzero(status == 0)

    npix = r.shape[1]
    out = {key: np.full(npix, np.nan) for key in _FLOAT_OUTPUTS}
    converged = np.zeros(npix, dtype=bool)
    pixels = max(1, min(_BLOCK, _BLOCK_VALUES // max(1, r.shape[0])))
    for block in np.array_split(fit, -(-fit.size // pixels)) if fit.size else ():
        # np.take keeps the gathered block C-contiguous; r[:, block] would not, and
        # halves the speed of every operation on it.
        gathered = (np.take(a, block, axis=1) for a in (r, theta, w))
        result, conv, positive = _fit_pixels(*gathered, n_views[block])
        for key in _FLOAT_OUTPUTS:
            out[key][block] = result[key]
        converged[block] = conv & positive
        status[block[~positive]] = 4
        status[block[positive & ~conv]] = 3
    bad = status != 0
    for key in out:
        out[key][bad] = np.nan
    out["n_views"] = n_views.astype(np.uint8)
    out["converged"] = converged
    out["status"] = status
    return {key: value.reshape(shape) for key, value in out.items()}


_OUTPUTS = {
    "R0": ("1", "reflectance at normal incidence (unsmoothed fit)"),
    "n": ("1", "scattering coefficient (unsmoothed fit)"),
    "R0_sigma": ("1", "standard uncertainty of R0 from the fit covariance"),
    "n_sigma": ("1", "standard uncertainty of n from the fit covariance"),
    "rms": ("1", "rms residual of the fit"),
    "n_views": ("1", "number of valid views"),
    "converged": (None, "fit converged"),
    "status": (None, "fit status code"),
}
_DTYPES = {"n_views": np.uint8, "converged": bool, "status": np.uint8}


def fit_scattering(
    reflectance: xr.DataArray, aoi: xr.DataArray, *, min_views: int = 2, min_spread: float = DEFAULT_MIN_SPREAD
) -> xr.Dataset:
    """Per-pixel least-squares fit of the scattering model over the views.

    Parameters
    ----------
    reflectance : (view, y, x) DataArray
        Absolute reflectance on a common grid (registered views); NaN = missing.
    aoi : (view, y, x) DataArray, radians
        Angle of incidence on the same grid; NaN = missing.
    min_views : int, default 2
        Minimum number of valid views of a pixel.
    min_spread : float, radians
        Minimum AOI spread over a pixel's valid views.

    Returns
    -------
    Dataset
        (y, x) variables ``R0``, ``n`` (unsmoothed; NaN where not fitted),
        ``R0_sigma``, ``n_sigma``, ``rms``, ``n_views``, ``converged`` and
        ``status`` (codes in ``status.attrs["flag_meanings"]``). Lazy on dask
        input, which must hold ``view`` in one chunk.
    """
    for name, arr in (("reflectance", reflectance), ("aoi", aoi)):
        if "view" not in arr.dims:
            raise ValueError(f"fit_scattering: {name} has dims {arr.dims}; it needs a 'view' dimension")
        if arr.chunks is not None and len(arr.chunksizes["view"]) > 1:
            raise ValueError(
                f"fit_scattering: {name} is split along 'view' ({arr.chunksizes['view']}); "
                "rechunk with {'view': -1} so each pixel's views are fitted together"
            )
    names = list(_OUTPUTS)

    def kernel(r, t):
        result = fit_scattering_arrays(r, t, min_views=min_views, min_spread=min_spread)
        return tuple(result[key] for key in names)

    results = xr.apply_ufunc(
        kernel,
        reflectance,
        aoi,
        input_core_dims=[["view"], ["view"]],
        output_core_dims=[[] for _ in names],
        dask="parallelized",
        output_dtypes=[_DTYPES.get(key, np.float64) for key in names],
    )
    ds = xr.Dataset(dict(zip(names, results)))
    for key, (units, long_name) in _OUTPUTS.items():
        ds[key].attrs = {"long_name": long_name} | ({"units": units} if units else {})
    ds["status"].attrs["flag_values"] = list(FIT_STATUS)
    ds["status"].attrs["flag_meanings"] = " ".join(v.replace(" ", "_") for v in FIT_STATUS.values())
    ds.attrs = {"min_views": min_views, "min_spread": min_spread}
    return ds
