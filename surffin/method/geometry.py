"""Angle of incidence and distance from organized point clouds (method step 2), and mixed pixels.

Per pixel, theta = arccos(|v . n|) and d = |P|, with v the unit ray to the point P and n the
normal of a least-squares plane through the valid points of a neighbourhood of P, fitted in ray
coordinates: a pinhole camera sees n . P = c as an inverse depth q = 1/z = a x' + b y' + e, linear
in x' = x/z, y' = y/z, which carry no range noise (a PCA plane tilts away from the ray under range
noise). The moments of (x', y', q) are box-summed (cv2.boxFilter): any window costs the same.

Depth discontinuities: two neighbours are on different surfaces when their log-depths differ by
``jump`` beyond what a surface at MAX_SLOPE_DEG (80 deg) to the ray gives over their ray spacing;
a mixed pixel splits such an edge into two steeper steps (:func:`mixed_pixels`).

The support adapts: at the base level a pixel takes the first of the 9 windows containing it whose
residual is at most twice the smallest; each level doubles the windows, up to ``max_window``, while
the window is usable and its residual within 1.5 times the smallest base residual around the pixel
(the depth noise): a crease or a strong curvature refuses growth.

Curved surfaces: a grown window's plane has the surface's normal at its centroid, not at the pixel
(3.5 deg at 18 mm on a 0.3 m cylinder). Above the base level each plane comes with the slopes of the
normal with x', y' from the windows half a window away, and the pixel's normal is carried from the
centroid to the pixel along them by what the carry exceeds its noise (:func:`_carry`): on a plane
the noise is all there is and the normal is kept. Measurements: ``docs/performance.md``,
``benchmarks/bench_curved.py``.
"""

from __future__ import annotations

import math
import numbers
from typing import TYPE_CHECKING

import cv2
import numpy as np
import xarray as xr

if TYPE_CHECKING:
    from surffin.grid import Roi

__all__ = [
    "angle_of_incidence",
    "frame_angle_of_incidence",
    "mixed_pixels",
    "plane_normals",
    "DEFAULT_WINDOW",
    "DEFAULT_JUMP",
]

#: Default smallest plane-fit window, pixels (side of the square neighbourhood).
DEFAULT_WINDOW = 15
#: Default depth-jump threshold, relative: neighbours whose depths differ by more than 1 % beyond what a
#: surface at :data:`MAX_SLOPE_DEG` from the ray gives between them are on different surfaces.
DEFAULT_JUMP = 0.01
#: Default largest plane-fit window, pixels: windows of ``window * 2**k`` pixels up to this side are tried.
DEFAULT_MAX_WINDOW = 120
#: Steepest surface (angle between the surface and the plane normal to the ray, degrees) taken as one surface.
MAX_SLOPE_DEG = 80.0
_MAX_SLOPE = math.tan(math.radians(MAX_SLOPE_DEG))
_MIN_FRACTION = 0.5
# A window's pixels are collinear (no plane) when the determinant of the 2x2 scatter matrix of
# their ray coordinates is below this fraction of the product of its diagonal (1 - correlation^2):
# >= 0.33 when at least half of a window's pixels are valid (3 and 5 px windows, exhaustively),
# <= ~1e-9 on collinear pixels (rounding of float32 coordinates).
_MIN_DETERMINANT = 1e-6
_DIRECTIONS = ((0, 1), (1, 0), (1, 1), (1, -1))
# Window centres tried for each pixel, in half windows: its own first, then the 8 shifted ones.
_CANDIDATES = ((0, 0), (-1, 0), (1, 0), (0, -1), (0, 1), (-1, -1), (-1, 1), (1, -1), (1, 1))
# A window is planar enough when its mean squared residual is at most this many times the
# smallest among a pixel's candidates.
_PLANARITY = 2.0
# (row, column) of the six second moments x'x', x'y', x'q, y'y', y'q, qq.
_PAIRS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
# A larger window replaces a pixel's plane when its mean squared residual is at most this many times
# the smallest of the base windows that contain the pixel (the local noise).
_GROWTH = 1.5
# A slope of the normal carries a pixel's normal only by what it exceeds this many standard deviations of its noise.
_SIGNIFICANCE = 2.0
# Pixels per block of the per-pixel arithmetic: its temporaries stay in the L2 cache.
_BLOCK = 16384


def _check_window(window) -> int:
    if isinstance(window, bool) or not isinstance(window, numbers.Integral) or window < 3 or window % 2 == 0:
        raise ValueError(f"window must be an odd integer >= 3 (pixels), got {window!r}")
    return int(window)


def _check_max_window(max_window, window: int) -> int:
    if isinstance(max_window, bool) or not isinstance(max_window, numbers.Integral) or max_window < window:
        raise ValueError(f"max_window must be an integer >= window ({window} pixels), got {max_window!r}")
    return int(max_window)


def _check_jump(jump) -> float:
    if isinstance(jump, bool) or not isinstance(jump, numbers.Real) or not 0 < jump < math.inf:
        raise ValueError(f"jump must be a positive finite number (relative depth step), got {jump!r}")
    return float(jump)


def _log_depth(points: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Log-depth, NaN at invalid pixels, and ray coordinates x/z, y/z, zero there, (3, H * W) of one frame, float32."""
    terms = np.empty((3, valid.size), dtype=np.float32)
    z = points[2].reshape(-1)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):  # invalid pixels: set below
        np.log(z, out=terms[0])
        np.divide(points[:2].reshape(2, -1), z, out=terms[1:])
    np.copyto(terms, np.array([[np.nan], [0.0], [0.0]], dtype=np.float32), where=~valid.reshape(-1))
    return terms


def _rise(terms: np.ndarray, offset: int, scratch: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Log-depth rise from each pixel p to p + ``offset`` (flat indices), and that of a surface at MAX_SLOPE_DEG.

    ``terms`` is :func:`_log_depth`'s; both results (of the pixels p < H * W - offset) are views of ``scratch`` (an
    array like it), overwritten. Pairs that wrap around a row are not neighbours: :func:`_unwrapped` drops them.
    """
    size = terms.shape[1] - offset
    difference = np.subtract(terms[:, offset:], terms[:, :size], out=scratch[:, :size])
    rise, spacing, along = difference
    np.square(difference[1:], out=difference[1:])
    spacing += along
    np.sqrt(spacing, out=spacing)
    spacing *= np.float32(_MAX_SLOPE)
    return rise, spacing


def _unwrapped(steps: np.ndarray, shape: tuple[int, int], dx: int, reach: int) -> np.ndarray:
    """Clear the steps that wrap around a row in flat masks of steps, in place, and return the masks.

    ``steps`` (..., H * W) bool holds a step from each pixel ``reach`` pixels along a direction of column step
    ``dx``; those leaving the frame's columns land on another row.
    """
    columns = slice(shape[1] - reach, None) if dx > 0 else slice(0, reach)
    if dx:
        steps.reshape(*steps.shape[:-1], *shape)[..., columns] = False
    return steps


def _jump_edges(points: np.ndarray, valid: np.ndarray, jump: float) -> np.ndarray:
    """Edge mask (H, W) bool of the depth discontinuities of one frame (module docstring)."""
    terms = _log_depth(points, valid)
    scratch = np.empty_like(terms)
    edge = np.zeros(valid.size, dtype=bool)
    step = np.empty(valid.size, dtype=bool)  # a jump from each pixel p to p + offset
    for dy, dx in _DIRECTIONS:
        for reach in (1, 2):
            offset = reach * (dy * valid.shape[1] + dx)
            size = valid.size - offset
            if size <= 0:
                continue
            rise, steepest = _rise(terms, offset, scratch)
            np.abs(rise, out=rise)
            rise -= np.float32(jump)
            np.greater(rise, steepest, out=step[:size])
            jumps = _unwrapped(step, valid.shape, dx, reach)[:size]
            if reach == 1:
                edge[:size] |= jumps
                edge[offset:] |= jumps
            else:
                edge[offset // 2 : offset // 2 + size] |= jumps
    return edge.reshape(valid.shape)


def _mixed(points: np.ndarray, valid: np.ndarray, jump: float) -> np.ndarray:
    """Mixed-pixel mask (H, W) bool of one frame (:func:`mixed_pixels`)."""
    terms = _log_depth(points, valid)
    scratch = np.empty_like(terms)
    mixed = np.zeros(valid.size, dtype=bool)
    half = np.float32(jump / 2)
    for dy, dx in _DIRECTIONS:
        offset = dy * valid.shape[1] + dx
        if 3 * offset >= valid.size:
            continue
        # the step from each pixel to the next along (dy, dx), stored at the first: a jump up or
        # down (judged at half the jump), or not steeper than 80 deg up, or down
        size = valid.size - offset
        rise, steepest = _rise(terms, offset, scratch)
        steps = np.empty((4, valid.size), dtype=bool)
        steps[:, size:] = False  # from the pixels without a neighbour there
        up, down, not_up, not_down = steps[:, :size]
        np.less_equal(rise, steepest, out=not_up)
        np.greater_equal(rise, -steepest, out=not_down)
        steepest += half
        np.greater(rise, steepest, out=up)
        np.less(rise, -steepest, out=down)
        up, down, not_up, not_down = _unwrapped(steps, valid.shape, dx, 1)
        # pixel p = q + 2 d: outer step from q, inner steps from q + d and p, outer step from p + d
        outer, before, after, beyond = (slice(k * offset, valid.size - (3 - k) * offset) for k in range(4))
        mixed[after] |= up[before] & up[after] & not_up[outer] & not_up[beyond]
        mixed[after] |= down[before] & down[after] & not_down[outer] & not_down[beyond]
    return mixed.reshape(valid.shape)


def _row_blocks(height: int, width: int) -> list[slice]:
    """Row slices of about :data:`_BLOCK` pixels covering an image."""
    step = max(1, _BLOCK // max(width, 1))
    return [slice(start, min(start + step, height)) for start in range(0, height, step)]


def _box(image: np.ndarray, window: int, out: np.ndarray | None = None) -> np.ndarray:
    """Unnormalised ``window x window`` box sums of a 2-D image, zero outside it."""
    return cv2.boxFilter(image, -1, (window, window), dst=out, normalize=False, borderType=cv2.BORDER_CONSTANT)


def _centre(coordinates: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Pick a point (3,) amid the valid pixels' coordinates: the mean of a 1-in-64 sample, else of all, else 0."""
    for step in (8, 1):
        sample = coordinates[:, ::step, ::step][:, valid[::step, ::step]]
        if sample.size:
            return sample.mean(axis=1)
    return np.zeros(3)


def _moments(points: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel moments of the ray coordinates x' = x/z, y' = y/z and inverse depth q = 1/z.

    Returns
    -------
    moments : (10, H, W) ndarray of float64
        count (the valid mask), x', y', q, x'x', x'y', x'q, y'y', y'q, qq, with x', y', q
        taken relative to ``centre`` and zero at invalid pixels.
    centre : (3,) ndarray of float64
        The (x', y', q) subtracted, :func:`_centre`.
    """
    moments = np.empty((10, *valid.shape))
    moments[0] = valid
    coordinates = moments[1:4]
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):  # invalid pixels: zeroed below
        np.divide(1.0, points[2], out=coordinates[2])
        np.multiply(points[:2], coordinates[2], out=coordinates[:2])
        centre = _centre(coordinates, valid)
        coordinates -= centre[:, None, None]
    np.copyto(coordinates, 0.0, where=~valid)
    for k, (i, j) in enumerate(_PAIRS, start=4):
        np.multiply(coordinates[i], coordinates[j], out=moments[k])
    return moments, centre


def _pool(image: np.ndarray) -> np.ndarray:
    """Sum over 2 x 2 blocks of the last two axes (odd sizes padded with zeros)."""
    height, width = image.shape[-2:]
    if height % 2 or width % 2:
        image = np.pad(image, [(0, 0)] * (image.ndim - 2) + [(0, height % 2), (0, width % 2)])
    size = (image.shape[-1] // 2, image.shape[-2] // 2)
    planes = image.reshape(-1, *image.shape[-2:])
    pooled = np.empty((planes.shape[0], size[1], size[0]), dtype=image.dtype)
    for plane, out in zip(planes, pooled):
        # INTER_AREA at exactly half the size is the mean of each 2 x 2 block
        cv2.resize(plane, size, dst=out, interpolation=cv2.INTER_AREA)
    pooled *= 4.0
    return pooled.reshape(*image.shape[:-2], size[1], size[0])


def _upsample(cells: np.ndarray, level: int, shape: tuple[int, int]) -> np.ndarray:
    """Each cell's value at the pixels it pools (cells of ``2**level`` pixels), cut to ``shape``."""
    factor = 2**level
    size = (cells.shape[-1] * factor, cells.shape[-2] * factor)
    planes = cells.reshape(-1, *cells.shape[-2:])
    repeated = np.empty((planes.shape[0], size[1], size[0]), dtype=cells.dtype)
    for plane, out in zip(planes, repeated):
        cv2.resize(plane, size, dst=out, interpolation=cv2.INTER_NEAREST)
    return repeated.reshape(*cells.shape[:-2], size[1], size[0])[..., : shape[0], : shape[1]]


def _choose_windows(residual: np.ndarray, eligible: np.ndarray, window: int) -> tuple[np.ndarray, np.ndarray]:
    """Choose the window each pixel takes, among the 9 that contain it (module docstring).

    Parameters
    ----------
    residual : (H, W) ndarray of float64
        Mean squared depth residual of the plane of the window centred on each
        pixel, m^2; inf where that window is not usable.
    eligible : (H, W) ndarray of bool
        Pixels that may get a normal (valid, not an edge).
    window : int
        Window side, pixels.

    Returns
    -------
    source : (H, W) ndarray of intp
        Flat index of the centre of the chosen window; -1 at pixels not eligible
        and where none of the 9 windows is usable.
    smallest : (H, W) ndarray of float32
        The smallest residual of the 9 windows, inf where none is usable.
    """
    height, width = residual.shape
    half = window // 2
    padded = np.full((height + 2 * half, width + 2 * half), np.inf, dtype=np.float32)
    np.maximum(residual, 0.0, out=padded[half : half + height, half : half + width], casting="same_kind")
    candidates = [
        padded[half * (1 + sy) : half * (1 + sy) + height, half * (1 + sx) : half * (1 + sx) + width]
        for sy, sx in _CANDIDATES
    ]
    # the minimum over the 3 x 3 centres: over the rows, then over the columns
    rows = np.minimum(padded[:height], padded[2 * half :])
    np.minimum(rows, padded[half : half + height], out=rows)
    smallest = np.minimum(rows[:, :width], rows[:, 2 * half :])
    np.minimum(smallest, rows[:, half : half + width], out=smallest)
    limit = _PLANARITY * smallest
    # number of the first candidate within the limit: min over k of k, or k + 16 beyond it
    number = np.full(residual.shape, 16, dtype=np.int8)
    for k, candidate in enumerate(candidates):
        np.minimum(number, (candidate > limit).view(np.int8) * np.int8(16) + np.int8(k), out=number)
    source = np.array([sy * half * width + sx * half for sy, sx in _CANDIDATES])[number]
    source += np.arange(width)
    source += np.arange(0, height * width, width)[:, None]
    source[~(eligible & (smallest < np.inf))] = -1
    return source, smallest


def _level_planes(
    moments: np.ndarray,
    centre: np.ndarray,
    edges: np.ndarray,
    eligible: np.ndarray,
    window: int,
    min_count: float,
    slopes: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Planes of the windows of one level of the moment pyramid, and the window each cell takes.

    Parameters
    ----------
    moments : (10, h, w) ndarray of float64
        Per-cell sums of :func:`_moments` (one pixel per cell at the base level);
        overwritten (the planes are computed in place).
    centre : (3,) ndarray
        The centre the moments are taken about.
    edges, eligible : (h, w) ndarray
        Edge pixels per cell (a window holding one is not usable); cells that may get a normal.
    window : int
        Window side, cells.
    min_count : float
        Fewest valid pixels of a usable window.
    slopes : bool, optional
        Whether the windows' centroids and noise are computed, for :func:`_normal_slopes`, and the normals
        normalised (not at the base level, whose few normals taken are normalised once gathered).

    Returns
    -------
    normal : (3, h, w) ndarray of float64
        Unit normal (with ``slopes``; else ``(a, b, e)``, not normalised), unoriented, of the window centred on
        each cell (meaningless where that window is not usable).
    residual : (h, w) ndarray of float64
        Its mean squared depth residual, m^2; inf where not usable.
    source : (h, w) ndarray of intp
        :func:`_choose_windows`: flat index of the chosen window's centre, -1 for none.
    smallest : (h, w) ndarray of float32
        The smallest residual among the cell's 9 windows.
    centroid : (2, h, w) ndarray of float64 or None
        Mean ray coordinates x', y' of the valid pixels of the window centred on
        each cell: where its plane is the surface's tangent plane, to first order.
    noise : (h, w) ndarray of float64 or None
        Variance of the direction of that window's normal from its residual,
        rad^2 (the least-squares variance of the slopes a, b over |(a, b, e)|^2).
    """
    centroid = np.empty((2, *moments.shape[1:])) if slopes else None
    noise = np.empty(moments.shape[1:]) if slopes else None
    for plane in moments:
        _box(plane, window, out=plane)
    usable = (_box(edges.astype(np.float32), window) == 0) & (moments[0] >= min_count)
    # The planes overwrite the count, first and second moments block by block, once read. The temporaries
    # of a block are views of one scratch array, written with out= in the operations' order of the formulas.
    normal, residual = moments[1:4], moments[0]
    blocks = _row_blocks(*usable.shape)
    scratch = np.empty((9, blocks[0].stop * usable.shape[1]))
    flags = np.empty(scratch.shape[1], dtype=bool)
    for rows in blocks:
        count, sums, squares = moments[0, rows], moments[1:4, rows], moments[4:, rows]
        block = scratch[:, : count.size].reshape(-1, *count.shape)
        inverse, determinant, inverse_determinant, variance, product, other = block[:6]
        mean, planar = block[6:], flags[: count.size].reshape(count.shape)
        with np.errstate(invalid="ignore", divide="ignore"):  # empty or collinear windows: discarded below
            np.divide(1.0, count, out=inverse)
            np.multiply(sums, inverse, out=mean)
            for k, (i, j) in enumerate(_PAIRS):
                squares[k] -= np.multiply(sums[i], mean[j], out=product)
            sxx, sxy, sxq, syy, syq, sqq = squares
            np.multiply(sxx, syy, out=determinant)
            determinant -= np.multiply(sxy, sxy, out=product)
            np.multiply(_MIN_DETERMINANT, sxx, out=product)
            np.greater(determinant, np.multiply(product, syy, out=product), out=planar)
            planar &= usable[rows]
            np.divide(1.0, determinant, out=inverse_determinant)
            a, b, e = sums  # the sums are no longer needed: the plane takes their place
            np.subtract(np.multiply(syy, sxq, out=product), np.multiply(sxy, syq, out=other), out=product)
            np.multiply(product, inverse_determinant, out=a)
            np.subtract(np.multiply(sxx, syq, out=product), np.multiply(sxy, sxq, out=other), out=product)
            np.multiply(product, inverse_determinant, out=b)
            mean += centre[:, None, None]
            np.subtract(mean[2], np.multiply(a, mean[0], out=product), out=product)
            np.subtract(product, np.multiply(b, mean[1], out=other), out=e)
            # residual variance of q times z^4 = 1 / mean(q)^4: depth units
            np.subtract(sqq, np.multiply(a, sxq, out=product), out=variance)
            variance -= np.multiply(b, syq, out=product)
            variance *= inverse
            if slopes:
                scale = _normalise(normal[:, rows])
                centroid[:, rows] = mean[:2]
                np.maximum(variance, 0.0, out=product)
                product *= np.add(sxx, syy, out=other)
                product *= inverse_determinant
                product *= scale
                np.multiply(product, scale, out=noise[rows])
            mean[2] *= mean[2]
            np.divide(variance, np.multiply(mean[2], mean[2], out=product), out=count)
            np.copyto(count, np.inf, where=~planar)
    source, smallest = _choose_windows(residual, eligible, window)
    return normal, residual, source, smallest, centroid, noise


def _normalise(vector: np.ndarray) -> np.ndarray:
    """Divide ``vector`` (3, ...) by its norm, in place, and return the inverse norm."""
    scale = np.multiply(vector[0], vector[0])
    square = np.multiply(vector[1], vector[1])
    scale += square
    scale += np.multiply(vector[2], vector[2], out=square)
    np.divide(1.0, np.sqrt(scale, out=scale), out=scale)
    vector *= scale
    return scale


def _normal_slopes(
    normal: np.ndarray,
    centroid: np.ndarray,
    noise: np.ndarray,
    residual: np.ndarray,
    source: np.ndarray,
    half: int,
    needed: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Model the normal around the centroid of the chosen window of some cells, to first order.

    A plane fitted to a window of a curved surface has, to first order, the
    surface's normal at the centroid of the window's points, not at a pixel
    away from it: a window shifted by half its side, cut by the image border
    or holed, or a cell's pixel off the cell's centre, errs by the curvature
    times that offset (3.5 deg for 18 mm on a 0.3 m radius). The slopes ``J``
    of the normal with the ray coordinates x', y' are the least-squares fit to
    the windows half a window away along rows and columns (those whose residual
    is within :data:`_PLANARITY` times the chosen window's: never across a
    crease), with their variance from the windows' normal noise; :func:`_carry`
    takes the normal to each pixel.

    Parameters
    ----------
    normal : (3, h, w) ndarray of float64
        Unit normals of the windows centred on each cell (:func:`_level_planes`),
        consistently oriented (``(a, b, e) . P = 1`` on the plane).
    centroid : (2, h, w) ndarray of float64
        Their centroids in ray coordinates.
    noise : (h, w) ndarray of float64
        Variance of their normals' directions, rad^2.
    residual : (h, w) ndarray of float64
        Their residuals, inf where a window is not usable.
    source : (h, w) ndarray of intp
        Flat index of each cell's chosen window's centre, -1 for none.
    half : int
        Half a window, cells.
    needed : (k,) ndarray of intp
        Flat indices of the cells whose models are computed.

    Returns
    -------
    model : (14, k) ndarray of float64
        The chosen window's normal ``n`` (3) and centroid ``m`` (2), the slopes
        ``J`` (3 x 2, row-major: d n_k / d x', d n_k / d y'; along the one axis
        with neighbours when only one has) and the variance ``V`` of ``J``'s
        rows (xx, xy, yy, 1/(x' y') units: a correction ``J o`` has variance
        ``o^T V o`` per unit of normal direction); zero at the cells without a window.
    known : (k,) ndarray of bool
        The slopes are known along both axes.
    """
    height, width = source.shape
    chosen = source.reshape(-1)[needed]
    cells = np.flatnonzero(chosen >= 0)  # the needed cells with a window
    chosen = chosen[cells]
    row, column = np.divmod(chosen, width)
    normals, centroids, residuals = normal.reshape(3, -1), centroid.reshape(2, -1), residual.reshape(-1)
    values = np.empty((14, cells.size))
    own_normal, own_centroid = values[:3], values[3:5]
    slopes, variance = values[5:11].reshape(3, 2, -1), values[11:]
    own_normal[:], own_centroid[:] = normals.take(chosen, axis=1), centroids.take(chosen, axis=1)
    limit = _PLANARITY * np.maximum(residuals[chosen], 0.0)
    noises, own_noise = noise.reshape(-1), noise.reshape(-1)[chosen]
    scatter = np.zeros((3, cells.size))  # sum of d d^T: xx, xy, yy
    spread = np.zeros((3, cells.size))  # sum of the changes' noise times d d^T
    moments = np.zeros((3, 2, cells.size))  # sum of (change of the normal) d^T
    # each neighbour's terms, written with out= in the formulas' order
    products, terms = np.empty((3, cells.size)), np.empty((3, 2, cells.size))
    for along_rows, (position, size) in enumerate(((column, width), (row, height))):  # _DIRECTIONS[:2]'s order
        for sign in (-1, 1):
            moved = position + sign * half  # the other coordinate stays inside the grid
            inside = (moved >= 0) & (moved < size)
            other = np.where(inside, moved * width + column if along_rows else row * width + moved, 0)
            unused = ~(inside & (residuals[other] <= limit))
            step = centroids.take(other, axis=1)
            step -= own_centroid
            np.copyto(step, 0.0, where=unused)
            change = normals.take(other, axis=1)
            change -= own_normal
            np.copyto(change, 0.0, where=unused)
            np.multiply(step[0], step[0], out=products[0])
            np.multiply(step[0], step[1], out=products[1])
            np.multiply(step[1], step[1], out=products[2])
            scatter += products
            # an unused neighbour adds nothing: beyond the border (read at cell 0) or empty, its noise is NaN
            weight = noises.take(other)
            np.add(own_noise, weight, out=weight)
            np.copyto(weight, 0.0, where=unused)
            products *= weight
            spread += products
            moments += np.multiply(change[:, None], step[None], out=terms)
    determinant = scatter[0] * scatter[2] - scatter[1] * scatter[1]
    trace = scatter[0] + scatter[2]
    with np.errstate(invalid="ignore", divide="ignore"):  # cells without neighbours: no slope
        # the (pseudo-)inverse of the scatter: both axes, or along the one with neighbours (S / trace^2), or none
        both = determinant > _MIN_DETERMINANT * trace * trace
        along = np.where(~both & (trace > 0), 1.0 / (trace * trace), 0.0)
        inverse = np.where(both, 1.0 / determinant, 0.0)
        pseudo = (
            scatter[2] * inverse + scatter[0] * along,
            -scatter[1] * inverse + scatter[1] * along,
            scatter[0] * inverse + scatter[2] * along,
        )
    slopes[:, 0] = moments[:, 0] * pseudo[0] + moments[:, 1] * pseudo[1]
    slopes[:, 1] = moments[:, 0] * pseudo[1] + moments[:, 1] * pseudo[2]
    # the least-squares sandwich: pseudo-inverse x spread x pseudo-inverse
    pxx, pxy, pyy = pseudo
    sxx, sxy, syy = spread
    variance[0] = pxx * (pxx * sxx + pxy * sxy) + pxy * (pxx * sxy + pxy * syy)
    variance[1] = pxx * (pxy * sxx + pyy * sxy) + pxy * (pxy * sxy + pyy * syy)
    variance[2] = pxy * (pxy * sxx + pyy * sxy) + pyy * (pxy * sxy + pyy * syy)
    if cells.size == needed.size:
        return values, both
    model = np.zeros((14, needed.size))
    model[:, cells] = values
    known = np.zeros(needed.size, dtype=bool)
    known[cells] = both
    return model, known


def _carry(model: np.ndarray, rays: np.ndarray, out: np.ndarray) -> None:
    """Evaluate :func:`_normal_slopes`' models (14, n) of n pixels at their rays (2, n): unit normals, into ``out``.

    The correction ``c = J (r - m)``, with ``v = o^T V o`` its noise variance, is
    shrunk by ``max(0, 1 - s^2 v / |c|^2)`` (s = :data:`_SIGNIFICANCE`, a
    positive-part James-Stein factor): where the slopes are noise (a plane) it
    vanishes, and the plane's normal is kept as it is; where they are the
    surface's curvature it stays. ``out`` is (3, n); the temporaries are written with out=, in the formulas' order.
    """
    x, y = np.subtract(rays[0], model[3]), np.subtract(rays[1], model[4])
    variance = model[11:]
    correction = np.multiply(model[5:11:2], x, out=out)
    correction += model[6:11:2] * y
    noise = np.multiply(variance[0], x)
    noise *= x
    term = np.multiply(2.0, variance[1])
    term *= x
    term *= y
    noise += term
    np.multiply(variance[2], y, out=term)
    term *= y
    noise += term
    size = np.multiply(correction[0], correction[0], out=x)
    size += np.multiply(correction[1], correction[1], out=y)
    size += np.multiply(correction[2], correction[2], out=term)
    with np.errstate(invalid="ignore", divide="ignore"):
        shrink = np.multiply(_SIGNIFICANCE**2, noise, out=noise)
        shrink /= size
        np.clip(np.subtract(1.0, shrink, out=shrink), 0.0, 1.0, out=shrink)
    np.copyto(shrink, 0.0, where=~(size > 0.0))
    correction *= shrink
    correction += model[:3]
    _normalise(correction)


def _levels(window: int, max_window: int) -> int:
    """Levels of the window pyramid: windows of ``window * 2**k`` pixels, k < levels, up to ``max_window``."""
    levels = 1
    while window * 2**levels <= max_window:
        levels += 1
    return levels


def _points(xyz) -> tuple[np.ndarray, np.ndarray]:
    """Planar float64 copy (3, H, W) of one frame and its valid mask (finite, z > 0)."""
    xyz = np.asarray(xyz)
    if xyz.ndim != 3 or xyz.shape[-1] != 3:
        raise ValueError(f"xyz must have shape (H, W, 3), got {xyz.shape}")
    points = np.ascontiguousarray(np.moveaxis(xyz, -1, 0), dtype=np.float64)
    valid = np.isfinite(points).all(axis=0) & (points[2] > 0)
    return points, valid


def _window_planes(
    points: np.ndarray,
    valid: np.ndarray,
    window: int,
    jump: float,
    min_fraction: float,
    max_window: int,
    region: tuple[slice, slice] = (slice(None), slice(None)),
) -> np.ndarray:
    """Find the plane each pixel of one frame takes: its unit normal (3, h, w), unoriented, NaN where none.

    The base level gives each eligible pixel the plane of one of the 9 windows
    of ``window`` pixels that contain it; each further level doubles the window
    (2 x 2 pixel cells) and replaces the plane while the chosen window of that
    level is usable and its residual stays within :data:`_GROWTH` times the
    smallest residual of the base windows (module docstring). The planes are
    fitted over the whole frame; the normals are those of the pixels of
    ``region`` (row and column slices, of step 1), as the whole frame's.
    """
    window = _check_window(window)
    jump = _check_jump(jump)
    max_window = _check_max_window(max_window, window)
    if not 0.0 <= min_fraction <= 1.0:
        raise ValueError(f"min_fraction must be in [0, 1], got {min_fraction!r}")
    edges = _jump_edges(points, valid, jump)
    eligible = valid & ~edges
    moments, centre = _moments(points, valid)
    levels = _levels(window, max_window)
    # x', y' (2, h * w) of the region's pixels (meaningless where invalid)
    rays = (moments[1:3, region[0], region[1]] + centre[:2, None, None]).reshape(2, -1) if levels > 1 else None
    pooled = _pool(moments) if levels > 1 else None
    min_count = max(3, math.ceil(min_fraction * window * window - 1e-9))
    base, _, base_source, smallest, _, _ = _level_planes(moments, centre, edges, eligible, window, min_count, False)
    taken = base_source >= 0
    limit = _GROWTH * smallest
    edge_count, eligible_count = edges.astype(np.float32), eligible.astype(np.float32)
    last = np.zeros(valid.shape, dtype=np.int8)  # the level of the plane each taken pixel takes
    planes = []  # normal, centroid, noise, residual and source of the cells of each level from 1
    for level in range(1, levels):
        moments, edge_count, eligible_count = pooled, _pool(edge_count), _pool(eligible_count)
        pooled = _pool(moments) if level + 1 < levels else None
        min_count = max(3, math.ceil(min_fraction * (window * 2**level) ** 2 - 1e-9))
        normal, residual, source, _, centroid, noise = _level_planes(
            moments, centre, edge_count > 0, eligible_count > 0, window, min_count
        )
        chosen = np.where(source >= 0, source, 0)
        fit = np.where(source >= 0, residual.reshape(-1).take(chosen), np.inf)
        taken &= _upsample(fit, level, valid.shape) <= limit
        if not taken.any():
            break
        planes.append((normal, centroid, noise, residual, source))
        last += taken
    # the region's pixels from here on: each pixel's normal is its own
    last, base_source = last[region[0], region[1]], base_source[region[0], region[1]]
    if planes:
        # every pixel is carried, in contiguous blocks (its ray and normal are slices, not gathers and scatters):
        # from the model of its last level's cell, or, at the pixels of the base level, from the column of NaN
        # (their normal, where they have one, is set below)
        taking = np.full(valid.shape, -1, dtype=np.int8)  # the last level of the region's pixels, -1 elsewhere
        taking[region[0], region[1]] = last
        models, columns = _level_models(planes, taking, window // 2)
        index = np.full(last.shape, models.shape[1] - 1, dtype=np.int32)
        for level, column in enumerate(columns, start=1):
            np.copyto(index, _upsample(column, level, valid.shape)[region[0], region[1]], where=last == level)
        out = np.empty((3, *last.shape))
        flat, index = out.reshape(3, -1), index.reshape(-1)
        for block in range(0, index.size, _BLOCK):
            part = slice(block, block + _BLOCK)
            _carry(models.take(index[part], axis=1), rays[:, part], flat[:, part])
    else:
        out = np.full((3, *last.shape), np.nan)
        flat = out.reshape(3, -1)
    pixel = np.flatnonzero((last == 0) & (base_source >= 0))
    normal = base.reshape(3, -1).take(base_source.reshape(-1)[pixel], axis=1)
    _normalise(normal)
    flat[:, pixel] = normal
    return out


def _level_models(planes: list, last: np.ndarray, half: int) -> tuple[np.ndarray, list[np.ndarray]]:
    """Model the normal (:func:`_normal_slopes`) in the cells of each level from 1 that a pixel takes.

    A cell without slopes on both axes takes the mean of its 2 x 2 smaller cells' that had them; so, from the
    largest level down, a level's models are computed at the cells its pixels take (those holding a pixel whose
    last level, in ``last`` (H, W), is that level) and at the smaller cells of the cells above that lack slopes.

    Returns
    -------
    models : (14, m + 1) ndarray of float64
        The models of all levels, side by side, and a last column of NaN.
    columns : list of ndarray
        For each level from 1, the column (h, w) int32 of each cell's model (meaningless at the cells no pixel takes).
    """
    found = []  # per level from the largest: models, slopes known, cells, column of each cell's model, grid shape
    lacking = None  # the cells of the level above without slopes on both axes
    for level in range(len(planes), 0, -1):
        normal, centroid, noise, residual, source = planes[level - 1]
        taking = (last == level).astype(np.float32)
        for _ in range(level):
            taking = _pool(taking)
        needed = taking > 0
        if lacking is not None:
            needed |= lacking.repeat(2, axis=0).repeat(2, axis=1)[: source.shape[0], : source.shape[1]]
        needed = np.flatnonzero(needed)
        model, known = _normal_slopes(normal, centroid, noise, residual, source, half, needed)
        lacking = np.zeros(source.shape, dtype=bool)
        lacking.reshape(-1)[needed[~known]] = True
        column = np.full(source.size, -1, dtype=np.int32)  # -1: no model
        column[needed] = np.arange(needed.size)
        found.append((model, known, needed, column, source.shape))
    found.reverse()
    for level, smaller in zip(found[1:], found):
        _fill_slopes(level, smaller)
    columns, offset = [], 0
    for model, _, _, column, shape in found:
        columns.append((column + np.int32(offset)).reshape(shape))
        offset += model.shape[1]
    return np.concatenate([model for model, *_ in found] + [np.full((14, 1), np.nan)], axis=1), columns


def _fill_slopes(level: tuple, smaller: tuple) -> None:
    """Give a level's cells lacking slopes the mean of their 2 x 2 smaller cells' known slopes, in place.

    Parameters
    ----------
    level, smaller : tuple
        A level's and the level below's models (14, m), slopes known (m,) bool, cells (m,) (flat indices),
        column of each cell's model (h * w,) (-1: none) and grid shape (h, w), as :func:`_level_models` keeps
        them: every smaller cell of a cell lacking slopes has a model. Summed in :func:`_pool`'s order.
    """
    model, known, cells, _, shape = level
    slopes, sloped, _, columns, grid = smaller
    lacking = np.flatnonzero(~known)
    row, column = np.divmod(cells[lacking], shape[1])
    total = weight = None
    for dy, dx in ((0, 0), (0, 1), (1, 0), (1, 1)):
        inside = (2 * row + dy < grid[0]) & (2 * column + dx < grid[1])
        child = columns.take(np.where(inside, (2 * row + dy) * grid[1] + 2 * column + dx, 0))
        present = inside & sloped.take(child)
        term = slopes[5:].take(child, axis=1) * present
        if total is None:
            total, weight = term, present.astype(np.float64)
        else:
            total += term
            weight += present
    fill = weight > 0
    model[5:, lacking[fill]] = total[:, fill] / weight[fill]
    known[lacking[fill]] = True


def plane_normals(
    xyz,
    window: int,
    *,
    jump: float = DEFAULT_JUMP,
    min_fraction: float = _MIN_FRACTION,
    max_window: int | None = None,
) -> np.ndarray:
    """Compute the unit normals of the local least-squares planes of one organized frame.

    Parameters
    ----------
    xyz : (H, W, 3) array_like of float32 or float64, metres
        Camera-frame points; a pixel is valid when x, y, z are finite and z > 0.
    window : int
        Odd side (pixels, >= 3) of the base square neighbourhood of each pixel.
    jump : float, optional
        Relative depth step, beyond the steepest surface's, between neighbours that separates two surfaces.
    min_fraction : float, optional
        Fraction of a window's pixels that must be valid (at least 3 always).
    max_window : int, optional
        Largest window side tried, pixels (default ``window``: the base windows only).

    Returns
    -------
    (H, W, 3) ndarray of float64
        Unit normals oriented towards the camera (``n . P < 0``); NaN at invalid
        pixels, edge pixels and where no usable window exists or the points are
        (nearly) collinear.
    """
    points, valid = _points(xyz)
    normals = np.moveaxis(_window_planes(points, valid, window, jump, min_fraction, max_window or window), 0, -1)
    normals[np.sum(normals * np.moveaxis(points, 0, -1), axis=-1) > 0] *= -1.0
    return normals


def frame_angle_of_incidence(
    xyz,
    window: int,
    *,
    jump: float = DEFAULT_JUMP,
    min_fraction: float = _MIN_FRACTION,
    max_window: int | None = None,
    region: Roi | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Angle of incidence and distance of every pixel of one organized frame, or of a region of it.

    Parameters
    ----------
    xyz : (H, W, 3) array_like of float32 or float64, metres
        As in :func:`plane_normals`.
    window, jump, min_fraction, max_window
        As in :func:`plane_normals`.
    region : Roi, optional
        The pixels to return (inside the frame), at less cost: the planes are still fitted to the
        whole frame, so their values are the whole frame's, to the bit; default the whole frame.

    Returns
    -------
    aoi : (H, W) ndarray of float64, radians
        ``arccos(|v . n|)`` in [0, pi/2]; NaN where the normal is undefined. With a
        ``region``, of its shape.
    distance : (H, W) ndarray of float64, metres
        ``|P|``; NaN at invalid pixels only.
    """
    points, valid = _points(xyz)
    part = (slice(None), slice(None)) if region is None else region.slices
    normal = _window_planes(points, valid, window, jump, min_fraction, max_window or window, part)
    points, valid = points[:, part[0], part[1]], valid[part]
    aoi = np.empty(valid.shape)
    distance = np.empty(valid.shape)
    for rows in _row_blocks(*valid.shape):
        # written with out= into the results, in the formulas' order: |P| = sqrt(x x + y y + z z), cos = |n . P| / |P|
        (x, y, z), (nx, ny, nz) = points[:, rows], normal[:, rows]
        norm, cosine, term = distance[rows], aoi[rows], np.multiply(y, y)
        with np.errstate(invalid="ignore", divide="ignore"):  # invalid points: NaN below
            np.multiply(x, x, out=norm)
            norm += term
            norm += np.multiply(z, z, out=term)
            np.sqrt(norm, out=norm)
            np.multiply(nx, x, out=cosine)
            cosine += np.multiply(ny, y, out=term)
            cosine += np.multiply(nz, z, out=term)
            np.abs(cosine, out=cosine)
            cosine /= norm
        np.arccos(np.minimum(cosine, 1.0, out=cosine), out=cosine)
        np.copyto(norm, np.nan, where=~valid[rows])
    return aoi, distance


def _frames(xyz: np.ndarray, window: int, jump: float, max_window: int) -> np.ndarray:
    """AOI and distance (..., H, W, 2) float32 of a stack of frames (..., H, W, 3)."""
    out = np.empty((*xyz.shape[:-1], 2), dtype=np.float32)
    for index in np.ndindex(xyz.shape[:-3]):
        aoi, distance = frame_angle_of_incidence(xyz[index], window, jump=jump, max_window=max_window)
        out[index + (Ellipsis, 0)] = aoi
        out[index + (Ellipsis, 1)] = distance
    return out


def _overlapping(xyz, kernel, halo: int, cell: int, quantities: int, dtype, **kwargs):
    """Apply a kernel of frames (..., H, W, 3) -> (..., H, W, quantities) to a dask array, lazily.

    Chunks of y and x get a halo of ``halo`` pixels (the reach of a pixel's
    result) and chunk boundaries fall on multiples of ``cell`` pixels; the
    image border gets none (``boundary="none"``), so every chunk sees exactly
    what the whole frame would.
    """
    import dask.array as da

    # one frame per chunk along the looped dimensions (views): frames are independent, so threads share them
    chunks = {**dict.fromkeys(range(xyz.ndim - 3), 1), xyz.ndim - 1: -1}
    depth = dict.fromkeys(range(xyz.ndim), 0)
    for axis in (xyz.ndim - 3, xyz.ndim - 2):
        size = max(xyz.chunks[axis][0], halo)
        size += -size % cell
        if len(xyz.chunks[axis]) > 1 and xyz.shape[axis] > size:
            chunks[axis] = size
            depth[axis] = halo
        else:
            chunks[axis] = -1
    padded = da.overlap.overlap(xyz.rechunk(chunks), depth=depth, boundary="none")
    out = padded.map_blocks(
        kernel,
        **kwargs,
        chunks=(*padded.chunks[:-1], (quantities,)),
        dtype=dtype,
        meta=np.empty((0,) * xyz.ndim, dtype=dtype),
    )
    return da.overlap.trim_internal(out, depth, boundary="none")


def _frames_dask(xyz, window: int, jump: float, max_window: int):
    """:func:`_frames` on a dask array, lazily: chunks overlap by the reach of a pixel's windows.

    A pixel's result depends on the pixels within the reach of its largest
    windows (shifted by half a window, on cells of ``2**(levels - 1)`` pixels,
    and the edge test one pixel beyond them). Chunks of y and x get a halo that
    deep, and chunk boundaries and halos fall on multiples of the largest cell,
    so that every chunk pools the pixels into the same cells as the whole frame
    (:func:`_overlapping`), and the result equals :func:`_frames` on the
    computed array up to rounding.
    """
    cell = 2 ** (_levels(window, max_window) - 1)
    halo = cell * (2 * (window // 2) + 2) + 2
    halo += -halo % cell
    return _overlapping(xyz, _frames, halo, cell, 2, np.float32, window=window, jump=jump, max_window=max_window)


def _dispatch(xyz, window: int, jump: float, max_window: int):
    """:func:`_frames` or, on a dask array, :func:`_frames_dask`."""
    if isinstance(xyz, np.ndarray):
        return _frames(xyz, window, jump, max_window)
    return _frames_dask(xyz, window, jump, max_window)


def _mixed_frames(xyz: np.ndarray, jump: float) -> np.ndarray:
    """Mixed-pixel masks (..., H, W, 1) bool of a stack of frames (..., H, W, 3)."""
    out = np.empty((*xyz.shape[:-1], 1), dtype=bool)
    for index in np.ndindex(xyz.shape[:-3]):
        out[index + (Ellipsis, 0)] = _mixed(*_points(xyz[index]), jump)
    return out


def _mixed_dispatch(xyz, jump: float):
    """:func:`_mixed_frames`, on a dask array lazily: a pixel's test reads the pixels up to 2 away."""
    if isinstance(xyz, np.ndarray):
        return _mixed_frames(xyz, jump)
    return _overlapping(xyz, _mixed_frames, 2, 1, 1, bool, jump=jump)


def _cloud(xyz: xr.DataArray) -> xr.DataArray:
    """Check an organized cloud (view, y, x, axis) and order its axis x, y, z (:func:`angle_of_incidence`)."""
    if not isinstance(xyz, xr.DataArray):
        raise TypeError(f"xyz must be an xarray.DataArray (view, y, x, axis), got {type(xyz).__name__}")
    missing = [dim for dim in ("y", "x", "axis") if dim not in xyz.dims]
    if missing:
        raise ValueError(f"xyz must have dims (view, y, x, axis); missing {missing} in {xyz.dims}")
    if "axis" in xyz.coords:
        labels = [str(label) for label in xyz["axis"].values]
        if sorted(labels) != ["x", "y", "z"]:
            raise ValueError(f"xyz axis coordinate must hold 'x', 'y', 'z', got {labels}")
        return xyz.sel(axis=["x", "y", "z"])
    if xyz.sizes["axis"] != 3:
        raise ValueError(f"xyz axis dimension must have size 3 (x, y, z), got {xyz.sizes['axis']}")
    return xyz


def _per_frame(function, xyz: xr.DataArray, **kwargs) -> xr.DataArray:
    """Apply ``function`` (frames (..., H, W, 3) -> (..., H, W, quantity)) over the y, x, axis dimensions of ``xyz``."""
    return xr.apply_ufunc(
        function,
        xyz,
        input_core_dims=[["y", "x", "axis"]],
        output_core_dims=[["y", "x", "quantity"]],
        kwargs=kwargs,
        dask="allowed",
        keep_attrs=False,
    ).drop_vars("axis", errors="ignore")


def angle_of_incidence(
    xyz: xr.DataArray,
    *,
    window: int = DEFAULT_WINDOW,
    jump: float = DEFAULT_JUMP,
    max_window: int = DEFAULT_MAX_WINDOW,
) -> xr.Dataset:
    """Angle of incidence and distance of every pixel of organized point clouds.

    Parameters
    ----------
    xyz : (view, y, x, axis) DataArray, metres
        Camera-frame points of each view (numpy- or dask-backed, any float
        dtype); ``axis`` holds x, y, z (in the order of an ``axis`` coordinate
        ``["x", "y", "z"]`` when there is one). NaN marks an invalid pixel, as
        does z <= 0. Dimensions other than y, x, axis are looped over.
    window : int, optional
        Odd side, pixels (>= 3), of the smallest square neighbourhood of the
        plane fit, which every pixel near an edge or crease keeps. A surface
        narrower than the window gets no AOI.
    jump : float, optional
        Relative depth step between neighbouring pixels, beyond what an 80 deg
        slope gives, that separates two surfaces: a window never spans one
        (see the module docstring).
    max_window : int, optional
        Largest window side tried, pixels (>= window): windows of ``window * 2**k``
        pixels replace the smaller ones while the surface stays planar.

    Returns
    -------
    Dataset
        ``aoi`` (view, y, x) float32, radians, in [0, pi/2]: NaN at invalid
        pixels, at depth edges and where no window has enough valid points;
        ``distance`` (view, y, x) float32, metres, ``|P|``: NaN at invalid
        pixels. Attributes ``window``, ``jump`` and ``max_window`` record the parameters.
        Lazy when ``xyz`` is dask-backed.

    Raises
    ------
    TypeError
        If ``xyz`` is not a DataArray.
    ValueError
        If ``window`` is not an odd integer >= 3, ``max_window`` is smaller, ``jump`` is not positive, or
        ``xyz`` lacks a ``y``, ``x`` or ``axis`` (of size 3) dimension.
    """
    xyz = _cloud(xyz)
    window = _check_window(window)
    jump = _check_jump(jump)
    max_window = _check_max_window(max_window, window)
    params = {"window": window, "jump": jump, "max_window": max_window}
    out = _per_frame(_dispatch, xyz, **params)
    aoi = out.isel(quantity=0, drop=True)
    distance = out.isel(quantity=1, drop=True)
    aoi.attrs = {"units": "rad", "long_name": "angle of incidence", **params}
    distance.attrs = {"units": "m", "long_name": "distance from the camera centre"}
    return xr.Dataset({"aoi": aoi, "distance": distance}, attrs=params)


def mixed_pixels(xyz: xr.DataArray, *, jump: float = DEFAULT_JUMP) -> xr.DataArray:
    """Find the mixed ("flying") pixels of organized point clouds.

    A time-of-flight pixel whose footprint straddles a depth edge returns a
    depth between the two surfaces, on neither. Along a row, column or
    diagonal, a pixel is mixed when

    - its steps to both neighbours are depth jumps in the same sense (it lies
      between them): steeper than 80 deg (:data:`MAX_SLOPE_DEG`) beyond a
      relative depth step of ``jump / 2`` each, as the pixel splits one jump
      in two (the edge test of :func:`angle_of_incidence` with half the jump);
    - and each neighbour's next step, away from the pixel, is not steeper
      than 80 deg in that sense: the neighbours lie on surfaces of their own.

    It is the veil-point test of laser scanners (the line to a neighbour
    nearly along the ray) asked on both sides, and checked against each
    side's surface: a true edge pixel has a gentle step on its own side, a
    continuous surface seen at a grazing angle steep steps throughout, and
    neither is mixed. Steps are judged as angles and relative depths, so no
    focal length or distance enters. A split is found when its smaller part
    exceeds ``jump / 2`` plus the rise of an 80 deg slope over the ray spacing
    (~1.5 % of the depth at 565 px focal length: 7.5 mm at 0.5 m); an invalid
    neighbour leaves a direction undecided, and a band of two mixed pixels
    across an edge is not found.

    Parameters
    ----------
    xyz : (view, y, x, axis) DataArray, metres
        Organized clouds, as in :func:`angle_of_incidence`.
    jump : float, optional
        Relative depth step, beyond what an 80 deg slope gives, that separates
        two surfaces, as in :func:`angle_of_incidence`.

    Returns
    -------
    (view, y, x) DataArray of bool
        ``mixed``: True at mixed pixels (never at invalid ones); attr ``jump``.
        Lazy when ``xyz`` is dask-backed.

    Raises
    ------
    TypeError, ValueError
        As :func:`angle_of_incidence`, for ``xyz`` and ``jump``.
    """
    xyz = _cloud(xyz)
    jump = _check_jump(jump)
    out = _per_frame(_mixed_dispatch, xyz, jump=jump).isel(quantity=0, drop=True)
    out.name = "mixed"
    out.attrs = {"long_name": "mixed (flying) pixel", "jump": jump}
    return out
