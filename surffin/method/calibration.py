"""Radiometric calibration (method step 3): the per-pixel instrument function and the scale k.

The instrument function of the paper's eq. 5,

    f(d, theta) = (A + B / d^2) (C theta^2 + D theta + E),   theta in radians, d in metres,

is fitted per pixel to the views of a flat Lambertian wall, ``y = I / cos(theta)`` (eq. 4), with
the gauge E = 1; calibrated reflectance is ``R = I / (k f)`` (eq. 2), k from views of a reference
panel (eq. 6). The model is linear in the six products ``vec([A, B]^T [C, D, E])`` of rank one, so
a pixel's fit depends on 22 moments of its observations, which :class:`WallStatistics`
accumulates view by view: memory and time do not grow with the views. :func:`fit_calibration`
starts a rank-one fit from the linear one, refines it by Gauss-Newton, then smooths the angular
factor (C, D: ~-0.99 correlated per pixel, smooth over a camera's field of view) over the sensor
and refits (A, B) per pixel.

A real camera has residual systematics eq. 5 cannot represent (e.g. a time-of-flight camera's
cyclic error in distance): :func:`fit_correction` smooths the ratios ``y / f`` of wall
observations, pooled over the sensor, into a factor ``c(d, theta)`` (penalised least squares,
smoothness by cross-validation over the wall views), and ``R = I / (k f c)``; :func:`calibrate`
refits eq. 5 to ``y / c`` once and ``c`` again (``residual_correction=False``: the paper's plain
method). Pixels without a fit are NaN with a status code (:data:`CALIBRATION_STATUS`), never a
number. Measurements: ``docs/performance.md``.
"""

from __future__ import annotations

import logging
import math
import os
import tempfile
from collections.abc import Callable, Collection, Iterable, Mapping
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import cv2
import numpy as np
import xarray as xr

from surffin.errors import CalibrationError, StoreError
from surffin.io.ingest import describe_file
from surffin.io.store import open_store, provenance
from surffin.io.viewfile import describe_groups, read_settings, setting_values
from surffin.method.geometry import DEFAULT_JUMP, DEFAULT_MAX_WINDOW, DEFAULT_WINDOW, frame_angle_of_incidence
from surffin.method.noise import NOISE_VIEWS, NoiseStatistics

if TYPE_CHECKING:
    from surffin.grid import Roi
    from surffin.io.campaign import Calibration, Campaign

__all__ = [
    "TERMS",
    "SAMPLE_QUANTITIES",
    "CALIBRATION_STATUS",
    "DEFAULT_MIN_OBS",
    "DEFAULT_ANGULAR_SMOOTHING",
    "DEFAULT_RESIDUAL_CORRECTION",
    "CORRECTION_DIMS",
    "instrument_function",
    "correction_factor",
    "fit_correction",
    "Observation",
    "WallStatistics",
    "fit_calibration",
    "reference_scale",
    "calibration_diagnostics",
    "with_reflectance",
    "observe_view",
    "calibration_set",
    "calibrate",
    "reflectance",
]

log = logging.getLogger("surffin")

#: Names of the instrument function's coefficients, in storage order (the ``term`` coordinate).
TERMS = ("A", "B", "C", "D", "E")

#: Default minimum number of wall observations of a pixel for a fit.
DEFAULT_MIN_OBS = 12
#: Default smoothing of the angular factor (C, D) over the sensor: a Gaussian whose standard
#: deviation is this fraction of the sensor diagonal (24 px on 640 x 480).
DEFAULT_ANGULAR_SMOOTHING = 0.03
#: Default of :func:`calibrate`'s ``residual_correction``: learn the factor eq. 5 leaves.
DEFAULT_RESIDUAL_CORRECTION = True
#: Dimensions of the residual correction's grid: distance (m) and angle of incidence (rad).
CORRECTION_DIMS = ("correction_distance", "correction_aoi")

#: Quantities of the raw wall observations a calibration keeps (the ``quantity`` coordinate of
#: ``sample_obs``, ``wall_obs`` and ``wall_image``): intensity (camera units), distance (m), AOI
#: (rad), and the reflectance ``I / (k f)`` the fitted calibration gives them.
SAMPLE_QUANTITIES = ("intensity", "distance", "aoi", "reflectance")

#: Names of the ``status`` codes of a calibration fit (CF ``flag_meanings``): 0 the fit
#: converged; 1 the pixel has fewer wall observations than ``min_obs``; 2 its observations do
#: not separate the effects of distance and angle (e.g. one distance, or fewer than three
#: angles): the Jacobi-scaled statistics are singular; 3 the fit did not converge.
CALIBRATION_STATUS = {0: "converged", 1: "too_few_observations", 2: "singular_statistics", 3: "not_converged"}

# Moments kept per pixel: S[a, c] = sum w^a theta^c (a <= 2, c <= 4) at 5 a + c,
# T[a, c] = sum y w^a theta^c (a <= 1, c <= 2) at 15 + 3 a + c, then sum y^2.
_N_MOMENTS = 22
_T0 = 15
_YY = 21
# z = u (x) v as powers (a, c) of w and theta: u = [1, w], v = [theta^2, theta, 1].
_Z_POWERS = ((0, 2), (0, 1), (0, 0), (1, 2), (1, 1), (1, 0))
_G_INDEX = np.array([[5 * (a + a2) + c + c2 for a2, c2 in _Z_POWERS] for a, c in _Z_POWERS])
_B_INDEX = np.array([_T0 + 3 * a + c for a, c in _Z_POWERS])
# Pixels per block: the temporaries of accumulation and fit stay in the cache.
_BLOCK = 16384
# Smallest pivot of the Jacobi-scaled G (unit diagonal) of a pixel with a fit.
_MIN_PIVOT = 1e-12
_MAX_ITER = 30
_MAX_HALVINGS = 30
_FTOL = 1e-12
_COST_RISE = 1e-14
_FLOOR = 1e-24
# Scale factor of the median absolute deviation to a normal standard deviation.
_MAD_SIGMA = 1.4826
# Wall observations kept by :func:`calibrate` (:class:`_WallSamples`): every view of the pixels
# on a grid over the crop (fractions of its rows x columns), and about _WALL_SAMPLES random
# usable pixels of the crop, spread evenly over the views.
_SAMPLE_ROWS = (0.25, 0.75)
_SAMPLE_COLUMNS = (1 / 6, 0.5, 5 / 6)
_WALL_SAMPLES = 3000
# Residual correction (:func:`fit_correction`): grid steps in distance (m) and AOI (rad); random
# wall observations kept for it (all views together); cross-validation folds of wall views and
# candidate penalties; observations of a node for it to be inside the support; the ratios kept
# (gross outliers, e.g. a mixed pixel, are left out); the ridge towards 1 (relative to the
# mean observations of a node) that keeps the system regular.
_CORRECTION_STEP = (0.01, math.radians(1.0))
_CORRECTION_SAMPLES = 2**20
_CORRECTION_FOLDS = 5
_CORRECTION_PENALTIES = tuple(10.0 ** np.arange(-1.0, 6.01, 0.5))
_CORRECTION_MIN_COUNT = 10
_CORRECTION_RATIOS = (0.5, 2.0)
_CORRECTION_RIDGE = 1e-6


def instrument_function(coef, distance, aoi):
    """Eq. 5: ``f = (A + B / d^2) (C theta^2 + D theta + E)``.

    Parameters
    ----------
    coef : (5, ...) ndarray, or DataArray with a ``term`` dimension
        A, B (m^2), C, D, E in the order of :data:`TERMS` (numpy: along the
        first axis; xarray: selected by the ``term`` coordinate), broadcasting
        against ``distance`` and ``aoi``.
    distance : ndarray or DataArray, metres
    aoi : ndarray or DataArray, radians

    Returns
    -------
    ndarray or DataArray
        Broadcast of the inputs (aligned by coordinates for xarray; lazy on dask).
    """
    if isinstance(coef, xr.DataArray):
        A, B, C, D, E = (coef.sel(term=term, drop=True) for term in TERMS)
    else:
        A, B, C, D, E = coef
    return (A + B / distance**2) * ((C * aoi + D) * aoi + E)


class Observation(NamedTuple):
    """One view of the calibration set, on the full sensor grid (or a region of it, :func:`observe_view`).

    Attributes
    ----------
    name : str
        The view file (for messages).
    intensity : (H, W) ndarray
        Camera intensity.
    distance : (H, W) ndarray of float, metres
    aoi : (H, W) ndarray of float, radians
    valid : (H, W) ndarray of bool
        Pixels with a return and an unsaturated intensity; pixels with a NaN
        distance or AOI are left out too.
    saturated : int
        Pixels with a return whose intensity is saturated (left out of ``valid``).
    """

    name: str
    intensity: np.ndarray
    distance: np.ndarray
    aoi: np.ndarray
    valid: np.ndarray
    saturated: int = 0


def _usable(intensity, distance, aoi, valid) -> tuple[np.ndarray, ...]:
    """Flat float64 copies and the usable mask: valid, finite, distance > 0, |theta| < pi/2."""
    arrays = [np.asarray(a, dtype=np.float64).ravel() for a in (intensity, distance, aoi)]
    intensity, distance, aoi = arrays
    with np.errstate(invalid="ignore"):
        ok = np.asarray(valid, dtype=bool).ravel() & (distance > 0) & (np.abs(aoi) < 0.5 * np.pi)
    ok &= np.isfinite(intensity)
    return intensity, distance, aoi, ok


class WallStatistics:
    """Sufficient statistics of the calibration fit, accumulated view by view.

    With ``u = [1, w]``, ``w = 1 / d^2``, ``v = [theta^2, theta, 1]`` and
    ``z = u (x) v``, the model is linear in the six products
    ``m = vec([A, B]^T [C, D, E])``: ``f = m . z``, with ``m`` of rank one. The
    whole least-squares problem of a pixel therefore depends on its
    observations only through ``G = sum z z^T``, ``b = sum y z`` and
    ``sum y^2``. The entries of ``G`` are moments ``sum w^a theta^c`` (a <= 2,
    c <= 4: 15 of them) and those of ``b`` are ``sum y w^a theta^c`` (a <= 1,
    c <= 2: 6), so 22 float64 are kept per pixel, accumulated view by view:
    memory and fit time do not depend on the number of views. ``N`` and
    ``sum y`` are the moments with a = c = 0.

    Parameters
    ----------
    shape : (int, int)
        Sensor (height, width).

    Attributes
    ----------
    moments : (22, height, width) ndarray of float64
        Per pixel ``sum w^a theta^c`` (a <= 2, c <= 4), ``sum y w^a theta^c``
        (a <= 1, c <= 2) and ``sum y^2``, with ``w = 1/d^2`` (m^-2), theta in
        radians and ``y = I / cos(theta)`` (module docstring).
    n_views : int
        Views added.
    """

    def __init__(self, shape: tuple[int, int]):
        height, width = (int(n) for n in shape)
        if height < 1 or width < 1:
            raise ValueError(f"shape must be a positive (height, width), got {shape!r}")
        self.shape = (height, width)
        self.moments = np.zeros((_N_MOMENTS, height, width))
        self.n_views = 0

    def add(self, intensity, distance, aoi, valid) -> WallStatistics:
        """Add one view of the wall.

        Parameters
        ----------
        intensity : (H, W) array_like
            Camera intensity of a Lambertian wall.
        distance : (H, W) array_like, metres
        aoi : (H, W) array_like, radians
        valid : (H, W) array_like of bool
            Pixels to use; NaN or non-positive distances, NaN intensities and
            AOIs outside [0, pi/2) are left out whatever ``valid`` says.

        Returns
        -------
        WallStatistics
            ``self``, updated.
        """
        for name, array in (("intensity", intensity), ("distance", distance), ("aoi", aoi), ("valid", valid)):
            if np.shape(array) != self.shape:
                raise ValueError(f"{name} must have the sensor shape {self.shape}, got {np.shape(array)}")
        intensity, distance, aoi, ok = _usable(intensity, distance, aoi, valid)
        flat = self.moments.reshape(_N_MOMENTS, -1)
        for start in range(0, ok.size, _BLOCK):
            block = slice(start, start + _BLOCK)
            _accumulate(flat[:, block], intensity[block], distance[block], aoi[block], ok[block])
        self.n_views += 1
        return self

    def merge(self, other: WallStatistics) -> WallStatistics:
        """Add the views of ``other`` (statistics of the same sensor) to ``self``; returns ``self``."""
        if other.shape != self.shape:
            raise ValueError(f"cannot merge statistics of shape {other.shape} into {self.shape}")
        self.moments += other.moments
        self.n_views += other.n_views
        return self

    @property
    def n_obs(self) -> np.ndarray:
        """(H, W) ndarray of int64: observations per pixel."""
        return np.rint(self.moments[0]).astype(np.int64)


def _accumulate(moments, intensity, distance, aoi, ok) -> None:
    """Add one block of observations (n,) to its moments (22, n), in place."""
    # q (1 on usable pixels, else 0) masks every product; w = q / d^2
    q = ok.astype(np.float64)
    t = np.where(ok, aoi, 0.0)
    w = np.where(ok, distance, 1.0)
    np.multiply(w, w, out=w)
    np.divide(q, w, out=w)
    y = np.where(ok, intensity, 0.0) / np.cos(t)
    # powers[c] = w^a theta^c (masked) for the current a
    powers = np.empty((5, q.size))
    powers[0] = q
    for c in range(1, 5):
        np.multiply(powers[c - 1], t, out=powers[c])
    scratch = np.empty((3, q.size))
    for a in range(3):
        moments[5 * a : 5 * a + 5] += powers
        if a < 2:
            moments[_T0 + 3 * a : _T0 + 3 * a + 3] += np.multiply(powers[:3], y, out=scratch)
            powers *= w
    moments[_YY] += np.multiply(y, y, out=t)


def _system(moments: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """G (6, 6, n) and b (6, n) of the moments (22, n) of n pixels."""
    return moments[_G_INDEX], moments[_B_INDEX]


def _pixel_dot(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Dot products ``sum_i u[i] v[i]`` (n,) of u, v (k, n), summed as einsum sums pixel-major arrays.

    einsum adds the terms along a contiguous axis with SIMD partial sums, along any other axis one
    after the other: the last bits depend on the memory layout. The fit's per-pixel dot products
    (signal energy, rank-one start, convergence test) are summed pixel-major (contiguous along i),
    as when the fit was validated, while its element-wise work runs on row-major arrays, where it
    is several times faster; the Gauss-Newton path of an ill-conditioned pixel follows the last bits.
    """
    return np.einsum("in,in->n", np.asfortranarray(u), np.asfortranarray(v))


def _solve_spd(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Solve symmetric positive definite systems a x = b, batched over the last axis, never raising.

    Gaussian elimination without pivoting (stable for SPD matrices) on the
    Jacobi-scaled matrix, vectorised over pixels; the scaled copy of a is
    eliminated in place, the outer products go to one scratch array.

    Parameters
    ----------
    a : (k, k, n) ndarray
    b : (k, n) ndarray

    Returns
    -------
    x : (k, n) ndarray
        Meaningless where ``pivot`` is not positive.
    pivot : (n,) ndarray
        Smallest pivot of the scaled matrix (unit diagonal), an upper bound of
        its smallest eigenvalue: ~1e-16 or below (or -inf) when a is singular.
    """
    k = len(b)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        scale = 1.0 / np.sqrt(np.einsum("iin->in", a))
        a = a * scale[:, None]
        a *= scale
        x = b * scale
        pivots = np.empty_like(x)
        outer = np.empty_like(a)
        for row in range(k):
            rest = slice(row + 1, None)
            pivots[row] = a[row, row]
            factor = a[rest, row] / a[row, row]
            a[rest, rest] -= np.multiply(factor[:, None], a[None, row, rest], out=outer[rest, rest])
            x[rest] -= np.multiply(factor, x[row], out=outer[row, rest])
        for row in range(k - 1, -1, -1):
            x[row] = (x[row] - np.einsum("in,in->n", a[row, row + 1 :], x[row + 1 :])) / a[row, row]
        x *= scale
    return x, np.where(np.isnan(pivots).any(axis=0), -np.inf, pivots.min(axis=0))


def _rank_one_shape(m_hat: np.ndarray) -> np.ndarray:
    """(C, D) (2, n) of the leading singular pair of M_hat = m_hat (6, n) as 2x3 matrices, scaled to E = 1.

    The leading left singular vector u is the top eigenvector of the 2x2
    ``M M^T`` (closed form); ``v = M^T u`` is then the leading right one up to scale.
    """
    M = m_hat.reshape(2, 3, -1)
    p00, p01, p11 = (_pixel_dot(M[i], M[j]) for i, j in ((0, 0), (0, 1), (1, 1)))
    half = 0.5 * (p00 - p11)
    top = 0.5 * (p00 + p11) + np.sqrt(half * half + p01 * p01)
    first = np.stack([top - p11, p01])
    second = np.stack([p01, top - p00])
    u = np.where(np.abs(first).sum(0) >= np.abs(second).sum(0), first, second)
    u[0, ~np.any(u, axis=0)] = 1.0
    v = np.einsum("ikn,in->kn", M, u)
    with np.errstate(invalid="ignore", divide="ignore"):
        return v[:2] / v[2]


def _best_ab(cd: np.ndarray, G: np.ndarray, b: np.ndarray) -> np.ndarray:
    """P = (A, B, C, D) (4, n) with the (A, B) minimising the cost for given (C, D) (2, n), E = 1.

    For fixed (C, D) the model is linear in (A, B), with design ``V = dm/d(A, B)``:
    a 2x2 solve of ``V^T G V (A, B) = V^T b``.
    """
    C, D = cd
    K = _contract_v(np.moveaxis(_contract_v(G, C, D), 0, 1), C, D)
    h = _contract_v(b, C, D)
    det = K[0, 0] * K[1, 1] - K[0, 1] * K[1, 0]
    with np.errstate(invalid="ignore", divide="ignore"):
        A = (K[1, 1] * h[0] - K[0, 1] * h[1]) / det
        B = (K[0, 0] * h[1] - K[1, 0] * h[0]) / det
    return np.concatenate([A[None], B[None], cd])


def _start(m_hat: np.ndarray, G: np.ndarray, b: np.ndarray, shapes: Iterable[np.ndarray]) -> np.ndarray:
    """Start p (4, n): of the rank-one projection of m_hat and the (C, D) ``shapes`` (2,) or (2, n), the least cost.

    m_hat (6 free products) is noisier than the rank-one fit (4 parameters);
    the sensor's typical (C, D) is a safe second candidate because the angular
    shape varies by a few % across the sensor (:func:`fit_calibration`, step 2),
    and a previous fit of each pixel a third.
    """
    p = _best_ab(_rank_one_shape(m_hat), G, b)
    cost = _cost(p, m_hat, G)[0]
    for shape in shapes:
        other = _best_ab(np.broadcast_to(np.reshape(shape, (2, -1)), (2, p.shape[1])), G, b)
        other_cost = _cost(other, m_hat, G)[0]
        better = (other_cost < cost) | ~np.isfinite(cost)
        p, cost = np.where(better, other, p), np.where(better, other_cost, cost)
    return p


def _products(p: np.ndarray) -> np.ndarray:
    """m(p) = vec([A, B]^T [C, D, 1]) (6, n) of p = (A, B, C, D) (4, n)."""
    A, B, C, D = p
    m = np.empty((6, p.shape[1]))
    np.multiply(A, p[2:], out=m[:2])
    np.multiply(B, p[2:], out=m[3:5])
    m[2::3] = p[:2]
    return m


def _contract_v(x: np.ndarray, C, D, out: np.ndarray | None = None) -> np.ndarray:
    """``(dm/dA, dm/dB)^T x``: ``sum_k x[(i, k)] v_k`` with v = (C, D, 1), along the first axis of x (6, ...).

    Returns (2, ...), in ``out`` if given; x may be a strided view (it is not copied).
    """
    out = np.multiply(x[0::3], C, out=out)
    out += x[1::3] * D
    out += x[2::3]
    return out


def _jt(x: np.ndarray, p: np.ndarray) -> np.ndarray:
    """J^T x for J = dm/dp of :func:`_products` at p (4, n), along the first axis of x (6, ..., n): (4, ..., n).

    J is sparse: dm/dA = [C, D, 1, 0, 0, 0], dm/dB = [0, 0, 0, C, D, 1],
    dm/dC = [A, 0, 0, B, 0, 0], dm/dD = [0, A, 0, 0, B, 0].
    """
    A, B, C, D = p
    out = np.empty_like(x, shape=(4, *x.shape[1:]))
    _contract_v(x, C, D, out=out[:2])
    np.multiply(A, x[:2], out=out[2:])
    out[2:] += B * x[3:5]
    return out


def _cost(p: np.ndarray, m_hat: np.ndarray, G: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Q(p) (n,) and G (m(p) - m_hat) (6, n)."""
    d = _products(p)
    d -= m_hat
    Gd = np.einsum("kln,ln->kn", G, d)
    return np.einsum("kn,kn->n", d, Gd), Gd


def _take(array: np.ndarray, index: np.ndarray) -> np.ndarray:
    """``array[..., index]`` for increasing indices (n,) into the last axis; ``array`` itself if they are all of it."""
    return array if index.size == array.shape[-1] else array.take(index, axis=-1)


def _put(array: np.ndarray, index: np.ndarray, ok: np.ndarray, values: np.ndarray) -> None:
    """``array[..., index[ok]] = values[..., ok]`` for increasing indices (n,) and a mask ok (n,), in place."""
    if index.size == array.shape[-1]:
        np.copyto(array, values, where=ok)
    else:
        array[..., index[ok]] = values[..., ok]


def _gauss_newton(p, m_hat, G, floor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Minimise Q over p (4, n), in place (:func:`fit_calibration`, step 3).

    Returns p, Q (n,) and a converged mask (n,): the predicted decrease of a
    Gauss-Newton step fell below ``_FTOL`` times the cost plus ``floor`` (n,).
    A pixel whose step does not lower the cost even when halved
    ``_MAX_HALVINGS`` times stops, not converged. The pixels still iterating
    are compacted when they fall below half of the working set.
    """
    cost, Gd = _cost(p, m_hat, G)
    converged = np.zeros(p.shape[1], dtype=bool)
    index = np.flatnonzero(np.isfinite(cost))
    work = tuple(_take(array, index) for array in (p, m_hat, G, floor, cost, Gd))
    live = np.ones(index.size, dtype=bool)
    for _ in range(_MAX_ITER):
        if not live.any():
            break
        if live.sum() < live.size // 2:
            p[:, index] = work[0]
            cost[index] = work[4]
            index, work, live = index[live], tuple(array.compress(live, axis=-1) for array in work), live[live]
        pw, mw, Gw, fw, cw, Gdw = work
        H = _jt(np.moveaxis(_jt(Gw, pw), 0, 1), pw)
        g = _jt(Gdw, pw)
        step, pivot = _solve_spd(H, -g)
        bad = ~live | ~((pivot > 0) & np.isfinite(step).all(axis=0))
        done = ~bad & (0.5 * _pixel_dot(step, -g) <= _FTOL * cw + fw)
        accepted = np.zeros(live.size, dtype=bool)
        factor = 1.0
        for _ in range(_MAX_HALVINGS):
            todo = np.flatnonzero(~accepted & ~bad & (~done | (factor == 1.0)))
            if todo.size == 0:
                break
            trial = _take(pw, todo) + factor * _take(step, todo)
            c, gd = _cost(trial, _take(mw, todo), _take(Gw, todo))
            ok = c <= _take(cw, todo) * (1.0 + _COST_RISE) + _take(fw, todo)
            chosen = todo[ok]
            for array, values in ((pw, trial), (cw, c), (Gdw, gd)):
                _put(array, todo, ok, values)
            accepted[chosen] = True
            factor *= 0.5
        converged[index[done]] = True
        live &= ~done & accepted
    p[:, index] = work[0]
    cost[index] = work[4]
    return p, cost, converged


def _free_fit(moments: np.ndarray, min_obs: int) -> tuple[np.ndarray, np.ndarray]:
    """Step 1 of :func:`fit_calibration` for n pixels: which of them get a fit, and their unconstrained products.

    Parameters
    ----------
    moments : (22, n) ndarray of float64
        :attr:`WallStatistics.moments` of n pixels.
    min_obs : int

    Returns
    -------
    status : (n,) ndarray of int8
        :data:`CALIBRATION_STATUS` codes 1 and 2 of the pixels without a fit, 3 (to be fitted) elsewhere.
    m_hat : (6, n) ndarray of float64
        ``G^-1 b`` of the pixels of status 3, NaN elsewhere.
    """
    n = moments.shape[1]
    status = np.full(n, 3, dtype=np.int8)
    m_hat = np.full((6, n), np.nan)
    enough = moments[0] >= min_obs
    status[~enough] = 1
    index = np.flatnonzero(enough)
    solution, pivot = _solve_spd(*_system(_take(moments, index)))
    regular = pivot > _MIN_PIVOT
    status[index[~regular]] = 2
    m_hat[:, index[regular]] = solution[:, regular]
    return status, m_hat


def _fit_block(
    moments: np.ndarray,
    free: tuple[np.ndarray, np.ndarray],
    shapes: tuple[np.ndarray, ...] = (),
    angular: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fit the pixels of one block.

    Parameters
    ----------
    moments : (22, n) ndarray of float64
        :attr:`WallStatistics.moments` of n pixels.
    free : ((n,) ndarray of int8, (6, n) ndarray of float64)
        Their status and unconstrained products (:func:`_free_fit`).
    shapes : tuple of ndarray, optional
        Further start candidates (:func:`_start`): (C, D) (2,) for every pixel
        (the sensor's typical) or (2, n) per pixel (a previous fit; NaN: none).
    angular : (2, n) ndarray, optional
        Fixed (C, D) of each pixel: only (A, B) are fitted (exactly, for them);
        NaN leaves a pixel unfitted (status 3).

    Returns
    -------
    coef : (5, n) ndarray of float64
        A, B, C, D, E = 1; NaN unless converged.
    r2 : (n,) ndarray of float64
        Coefficient of determination of the fit on ``y = I / cos(theta)``.
    status : (n,) ndarray of int8
        :data:`CALIBRATION_STATUS` codes.
    """
    status, m_hat = free
    n = moments.shape[1]
    coef = np.full((5, n), np.nan)
    r2 = np.full(n, np.nan)
    index = np.flatnonzero(status == 3)
    status = status.copy()
    G, b = _system(_take(moments, index))
    m_hat = _take(m_hat, index)
    energy = _pixel_dot(m_hat, b)
    if angular is None:
        candidates = [shape if shape.ndim == 1 else shape[:, index] for shape in shapes]
        p, cost, converged = _gauss_newton(_start(m_hat, G, b, candidates), m_hat, G, _FLOOR * np.abs(energy))
    else:
        p = _best_ab(angular[:, index], G, b)
        cost, converged = _cost(p, m_hat, G)[0], np.ones(index.size, dtype=bool)
    converged &= np.isfinite(p).all(axis=0)
    index, p, cost, energy = index[converged], p[:, converged], cost[converged], energy[converged]
    coef[:4, index] = p
    coef[4, index] = 1.0
    count, total, squares = moments[0, index], moments[_T0, index], moments[_YY, index]
    residual = np.maximum(squares - energy + cost, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        r2[index] = 1.0 - residual / (squares - total * total / count)
    status[index] = 0
    return coef, r2, status


def _smooth_angular(coef: np.ndarray, sigma: float) -> np.ndarray:
    """(C, D) (2, H, W) of the fitted pixels, Gaussian-smoothed over the fitted pixels (normalised convolution)."""
    fitted = np.isfinite(coef[2]).astype(np.float64)
    mass = cv2.GaussianBlur(fitted, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT)
    out = np.full((2, *fitted.shape), np.nan)
    for row, term in enumerate((2, 3)):
        total = cv2.GaussianBlur(np.where(fitted > 0, coef[term], 0.0), (0, 0), sigma, borderType=cv2.BORDER_CONSTANT)
        np.divide(total, mass, out=out[row], where=fitted > 0)
    return out


def fit_calibration(
    stats: WallStatistics,
    *,
    min_obs: int = DEFAULT_MIN_OBS,
    angular_smoothing: float = DEFAULT_ANGULAR_SMOOTHING,
    start: np.ndarray | None = None,
) -> xr.Dataset:
    """Fit the instrument function of every pixel from its wall statistics.

    Parameters
    ----------
    stats : WallStatistics
        Accumulated views of a Lambertian wall.
    min_obs : int, optional
        Pixels with fewer observations get no fit (at least 4 parameters are fitted).
    angular_smoothing : float, optional
        Standard deviation of the Gaussian that smooths the angular factor's
        coefficients C and D over the sensor, as a fraction of the sensor's
        diagonal; then A and B of each pixel are refitted for the smoothed
        (C, D). 0 keeps every pixel's own fit (the paper). Per pixel, C and D
        are ~-0.99 correlated and noisy, while the angular response varies
        smoothly over the field of view (module docstring).
    start : (5, H, W) ndarray, optional
        Coefficients of a previous fit of the same pixels (e.g. before the
        residual correction): each pixel's (C, D) is a further start candidate
        of step 2.

    Returns
    -------
    Dataset
        On the sensor grid (``y`` 0..H-1, ``x`` 0..W-1):
        ``coef`` (term=[A, B, C, D, E], y, x) float64, gauge E = 1, NaN where
        not fitted; ``r2`` (y, x) float64, fit of ``I / cos(theta)``;
        ``n_obs`` (y, x) int32; ``status`` (y, x) int8, codes of
        :data:`CALIBRATION_STATUS` (CF ``flag_values``/``flag_meanings``).

    Notes
    -----
    Per pixel and batched over pixels (``G``, ``b``: :class:`WallStatistics`):

    1. the unconstrained linear least squares ``m_hat = G^-1 b`` on the
       Jacobi-scaled system; pixels whose scaled ``G`` is (nearly) singular, i.e.
       whose views do not separate the effects of distance and angle, are rejected;
    2. a start of rank one with E = 1: of the (C, D) of the leading singular pair
       of the 2x3 matrix ``M_hat``, the sensor's typical (C, D) (a fit of the
       statistics pooled over all pixels) and the pixel's (C, D) of ``start`` when
       given, the one of least cost, each with its exact (A, B) (a 2x2 solve in
       the metric of ``G``); with few or poorly spread views ``m_hat`` is noisy
       and its projection alone may start in the wrong valley;
    3. Gauss-Newton on ``p = (A, B, C, D)`` minimising
       ``Q(p) = (m(p) - m_hat)^T G (m(p) - m_hat)``, which equals the sum of
       squared residuals minus the constant ``SSR(m_hat)``; computing it from the
       difference ``m - m_hat`` avoids the cancellation of
       ``sum y^2 - 2 b^T m + m^T G m``. The 4x4 normal equations ``J^T G J``
       (J = dm/dp, analytic) are solved with scaled columns (C and D are ~-0.99
       correlated), a step is halved until the cost does not rise (beyond 1e-14
       relative), and the iteration stops when the predicted cost decrease falls
       below ``1e-12`` of the cost (or of a floor at 1e-24 of the signal energy,
       for noise-free data);
    4. the angular factor smoothed over the sensor (``angular_smoothing``): C and
       D of the fitted pixels are replaced by their Gaussian-weighted mean over the
       neighbouring fitted pixels, and each pixel's (A, B) is refitted exactly for
       them. Per pixel, C and D are ~-0.99 correlated and their estimates noisy,
       while the angular response of a camera varies smoothly over its field of
       view (the paper's Table 2: C and D vary by 1.8 % and 1.4 % over the image);
       smoothing them lowers the error of the fitted ``k f``
       (``docs/performance.md``).
    """
    if isinstance(min_obs, bool) or not isinstance(min_obs, int | np.integer) or min_obs < 4:
        raise ValueError(f"min_obs must be an integer >= 4 (the fit has 4 free parameters), got {min_obs!r}")
    if (
        isinstance(angular_smoothing, bool)
        or not isinstance(angular_smoothing, int | float)
        or not (0 <= angular_smoothing < 1)
    ):
        raise ValueError(
            f"angular_smoothing must be a fraction of the sensor diagonal in [0, 1), got {angular_smoothing!r}"
        )
    height, width = stats.shape
    flat = stats.moments.reshape(_N_MOMENTS, -1)
    coef = np.empty((5, flat.shape[1]))
    r2 = np.empty(flat.shape[1])
    status = np.empty(flat.shape[1], dtype=np.int8)
    pooled = np.sum(flat, axis=1, where=flat[0] >= min_obs, keepdims=True)
    typical = _fit_block(pooled, _free_fit(pooled, int(min_obs)))[0][2:4, 0]
    shapes = [typical] if np.isfinite(typical).all() else []
    previous = None if start is None else np.asarray(start, dtype=np.float64).reshape(5, -1)[2:4]
    blocks = [slice(first, first + _BLOCK) for first in range(0, flat.shape[1], _BLOCK)]
    # step 1 of each block, kept for the refit of step 4
    free = [_free_fit(flat[:, block], int(min_obs)) for block in blocks]
    for block, solved in zip(blocks, free, strict=True):
        candidates = shapes if previous is None else [*shapes, previous[:, block]]
        coef[:, block], r2[block], status[block] = _fit_block(flat[:, block], solved, tuple(candidates))
    if angular_smoothing > 0:
        sigma = angular_smoothing * math.hypot(height, width)
        angular = _smooth_angular(coef.reshape(5, height, width), sigma).reshape(2, -1)
        for block, solved in zip(blocks, free, strict=True):
            coef[:, block], r2[block], status[block] = _fit_block(flat[:, block], solved, angular=angular[:, block])
    image = ("y", "x")
    return xr.Dataset(
        {
            "coef": (
                ("term", "y", "x"),
                coef.reshape(5, height, width),
                {
                    "units": "1",
                    "long_name": "instrument function coefficients, gauge E = 1: R = I / (scale_k f)",
                    "model": "f = (A + B/d^2)(C theta^2 + D theta + E), d in m, theta in rad",
                },
            ),
            "r2": (image, r2.reshape(height, width), {"units": "1", "long_name": "coefficient of determination"}),
            "n_obs": (
                image,
                stats.n_obs.astype(np.int32),
                {"units": "1", "long_name": "wall observations of the pixel"},
            ),
            "status": (
                image,
                status.reshape(height, width),
                {
                    "long_name": "calibration fit status",
                    "flag_values": list(CALIBRATION_STATUS),
                    "flag_meanings": " ".join(CALIBRATION_STATUS.values()),
                },
            ),
        },
        coords={
            "term": list(TERMS),
            "y": ("y", np.arange(height), {"long_name": "sensor row"}),
            "x": ("x", np.arange(width), {"long_name": "sensor column"}),
        },
        attrs={"min_obs": int(min_obs), "angular_smoothing": float(angular_smoothing), "wall_views": stats.n_views},
    )


def _correction_nodes(low: float, high: float, step: float) -> np.ndarray:
    """At least two nodes ``step`` apart, on multiples of ``step``, covering [low, high]."""
    first, last = math.floor(low / step), math.ceil(high / step)
    return np.arange(first, max(last, first + 1) + 1) * step


def _roughness_penalty(shape: tuple[int, int]):
    """Sparse ``P = sum over both axes of D2^T D2`` of a grid ``shape``: squared second differences."""
    import scipy.sparse as sp

    penalty = sp.csr_matrix((shape[0] * shape[1],) * 2)
    for axis, size in enumerate(shape):
        if size < 3:
            continue
        second = sp.diags([1.0, -2.0, 1.0], [0, 1, 2], shape=(size - 2, size))
        eye = sp.identity(shape[1 - axis])
        along = second.T @ second
        penalty = penalty + (sp.kron(along, eye) if axis == 0 else sp.kron(eye, along))
    return penalty.tocsc()


def _smooth_grid(count: np.ndarray, total: np.ndarray, penalty, weight: float) -> np.ndarray:
    """Node values c (flat) minimising ``sum n (mean - c)^2 + weight c^T P c`` plus a tiny ridge towards 1.

    ``count`` and ``total`` (flat) are the observations and the sum of their
    ratios at each node; the ridge (``_CORRECTION_RIDGE`` of the mean count of the
    occupied nodes) keeps nodes far from any data from being undetermined.
    """
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    occupied = count[count > 0]
    ridge = _CORRECTION_RIDGE * (occupied.mean() if occupied.size else 1.0)
    system = (sp.diags(count + ridge) + weight * penalty).tocsc()
    # symmetric positive definite: no pivoting needed (and 4x faster than partial pivoting)
    factor = splu(system, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    return factor.solve(total + ridge)


def fit_correction(
    ratio, distance, aoi, group, *, folds: int = _CORRECTION_FOLDS, penalty: float | None = None
) -> xr.Dataset:
    """Fit the smooth factor ``c(d, theta)`` that eq. 5 leaves, from residual ratios of the wall pooled over the sensor.

    The ratios ``y / f`` (wall observations over their pixel's fitted
    instrument function) are pooled on a grid of distance (1 cm) and AOI (1 deg),
    each at its nearest node, and smoothed by penalised least squares, a 2-D
    Whittaker smoother: ``c`` minimises ``sum_obs (ratio - c(node))^2 +
    lambda sum (second differences of c along both axes)^2``. ``lambda`` is
    chosen by cross-validation over groups of observations (the wall views,
    assigned at random to ``folds`` folds): of the candidates 10^-1..10^6 (every
    decade, then the half decades beside the best), the one with the least
    squared error on the held-out views. The support is the nodes with at least
    ``_CORRECTION_MIN_COUNT`` (10) observations; every other node takes the value
    of the nearest node of the support, and :func:`correction_factor` clamps
    beyond the grid: the factor is never extrapolated.

    Parameters
    ----------
    ratio : (N,) array_like
        ``y / f`` of wall observations, ``y = I / cos(theta)``; non-finite values
        and gross outliers (outside [0.5, 2]) are left out.
    distance : (N,) array_like, metres
    aoi : (N,) array_like, radians
    group : (N,) array_like of int
        The wall view of each observation (the unit left out by the cross-validation).
    folds : int, optional
        Cross-validation folds (at most the number of groups, at least 2).
    penalty : float, optional
        ``lambda``, instead of choosing it by cross-validation (e.g. the one
        chosen for a previous fit of similar ratios).

    Returns
    -------
    Dataset
        On :data:`CORRECTION_DIMS`, with coordinates ``correction_distance`` (m)
        and ``correction_aoi`` (rad): ``correction``, the factor c (attrs
        ``penalty``, ``cv_penalties``, ``cv_scores`` (mean squared held-out
        error; empty when ``penalty`` is given), ``folds``, ``n_samples``, ``support_distance`` and
        ``support_aoi`` (ranges of the support's nodes), ``outside``: what
        happens beyond the support); ``correction_count``: the observations
        pooled at each node.

    Raises
    ------
    CalibrationError
        Fewer than two groups, or no node with enough observations.
    """
    from scipy.ndimage import distance_transform_edt

    ratio, distance, aoi = (np.asarray(a, dtype=np.float64).ravel() for a in (ratio, distance, aoi))
    group = np.asarray(group).ravel()
    low, high = _CORRECTION_RATIOS
    with np.errstate(invalid="ignore"):
        keep = np.isfinite(distance) & np.isfinite(aoi) & (ratio >= low) & (ratio <= high)
    ratio, distance, aoi, group = ratio[keep], distance[keep], aoi[keep], group[keep]
    # the distinct groups are those of the first of each run (a view's observations come together): no sort of them all
    heads = np.ones(group.size, dtype=bool)
    np.not_equal(group[1:], group[:-1], out=heads[1:])
    groups = np.unique(group[heads])
    group = np.searchsorted(groups, group)
    if groups.size < 2:
        raise CalibrationError(
            f"the residual correction needs wall observations from at least 2 views, got {groups.size}"
        )
    n_folds = int(min(max(folds, 2), groups.size))
    fold = np.random.default_rng(0).permutation(groups.size)[group] % n_folds
    (d_step, t_step), coords = _CORRECTION_STEP, []
    index = []
    for values, step in ((distance, d_step), (aoi, t_step)):
        nodes = _correction_nodes(values.min(), values.max(), step)
        coords.append(nodes)
        index.append(np.rint((values - nodes[0]) / step).astype(np.int64))
    shape = (coords[0].size, coords[1].size)
    flat = np.ravel_multi_index(index, shape)
    size = shape[0] * shape[1]
    count = np.bincount(fold * size + flat, minlength=n_folds * size).reshape(n_folds, size).astype(np.float64)
    total = np.bincount(fold * size + flat, weights=ratio, minlength=n_folds * size).reshape(n_folds, size)
    all_count, all_total = count.sum(axis=0), total.sum(axis=0)
    support = (all_count >= _CORRECTION_MIN_COUNT).reshape(shape)
    if not support.any():
        raise CalibrationError(
            f"no node of the residual correction's grid has {_CORRECTION_MIN_COUNT} wall observations "
            f"({ratio.size} usable ratios)"
        )
    roughness = _roughness_penalty(shape)
    scores: dict[int, float] = {}

    def score(candidate: int) -> None:
        # held-out sum of (ratio - c)^2, less the constant sum of ratio^2
        if candidate in scores or not 0 <= candidate < len(_CORRECTION_PENALTIES):
            return
        scores[candidate] = 0.0
        for k in range(n_folds):
            c = _smooth_grid(all_count - count[k], all_total - total[k], roughness, _CORRECTION_PENALTIES[candidate])
            scores[candidate] += float(np.sum(count[k] * c * c - 2.0 * c * total[k]))

    if penalty is None:
        for candidate in range(0, len(_CORRECTION_PENALTIES), 2):
            score(candidate)
        coarse = min(scores, key=scores.get)
        score(coarse - 1)
        score(coarse + 1)
        penalty = _CORRECTION_PENALTIES[min(scores, key=scores.get)]
    c = _smooth_grid(all_count, all_total, roughness, penalty).reshape(shape)
    nearest = distance_transform_edt(~support, return_distances=False, return_indices=True)
    c = c[tuple(nearest)]
    rows, columns = np.nonzero(support)
    # the held-out error per observation: the scores lack the constant sum of squared ratios
    squares = float(np.sum(ratio * ratio))
    attrs = {
        "units": "1",
        "long_name": "residual correction of the instrument function: R = I / (scale_k f c)",
        "penalty": float(penalty),
        "cv_penalties": [float(_CORRECTION_PENALTIES[candidate]) for candidate in sorted(scores)],
        "cv_scores": [(scores[candidate] + squares) / ratio.size for candidate in sorted(scores)],
        "folds": n_folds,
        "n_samples": int(ratio.size),
        "support_distance": [float(coords[0][rows.min()]), float(coords[0][rows.max()])],
        "support_aoi": [float(coords[1][columns.min()]), float(coords[1][columns.max()])],
        "outside": (
            f"nodes with fewer than {_CORRECTION_MIN_COUNT} wall observations take the value of the nearest node "
            f"with them; beyond the grid, the value at its edge (clamped, never extrapolated)"
        ),
    }
    return xr.Dataset(
        {
            "correction": (CORRECTION_DIMS, c, attrs),
            "correction_count": (
                CORRECTION_DIMS,
                all_count.reshape(shape).astype(np.int64),
                {"units": "1", "long_name": "wall observations pooled at the node"},
            ),
        },
        coords={
            CORRECTION_DIMS[0]: (CORRECTION_DIMS[0], coords[0], {"units": "m", "long_name": "distance"}),
            CORRECTION_DIMS[1]: (CORRECTION_DIMS[1], coords[1], {"units": "rad", "long_name": "angle of incidence"}),
        },
    )


def _bilinear(table: np.ndarray, d_nodes: np.ndarray, t_nodes: np.ndarray, distance, aoi) -> np.ndarray:
    """Bilinear interpolation of ``table`` (nd, nt) on equally spaced nodes, clamped to the grid; NaN where input is.

    The arithmetic of ``scipy.ndimage.map_coordinates`` (order 1, mode ``"nearest"``, no prefilter) to the bit:
    along each axis the weights ``1 - t`` and ``1 - (1 - t)`` of the fraction ``t``, beyond the last node the
    node before it (with a weight of 0), and each sum from 0 over the four neighbours in order, each
    ``(value * w_d) * w_theta``; in blocks of pixels whose buffers stay in the cache (2.6x faster than it).
    """
    block = 1 << 14
    distance, aoi = np.broadcast_arrays(np.asarray(distance), np.asarray(aoi))
    out = np.empty(distance.shape)
    # map_coordinates mirrors an index beyond the last node to the one before it: one row and column more
    padded = np.pad(table, ((0, 1), (0, 1)), mode="reflect")
    flat, width = padded.ravel(), padded.shape[1]
    total, buffer = out.reshape(-1), np.empty(min(out.size, block))
    for start in range(0, out.size, block):
        part = slice(start, start + block)
        # the nodes are equally spaced: a position's fractional index is arithmetic, no search
        index = [
            (np.clip(values.reshape(-1)[part].astype(np.float64), nodes[0], nodes[-1]) - nodes[0])
            / (nodes[1] - nodes[0])
            for values, nodes in ((distance, d_nodes), (aoi, t_nodes))
        ]
        missing = ~(np.isfinite(index[0]) & np.isfinite(index[1]))
        floors, weights = [], []
        for position in index:
            np.copyto(position, 0.0, where=missing)
            floors.append(np.floor(position))
            low = 1.0 - (position - floors[-1])
            weights.append((low, 1.0 - low))
        base = (floors[0] * width + floors[1]).astype(np.intp)
        sums, values = total[part], buffer[: base.size]
        sums[...] = 0.0
        for offset, (i, j) in zip((0, 1, width, width + 1), ((0, 0), (0, 1), (1, 0), (1, 1)), strict=True):
            # the indices are in range; mode="raise" would buffer the output
            np.take(flat[offset:], base, out=values, mode="clip")
            values *= weights[0][i]
            values *= weights[1][j]
            sums += values
        np.copyto(sums, np.nan, where=missing)
    return out


def correction_factor(correction: xr.DataArray, distance, aoi):
    """Look up the residual correction ``c(d, theta)`` of :func:`fit_correction`.

    Bilinear between the grid's nodes; beyond the grid, the value at its edge
    (the distance and AOI are clamped to the grid's range): never extrapolated.

    Parameters
    ----------
    correction : DataArray on :data:`CORRECTION_DIMS`
        Node values on equally spaced ``correction_distance`` (m) and
        ``correction_aoi`` (rad) coordinates (a calibration store's ``correction``).
    distance : ndarray or DataArray, metres
    aoi : ndarray or DataArray, radians

    Returns
    -------
    ndarray or DataArray of float64
        The broadcast of ``distance`` and ``aoi``; NaN where either is NaN.
        Lazy on dask.

    Raises
    ------
    ValueError
        ``correction`` is not on :data:`CORRECTION_DIMS`, or its nodes are not
        equally spaced and increasing.
    """
    if not isinstance(correction, xr.DataArray) or set(correction.dims) != set(CORRECTION_DIMS):
        shown = getattr(correction, "dims", type(correction).__name__)
        raise ValueError(f"correction must be a DataArray on {CORRECTION_DIMS}, got {shown!r}")
    table = correction.transpose(*CORRECTION_DIMS).values.astype(np.float64)
    nodes = [correction[dim].values.astype(np.float64) for dim in CORRECTION_DIMS]
    for dim, values in zip(CORRECTION_DIMS, nodes, strict=True):
        steps = np.diff(values)
        if values.size < 2 or not (steps > 0).all() or not np.allclose(steps, steps[0], rtol=1e-6):
            raise ValueError(f"correction's {dim} nodes must be at least 2, increasing and equally spaced")
    if isinstance(distance, xr.DataArray) or isinstance(aoi, xr.DataArray):
        return xr.apply_ufunc(
            partial(_bilinear, table, *nodes), distance, aoi, dask="parallelized", output_dtypes=[np.float64]
        )
    return _bilinear(table, *nodes, distance, aoi)


def reference_scale(
    coef: np.ndarray,
    views: Iterable[Observation],
    roi: Roi,
    reflectance: float,
    correction: xr.DataArray | None = None,
) -> tuple[float, dict]:
    """Compute the scale k of eq. 6 from views of a reference panel of known reflectance.

    On every panel pixel, ``I / (f(d, theta) c(d, theta) cos(theta))`` is the panel's
    reflectance relative to the calibration wall (f is fitted to the wall's
    ``I / cos(theta)``): its median over the roi pixels of all views is the
    intensity ratio r of panel and wall under the same conditions, and
    ``k = r / reflectance``.

    Parameters
    ----------
    coef : (5, H, W) ndarray of float64
        Fitted coefficients on the sensor grid (NaN pixels are skipped).
    views : iterable of Observation
        Views of the panel on the sensor grid, consumed one at a time.
    roi : Roi
        Panel pixels, sensor coordinates, in every view.
    reflectance : float
        The panel's known reflectance, in (0, 1].
    correction : DataArray, optional
        The residual correction c (:func:`fit_correction`); default none (c = 1).

    Returns
    -------
    scale_k : float
    details : dict
        ``ratio`` (r), ``n_pixels``, ``n_views``, ``relative_spread`` (robust
        standard deviation of the per-pixel ratios, 1.4826 MAD / r),
        ``view_range`` ((max - min) / r of the per-view medians) and
        ``per_view`` (view name -> median ratio).

    Raises
    ------
    CalibrationError
        No view, or a view without a valid, calibrated pixel in the roi.
    """
    if not 0.0 < reflectance <= 1.0:
        raise CalibrationError(f"reference reflectance must be in (0, 1], got {reflectance!r}")
    rows, cols = roi.slices
    local = coef[:, rows, cols].reshape(5, -1)
    ratios, per_view = [], {}
    for view in views:
        intensity, distance, aoi, ok = _usable(
            *(array[rows, cols] for array in (view.intensity, view.distance, view.aoi, view.valid))
        )
        f = instrument_function(local, distance, aoi) * np.cos(aoi)
        if correction is not None:
            f = f * correction_factor(correction, distance, aoi)
        with np.errstate(invalid="ignore"):
            ok &= f > 0
        if not ok.any():
            raise CalibrationError(
                f"{view.name}: the reference roi (y {list(roi.y)}, x {list(roi.x)}) has no valid pixel with a "
                f"fitted calibration in this view; check calibration.reference.roi in campaign.yaml and that the "
                f"panel is seen there"
            )
        ratio = intensity[ok] / f[ok]
        per_view[Path(view.name).name] = float(np.median(ratio))
        ratios.append(ratio)
    if not ratios:
        raise CalibrationError("no reference panel view given; calibration.reference.views needs at least one view")
    ratios = np.concatenate(ratios)
    ratio = float(np.median(ratios))
    medians = np.array(list(per_view.values()))
    details = {
        "ratio": ratio,
        "n_pixels": int(ratios.size),
        "n_views": len(per_view),
        "relative_spread": float(_MAD_SIGMA * np.median(np.abs(ratios - ratio)) / ratio),
        "view_range": float((medians.max() - medians.min()) / ratio),
        "per_view": per_view,
    }
    return ratio / reflectance, details


def calibration_diagnostics(ds: xr.Dataset) -> dict:
    """Fit quality and the spatial behaviour of the coefficients (paper section 3.3, Table 2).

    Parameters
    ----------
    ds : Dataset
        From :func:`fit_calibration` or :func:`calibrate`.

    Returns
    -------
    dict
        Over the converged pixels: ``mean_r2`` (paper: 0.98), ``median_r2``;
        ``variability_percent`` (term -> 100 std / |mean| across the image;
        paper: A 8.94, B 3.92, C 1.79, D 1.38, E 4.44, in an unstated gauge; E
        is 0 in the gauge E = 1); ``correlation`` (matrix across pixels of the
        terms that vary, listed in ``correlation_terms``; paper Table 2: C-D
        -0.99); ``n_fitted``, ``n_pixels`` and ``status_counts``
        (status name -> pixels).
    """
    status = np.asarray(ds["status"]).ravel()
    fitted = status == 0
    coef = np.asarray(ds["coef"].transpose("term", ...)).reshape(len(TERMS), -1)[:, fitted]
    r2 = np.asarray(ds["r2"]).ravel()[fitted]
    counts = {name: int(np.count_nonzero(status == code)) for code, name in CALIBRATION_STATUS.items()}
    if not fitted.any():
        raise CalibrationError(f"no pixel has a fitted calibration (status counts {counts})")
    mean, std = coef.mean(axis=1), coef.std(axis=1)
    varying = [index for index in range(len(TERMS)) if std[index] > 0]
    correlation = np.corrcoef(coef[varying]) if varying else np.empty((0, 0))
    return {
        "mean_r2": float(r2.mean()),
        "median_r2": float(np.median(r2)),
        "variability_percent": {term: float(100.0 * s / abs(m)) for term, m, s in zip(TERMS, mean, std)},
        "correlation_terms": [TERMS[index] for index in varying],
        "correlation": np.atleast_2d(correlation).tolist(),
        "n_fitted": int(fitted.sum()),
        "n_pixels": int(status.size),
        "status_counts": counts,
    }


class _WallSamples:
    """Raw wall observations kept while the views stream by, for the calibration's figures.

    Memory is bounded whatever the number of views: every view of a few sample
    pixels on a grid over the crop (paper Fig. 9), about ``_WALL_SAMPLES``
    random usable pixels of the crop spread evenly over the views, and the full
    images of one view, the most perpendicular so far (smallest median AOI over
    the usable pixels of the crop; paper Fig. 10). :meth:`dataset` adds their
    reflectance once the calibration is fitted. A larger random sample (``pool``
    observations over all views) serves the residual correction (:meth:`pool`).

    Parameters
    ----------
    crop : Roi
        The campaign's usable sensor region.
    n_views : int
        Wall views that will be added.
    pool : int, optional
        Random usable observations of the crop to keep over all views for
        :meth:`pool` (at least those of the figures).
    seed : int, optional
        Seed of the random pixel choice.
    """

    def __init__(self, crop: Roi, n_views: int, pool: int = 0, seed: int = 0):
        (top, bottom), (left, right) = crop.y, crop.x
        rows = [top + int(f * (bottom - top)) for f in _SAMPLE_ROWS]
        columns = [left + int(f * (right - left)) for f in _SAMPLE_COLUMNS]
        self.pixels = np.array([(row, column) for row in rows for column in columns]).T
        self.crop = crop
        self.shown = -(-_WALL_SAMPLES // max(1, n_views))
        self.per_view = max(self.shown, -(-pool // max(1, n_views)))
        self.rng = np.random.default_rng(seed)
        self.views: list[str] = []
        self.probes: list[np.ndarray] = []
        self.random: list[tuple[np.ndarray, np.ndarray]] = []
        self.image: tuple[str, float, np.ndarray] | None = None

    def add(self, view: Observation, stem: str) -> None:
        """Keep what is needed of one wall view (unusable observations are NaN)."""
        shape = np.shape(view.aoi)
        intensity, distance, aoi, ok = _usable(view.intensity, view.distance, view.aoi, view.valid)
        values = np.where(ok, np.stack([intensity, distance, aoi]), np.nan)
        inside = np.zeros(shape, dtype=bool)
        inside[self.crop.slices] = True
        candidates = np.flatnonzero(ok & inside.ravel())
        chosen = self.rng.choice(candidates, min(self.per_view, candidates.size), replace=False)
        self.views.append(stem)
        self.probes.append(values[:, np.ravel_multi_index(self.pixels, shape)].T)
        self.random.append((chosen, values[:, chosen]))
        median = float(np.median(aoi[candidates])) if candidates.size else np.inf
        if self.image is None or median < self.image[1]:
            self.image = (stem, median, values.reshape(3, *shape))

    def pool(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return the random observations of all views: flat sensor index (N,), view index (N,), values (3, N).

        The values are intensity, distance (m) and AOI (rad).
        """
        pixels = np.concatenate([index for index, _ in self.random])
        views = np.repeat(np.arange(len(self.random)), [index.size for index, _ in self.random])
        return pixels, views, np.concatenate([values for _, values in self.random], axis=1)

    def dataset(self, coef: np.ndarray, scale_k: float, correction: xr.DataArray | None = None) -> xr.Dataset:
        """Return the kept observations with their reflectance under the fitted calibration.

        Parameters
        ----------
        coef : (5, H, W) ndarray of float64
            The fitted coefficients on the sensor grid.
        scale_k : float
        correction : DataArray, optional
            The residual correction (:func:`fit_correction`).

        Returns
        -------
        Dataset
            ``sample_obs (sample_pixel, view, quantity)`` with coordinates
            ``sample_y``, ``sample_x`` (sample_pixel) and ``view`` (wall view
            stems); ``wall_obs (wall_sample, quantity)`` with coordinates
            ``wall_y``, ``wall_x``, ``wall_view`` (wall_sample); ``wall_image
            (quantity, y, x)`` of one view (attr ``view``); ``quantity`` =
            :data:`SAMPLE_QUANTITIES`.
        """
        width = coef.shape[2]
        probes = np.stack(self.probes, axis=1)
        rows, columns = self.pixels
        # the first self.shown of each view's random choice, in sensor order
        shown = [np.argsort(index[: self.shown]) for index, _ in self.random]
        chosen = np.concatenate([index[order] for (index, _), order in zip(self.random, shown, strict=True)])
        random = np.concatenate([values[:, order] for (_, values), order in zip(self.random, shown, strict=True)], 1)
        wall_y, wall_x = np.divmod(chosen, width)
        stem, _, image = self.image
        units = {"units": "intensity: 1, distance: m, aoi: rad, reflectance: 1"}
        return xr.Dataset(
            {
                "sample_obs": (
                    ("sample_pixel", "view", "quantity"),
                    with_reflectance(probes, coef[:, rows, columns][:, :, None], scale_k, -1, correction),
                    {**units, "long_name": "wall observations of the sample pixels in every wall view"},
                ),
                "wall_obs": (
                    ("wall_sample", "quantity"),
                    with_reflectance(random, coef[:, wall_y, wall_x], scale_k, 0, correction).T,
                    {**units, "long_name": "wall observations at random pixels of the crop"},
                ),
                "wall_image": (
                    ("quantity", "y", "x"),
                    with_reflectance(image, coef, scale_k, 0, correction).astype(np.float32),
                    {**units, "long_name": "the most perpendicular wall view", "view": stem},
                ),
            },
            coords={
                "quantity": list(SAMPLE_QUANTITIES),
                "view": self.views,
                "sample_y": ("sample_pixel", rows, {"long_name": "sensor row"}),
                "sample_x": ("sample_pixel", columns, {"long_name": "sensor column"}),
                "wall_y": ("wall_sample", wall_y, {"long_name": "sensor row"}),
                "wall_x": ("wall_sample", wall_x, {"long_name": "sensor column"}),
                "wall_view": ("wall_sample", np.repeat(self.views, [order.size for order in shown])),
            },
        )


def with_reflectance(
    values: np.ndarray, coef: np.ndarray, scale_k: float, axis: int, correction: xr.DataArray | None = None
) -> np.ndarray:
    """Observations (intensity, distance, aoi along ``axis``) with their reflectance ``I / (k f c)`` appended.

    Parameters
    ----------
    values : ndarray
        Intensity (camera units), distance (m) and AOI (rad), stacked along ``axis`` (size 3).
    coef : (5, ...) ndarray
        Coefficients A..E of the instrument function; broadcasts against the
        observations without ``axis``.
    scale_k : float
        The calibration's scale k.
    axis : int
        The axis of the quantities.
    correction : DataArray, optional
        The residual correction c (:func:`fit_correction`); default none (c = 1).

    Returns
    -------
    ndarray
        ``values`` with the reflectance appended along ``axis`` (size 4); NaN
        where ``f <= 0`` or an input is NaN.
    """
    intensity, distance, aoi = np.moveaxis(values, axis, 0)
    f = instrument_function(coef, distance, aoi)
    if correction is not None:
        f = f * correction_factor(correction, distance, aoi)
    with np.errstate(invalid="ignore", divide="ignore"):
        reflectance = np.where(f > 0, intensity / (scale_k * f), np.nan)
    return np.concatenate([values, np.expand_dims(reflectance, axis)], axis=axis)


def observe_view(campaign: Campaign, path: os.PathLike, aoi: Mapping, region: Roi | None = None) -> Observation:
    """Read one view and compute its AOI and distance on the full sensor, as the calibration does.

    Parameters
    ----------
    campaign : Campaign
        The campaign whose camera took the view.
    path : path-like
        The view file.
    aoi : mapping
        AOI parameters ``window``, ``jump``, ``max_window``
        (:func:`surffin.method.geometry.frame_angle_of_incidence`).
    region : Roi, optional
        Sensor pixels to observe, at less cost: their values are the full sensor's, to the bit; default all.

    Returns
    -------
    Observation
        The view's intensity, distance (m), AOI (rad) and valid mask on the full sensor (or the
        ``region``); saturated pixels are not valid, but their points take part in the AOI.
    """
    view = campaign.read_view(path)
    aoi, distance = frame_angle_of_incidence(
        view.xyz, aoi["window"], jump=aoi["jump"], max_window=aoi["max_window"], region=region
    )
    part = (slice(None), slice(None)) if region is None else region.slices
    valid, radiometric = view.valid[part], view.radiometric[part]
    saturated = int(valid.sum() - radiometric.sum())
    return Observation(str(path), view.intensity[part], distance, aoi, radiometric, saturated)


class _SpilledViews:
    """Wall observations kept on disk between the calibration's two passes over the wall.

    The second pass needs each wall view's distance and AOI again: computing them
    twice cost about half of the calibration's time. Kept in memory they would grow
    with the number of views (about 6.5 MB a 640 x 480 view), so they go to a
    temporary folder, removed on exit, and are read back one at a time, exactly
    as computed.
    """

    _ARRAYS = ("intensity", "distance", "aoi", "valid")

    def __init__(self) -> None:
        self._folder = tempfile.TemporaryDirectory(prefix="surffin-calibration-")
        self._kept: dict[str, tuple[Path, int]] = {}

    def __enter__(self) -> _SpilledViews:
        return self

    def __exit__(self, *exc) -> None:
        self._folder.cleanup()

    def keep(self, view: Observation) -> None:
        """Write ``view``'s arrays to the folder."""
        prefix = Path(self._folder.name, str(len(self._kept)))
        self._kept[view.name] = (prefix, view.saturated)
        for field in self._ARRAYS:
            np.save(f"{prefix}-{field}.npy", getattr(view, field), allow_pickle=False)

    def get(self, name: str) -> Observation:
        """Read back the observation of view file ``name`` that :meth:`keep` wrote."""
        prefix, saturated = self._kept[name]
        arrays = {field: np.load(f"{prefix}-{field}.npy", allow_pickle=False) for field in self._ARRAYS}
        return Observation(name, **arrays, saturated=saturated)


def calibration_set(campaign: Campaign, wall: str, reference: str) -> Calibration:
    """Another calibration set of a campaign's camera, in folders that ``campaign.yaml`` does not name.

    E.g. a repeat acquisition for repeatability: views of the same wall and of
    the same reference panel, whose reflectance and roi are those of the
    campaign's ``calibration:`` section.

    Parameters
    ----------
    campaign : Campaign
        With a ``calibration:`` section.
    wall, reference : str
        Folders of the wall and of the panel views, relative to the campaign
        directory.

    Returns
    -------
    Calibration
        To pass to :func:`calibrate`.

    Raises
    ------
    CalibrationError
        The campaign has no calibration section, or a folder is outside the
        campaign directory, missing, or holds fewer than 2 view files.
    ViewFileError
        A view file is broken, or two share a stem.
    """
    from surffin.io.campaign import MIN_VIEWS, Calibration, Reference
    from surffin.io.viewfile import check_view, list_views

    if campaign.calibration is None:
        raise CalibrationError(
            f"{campaign.path}: no calibration section, so no reference reflectance and roi for the calibration set "
            f"{wall}, {reference}; add calibration: to campaign.yaml"
        )
    views = {}
    for key, relative in (("wall", wall), ("reference", reference)):
        folder = (campaign.root / relative).resolve()
        if not folder.is_relative_to(campaign.root) or not folder.is_dir():
            raise CalibrationError(
                f"{folder}: calibration set {key} folder {relative!r} is not a folder inside the campaign "
                f"directory {campaign.root}"
            )
        found = list_views(folder)
        if len(found) < MIN_VIEWS:
            raise CalibrationError(
                f"{folder}: the calibration set's {key} folder holds {len(found)} view files; expected at least "
                f"{MIN_VIEWS} (*.npz, *.ply, *.raw)"
            )
        for path in found:
            check_view(path, **campaign.camera.view_kwargs)
        views[key] = tuple(found)
    panel = campaign.calibration.reference
    return Calibration(wall=views["wall"], reference=Reference(views["reference"], panel.reflectance, panel.roi))


def calibrate(
    campaign: Campaign,
    *,
    calibration: Calibration | None = None,
    window: int = DEFAULT_WINDOW,
    jump: float = DEFAULT_JUMP,
    max_window: int = DEFAULT_MAX_WINDOW,
    min_obs: int = DEFAULT_MIN_OBS,
    angular_smoothing: float = DEFAULT_ANGULAR_SMOOTHING,
    residual_correction: bool = DEFAULT_RESIDUAL_CORRECTION,
    exclude: Collection[str] = (),
    progress: Callable[[int, int], None] | None = None,
) -> xr.Dataset:
    """Fit the radiometric calibration of a campaign's camera.

    The wall views are read one at a time (AOI and distance on the full sensor
    by :mod:`surffin.method.geometry`) and added to :class:`WallStatistics`, so memory
    does not grow with their number (the views a second pass needs wait in a
    temporary folder, :class:`_SpilledViews`); then every pixel is fitted
    (:func:`fit_calibration`), the residual correction is fitted to random wall
    observations kept while they streamed by (:func:`fit_correction`), up to
    :data:`~surffin.method.noise.NOISE_VIEWS` wall views are taken again for the
    intensity noise model (:mod:`surffin.method.noise`) and the reference panel
    views give the scale k (:func:`reference_scale`).

    Parameters
    ----------
    campaign : Campaign
        With a ``calibration:`` section, unless ``calibration`` is given.
    calibration : Calibration, optional
        The views to fit (default: the campaign's ``calibration:`` section),
        e.g. another set of :func:`calibration_set`.
    window, jump, max_window : optional
        AOI plane-fit window (odd, pixels), depth-jump threshold and largest
        window of :func:`surffin.method.geometry.angle_of_incidence`.
    min_obs : int, optional
        Fewest wall observations of a pixel for a fit.
    angular_smoothing : float, optional
        Smoothing of the angular factor over the sensor (:func:`fit_calibration`).
    residual_correction : bool, optional
        Learn the factor ``c(d, theta)`` that eq. 5 leaves (:func:`fit_correction`),
        from about 10^6 random wall observations of the crop kept while the
        views stream by, in one alternation: c from their ratios to the plain
        eq. 5 fit, eq. 5 refitted per pixel to ``I / c`` (the wall views
        taken a second time), c again from the ratios to that fit; the scale k
        and the reflectance use it (``R = I / (k f c)``). False: the paper's
        plain eq. 5, fitted to ``I`` itself. The noise model is the same either way.
    exclude : collection of str, optional
        Stems of wall views left out of the fit (e.g. held out for validation).
    progress : callable (done, total), optional
        Called after each view read (wall; the wall views again, all of them
        with ``residual_correction``, else those of the noise model; then
        reference views).

    Returns
    -------
    Dataset
        :func:`fit_calibration`'s variables on the full sensor grid; a few
        raw wall observations with their reflectance, for figures and checks:
        ``sample_obs`` (every view of six pixels spread over the crop),
        ``wall_obs`` (about 3000 random pixels of the crop over all views) and
        ``wall_image`` (the most perpendicular view), along ``quantity`` =
        :data:`SAMPLE_QUANTITIES`; with ``residual_correction``, ``correction``
        and ``correction_count`` of :func:`fit_correction`; the wall's intensity noise model
        (``noise_variance`` per ``noise_intensity``, :mod:`surffin.method.noise`); attrs ``scale_k``,
        ``reference_reflectance``, ``reference`` (details of
        :func:`reference_scale`), ``diagnostics``
        (:func:`calibration_diagnostics`), ``campaign``, ``calibration_set``
        (``{"wall", "reference"}`` folders of the views, relative to the
        campaign directory), per view file (relative to the campaign directory)
        ``saturated_pixels`` (left out of the fit and the scale) and
        ``settings`` (its ``<stem>.meta.json``), and provenance.

    Raises
    ------
    CalibrationError
        No calibration section, unknown excluded views, no fitted pixel, or a
        reference view without valid panel pixels.
    """
    if calibration is None and campaign.calibration is None:
        raise CalibrationError(
            f"{campaign.path}: no calibration section; add calibration: (wall, reference) or use an existing "
            f"calibration store"
        )
    calibration = calibration or campaign.calibration
    reference = calibration.reference
    folders = {
        key: str(views[0].parent.relative_to(campaign.root))
        for key, views in (("wall", calibration.wall), ("reference", reference.views))
    }
    excluded = set(exclude)
    unknown = sorted(excluded - {path.stem for path in calibration.wall})
    if unknown:
        raise CalibrationError(
            f"{campaign.path}: the wall folder {folders['wall']} has no views named {unknown}; exclude only its "
            f"view stems"
        )
    wall = [path for path in calibration.wall if path.stem not in excluded]
    noise_views = wall[:: max(1, -(-len(wall) // NOISE_VIEWS))]
    total = 2 * len(wall) if residual_correction else len(wall) + len(noise_views)
    total += len(reference.views)
    step = max(1, total // 10)
    done = 0

    def advance(path) -> None:
        nonlocal done
        done += 1
        if progress is not None:
            progress(done, total)
        if done % step == 0 or done == total:
            log.info("calibration: %d/%d views (%s)", done, total, path.name)

    aoi = {"window": window, "jump": jump, "max_window": max_window}
    stats = WallStatistics((campaign.camera.height, campaign.camera.width))
    samples = _WallSamples(campaign.crop, len(wall), pool=_CORRECTION_SAMPLES if residual_correction else 0)

    def checked(ds: xr.Dataset) -> dict:
        try:
            return calibration_diagnostics(ds)
        except CalibrationError as exc:
            raise CalibrationError(
                f"{campaign.path}: wall folder {folders['wall']}: {exc}; the wall views must cover each pixel at "
                f"several distances and angles, at least {min_obs} times"
            ) from exc

    def residuals(pooled: tuple, coef: np.ndarray, penalty: float | None = None) -> xr.Dataset:
        pixels, views, (intensity, distance, angle) = pooled
        f = instrument_function(coef.reshape(5, -1).take(pixels, axis=1), distance, angle)
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = intensity / (f * np.cos(angle))
        try:
            return fit_correction(ratio, distance, angle, views, penalty=penalty)
        except CalibrationError as exc:
            raise CalibrationError(
                f"{campaign.path}: wall folder {folders['wall']}: {exc}; add wall views, or calibrate with "
                f"residual_correction=False"
            ) from exc

    saturated = {}
    again = wall if residual_correction else noise_views
    with _SpilledViews() as spilled:
        for path in wall:
            view = observe_view(campaign, path, aoi)
            saturated[str(path.relative_to(campaign.root))] = view.saturated
            stats.add(view.intensity, view.distance, view.aoi, view.valid)
            samples.add(view, path.stem)
            if path in again:
                spilled.keep(view)
            advance(path)
        ds = fit_calibration(stats, min_obs=min_obs, angular_smoothing=angular_smoothing)
        diagnostics = checked(ds)
        # the noise model flat-fields with the plain fit (its 3 x 3 ratios cancel any smooth factor)
        plain = ds["coef"].values
        noise = NoiseStatistics()
        correction = first = None
        if residual_correction:
            # the random observations are all kept by now: pooled once for both fits of the correction
            pooled = samples.pool()
            first = residuals(pooled, plain)["correction"]
            refit = WallStatistics(stats.shape)
        for path in again:
            view = spilled.get(str(path))
            if path in noise_views:
                expected = instrument_function(plain, view.distance, view.aoi) * np.cos(view.aoi)
                noise.add(view.intensity, view.intensity / expected, view.valid)
            if residual_correction:
                factor = correction_factor(first, view.distance, view.aoi)
                refit.add(view.intensity / factor, view.distance, view.aoi, view.valid)
            advance(path)
    if residual_correction:
        ds = fit_calibration(refit, min_obs=min_obs, angular_smoothing=angular_smoothing, start=plain)
        diagnostics = checked(ds)
        # the smoothness cross-validated on the ratios to the plain fit
        ds = ds.merge(residuals(pooled, ds["coef"].values, first.attrs["penalty"]))
        ds["correction"].attrs.update({key: first.attrs[key] for key in ("cv_penalties", "cv_scores")})
        correction = ds["correction"]
        log.info(
            "calibration: residual correction %.4f..%.4f over %d wall observations (penalty %g)",
            float(correction.min()),
            float(correction.max()),
            correction.attrs["n_samples"],
            correction.attrs["penalty"],
        )

    def panel_views():
        for path in reference.views:
            view = observe_view(campaign, path, aoi)
            saturated[str(path.relative_to(campaign.root))] = view.saturated
            yield view
            advance(path)

    scale_k, details = reference_scale(
        ds["coef"].values, panel_views(), reference.roi, reference.reflectance, correction
    )
    log.info(
        "calibration: %d of %d pixels fitted (status counts %s), mean R2 %.4f, scale_k %.5g",
        diagnostics["n_fitted"],
        diagnostics["n_pixels"],
        diagnostics["status_counts"],
        diagnostics["mean_r2"],
        scale_k,
    )
    parameters = {
        **aoi,
        "min_obs": min_obs,
        "angular_smoothing": angular_smoothing,
        "residual_correction": bool(residual_correction),
        "exclude": sorted(excluded),
    }
    inputs = {str(path.relative_to(campaign.root)): describe_file(path) for path in (*wall, *reference.views)}
    settings = {str(path.relative_to(campaign.root)): read_settings(path) for path in (*wall, *reference.views)}
    return (
        ds.merge(samples.dataset(ds["coef"].values, scale_k, correction))
        .merge(noise.dataset())
        .assign_attrs(
            scale_k=scale_k,
            reference_reflectance=reference.reflectance,
            reference=details,
            diagnostics=diagnostics,
            campaign=campaign.name,
            calibration_set=folders,
            saturated_pixels=saturated,
            settings=settings,
            **provenance("calibration", parameters, inputs),
        )
    )


def reflectance(
    intensity: xr.DataArray,
    distance: xr.DataArray,
    aoi: xr.DataArray,
    coef: xr.DataArray,
    scale_k: float,
    correction: xr.DataArray | None = None,
) -> xr.DataArray:
    """Calibrated absolute reflectance ``R = I / (k f(d, theta) c(d, theta))`` (paper eq. 2).

    Parameters
    ----------
    intensity : (view, y, x) DataArray
        Camera intensity; ``y``, ``x`` coordinates are sensor indices.
    distance : (view, y, x) DataArray, metres
    aoi : (view, y, x) DataArray, radians
    coef : (term, y, x) DataArray
        The calibration's coefficients on (at least) the same sensor pixels;
        selected by the ``y``/``x`` coordinates of ``intensity``.
    scale_k : float
        The calibration's scale k.
    correction : DataArray on :data:`CORRECTION_DIMS`, optional
        The calibration's residual correction c (:func:`fit_correction`;
        clamped beyond its grid, :func:`correction_factor`); default none, c = 1
        (the paper's eq. 2).

    Returns
    -------
    (view, y, x) DataArray
        Reflectance at the observed AOI, NaN where an input is NaN or
        ``f c <= 0``. Lazy when an input is dask-backed.

    Raises
    ------
    CalibrationError
        ``scale_k`` is not a positive number, or the calibration does not cover
        the pixels of ``intensity``.
    """
    for name, array in (("intensity", intensity), ("distance", distance), ("aoi", aoi), ("coef", coef)):
        if not isinstance(array, xr.DataArray):
            raise TypeError(f"{name} must be an xarray.DataArray, got {type(array).__name__}")
    if "term" not in coef.dims:
        raise ValueError(f"coef must have dims (term, y, x), got {coef.dims}")
    if not (isinstance(scale_k, int | float | np.floating) and math.isfinite(scale_k) and scale_k > 0):
        raise CalibrationError(f"scale_k must be a positive finite number, got {scale_k!r}")
    missing = [dim for dim in ("y", "x") if dim not in intensity.coords or dim not in coef.coords]
    if missing:
        raise ValueError(f"intensity and coef need {missing} coordinates (sensor indices) to be aligned")
    try:
        intensity, distance, aoi = xr.align(intensity, distance, aoi, join="exact", copy=False)
    except ValueError as exc:
        raise ValueError(f"intensity, distance and aoi must share their coordinates: {exc}") from exc
    try:
        local = coef.sel(y=intensity["y"].values, x=intensity["x"].values)
    except KeyError as exc:
        raise CalibrationError(
            f"the calibration (y {int(coef.y.min())}..{int(coef.y.max())}, x {int(coef.x.min())}.."
            f"{int(coef.x.max())}) does not cover the image's pixels (y {int(intensity.y.min())}.."
            f"{int(intensity.y.max())}, x {int(intensity.x.min())}..{int(intensity.x.max())}); use a calibration "
            f"of the same camera on its full sensor"
        ) from exc
    factors = [] if correction is None else [correction_factor(correction, distance, aoi)]

    def kernel(counts, d, theta, *arrays):
        # R = I / (k f c), NaN where f c <= 0: the arithmetic of eq. 2 on the DataArrays, in numpy
        f = instrument_function(arrays[: len(TERMS)], d, theta)
        for factor in arrays[len(TERMS) :]:
            f *= factor
        out = counts / (scale_k * f)
        np.copyto(out, np.nan, where=~(f > 0))
        return out

    terms = [local.sel(term=term, drop=True) for term in TERMS]
    out = xr.apply_ufunc(
        kernel, intensity, distance, aoi, *terms, *factors, dask="parallelized", output_dtypes=[np.float64]
    ).transpose(*intensity.dims)
    out.name = "reflectance"
    out.attrs = {"units": "1", "long_name": "absolute reflectance at the observed angle of incidence"}
    return out


def check_calibration(path: str | os.PathLike, campaign: Campaign) -> None:
    """Check that a calibration store made by another campaign fits this campaign's camera.

    Raises
    ------
    StoreError
        The store is not a calibration, or its sensor grid is not this camera's
        (width x height), so it cannot cover the crop, or a setting of
        ``camera.match_settings`` differs between its views and the items'.
    """
    ds = open_store(path, stage="calibration", chunks=None)  # without dask: the check reads one array
    camera = campaign.camera
    grid = (ds.sizes.get("y"), ds.sizes.get("x"))
    if grid != (camera.height, camera.width):
        raise StoreError(
            f"{path}: calibration of a {grid[1]}x{grid[0]} sensor, but {campaign.path} describes a "
            f"{camera.width}x{camera.height} camera; use a calibration of the same camera"
        )
    rows, cols = campaign.crop.slices
    if not bool(ds["coef"].isel(y=rows, x=cols).notnull().any()):
        raise StoreError(f"{path}: no calibrated pixel inside the crop {campaign.crop} of {campaign.path}")
    _check_settings(path, ds.attrs.get("settings"), campaign)


def _check_settings(path, recorded: Mapping | None, campaign: Campaign) -> None:
    """Check that the settings of ``camera.match_settings`` of the calibration's views are the items' views'."""
    names = campaign.camera.match_settings
    if not names:
        return
    if recorded is None:
        raise StoreError(
            f"{path}: the calibration records no acquisition settings, but {campaign.path} asks "
            f"camera.match_settings {list(names)} to match; refit it with this surffin from views with "
            f"<stem>.meta.json sidecars, or remove camera.match_settings"
        )
    items = {
        str(view.relative_to(campaign.root)): read_settings(view)
        for item in campaign.items.values()
        for view in item.views
    }
    for name in names:
        theirs, ours = setting_values(recorded, name), setting_values(items, name)
        if len(theirs.keys() | ours.keys()) > 1:
            raise StoreError(
                f"{path}: setting {name!r} differs between the calibration's views ({describe_groups(theirs)}) and "
                f"the items' views of {campaign.path} ({describe_groups(ours)}); camera.match_settings asks them "
                f"equal: use a calibration acquired with the items' settings, or remove {name!r} from "
                f"camera.match_settings"
            )
