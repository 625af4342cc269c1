"""Co-registration: every view of an item on the reference view's pixel grid (METHOD.md step 4).

:func:`registration_maps` finds, for every pixel of the reference grid (the item's cropped
sensor grid, or a window of it), the sub-pixel sensor position ``(map_x, map_y)`` in each view
where the same surface point is seen; :func:`warp` resamples any (view, y, x) image there
(NaN-aware bilinear), :func:`register` warps an item's reflectance and AOI, and
:func:`registration_error` scores maps against the synthetic camera's truth. The methods:

- ``"poses"``: the reference pixel's 3-D point (range averaged over its surface neighbours) goes
  through the two poses and the camera model (:class:`~surffin.method.camera_model.CameraModel`:
  the given intrinsics with their distortion, else fitted to the clouds) onto the view's sensor;
  a point behind something closer is occluded. Any surface shape. A robot's recorded poses are
  off by ~1-2 mm and 0.2-0.5 deg, so each view's pose is first refined against the reference view
  (:func:`_refine_pose`: point-to-plane ICP and direct alignment of the texture), bounded, and
  its correction reported.
- ``"homography"``: SIFT keypoints on contrast-normalised log intensity, Lowe's ratio test and a
  robust homography (USAC MAGSAC++): exact for one plane only, as in the paper; an ``roi`` picks
  the plane.
- ``"clouds"``: as ``"poses"``, each view's pose estimated from the clouds alone
  (:func:`_pose_estimator`): the dominant planes fix tilt and distance, the relief the turn and
  shift, the refinement the rest, the texture chooses among a symmetric relief's poses. Needs
  relief (a plane fixes only 3 of a pose's 6 directions).
- ``"auto"``: poses when every view has one, else ``"clouds"``, and where that fails the homography.
"""

from __future__ import annotations

from collections.abc import Mapping
from functools import cache, partial

import cv2
import numpy as np
import xarray as xr

from surffin.errors import RegistrationError
from surffin.grid import Roi
from surffin.method.camera_model import CameraModel, fit_camera_model, model_residual
from surffin.method.geometry import plane_normals

__all__ = [
    "METHODS",
    "DETECTORS",
    "HOMOGRAPHY_OPTIONS",
    "POSE_OPTIONS",
    "registration_maps",
    "warp",
    "register",
    "registration_error",
]

#: Methods of :func:`registration_maps`.
METHODS = ("auto", "poses", "clouds", "homography")

# OpenCV 5 moved AKAZE to opencv-contrib (cv2.xfeatures2d); use it where it is installed.
_AKAZE = next(
    (module.AKAZE_create for module in (cv2, getattr(cv2, "xfeatures2d", None)) if hasattr(module, "AKAZE_create")),
    None,
)

#: Keypoint detectors of the homography method: factory and descriptor norm. SIFT is the
#: default, chosen by measurement (benchmarks/bench_registration.py: most inliers per match,
#: lowest error); ORB keeps up to 5000 keypoints; "akaze" is listed only when the installed
#: OpenCV has it.
DETECTORS = {
    "sift": (cv2.SIFT_create, cv2.NORM_L2),
    "orb": (lambda: cv2.ORB_create(nfeatures=5000), cv2.NORM_HAMMING),
} | ({"akaze": (_AKAZE, cv2.NORM_HAMMING)} if _AKAZE else {})

#: Options of the ``"homography"`` method and their defaults.
HOMOGRAPHY_OPTIONS = {
    "detector": "sift",  # a key of DETECTORS
    "ratio": 0.75,  # Lowe's ratio test: best / second-best descriptor distance
    "threshold": 1.5,  # MAGSAC++ inlier threshold, pixels
    "min_matches": 20,  # fewer matches after the ratio test: RegistrationError
    "min_inliers": 12,  # fewer homography inliers: RegistrationError
    "contrast_sigma": 12.0,  # pixels: window of the local contrast normalisation of log intensity
    "roi": None,  # {"y": [y0, y1], "x": [x0, x1]}: reference keypoints only there (sensor, half-open)
}

#: Options of the ``"poses"`` method and their defaults.
POSE_OPTIONS = {
    "tolerance": 0.005,  # metres: ranges closer than max(tolerance, relative * range) are one surface
    "relative": 0.01,
    "smooth": 9,  # odd window (pixels) averaging the reference range over one surface; 1 = off
    "refine": True,  # refine each view's pose against the reference view's before mapping
    "max_translation": 0.01,  # metres: a larger correction of a pose is refused
    "max_rotation": 2.0,  # degrees: a larger correction of a pose is refused
}

# Pose refinement (POSE_OPTIONS["refine"]), chosen on benchmarks/bench_registration.py.
_REFINE_SAMPLES = 20000  # about this many pixels (a regular subsample) of each grid give residuals
_REFINE_WINDOW = 15  # pixels: plane-fit window of the reference normals
_REFINE_CONTRAST = 4.0  # pixels: local normalisation of the texture (wider windows reach across edges: biased)
_REFINE_LEVELS = (2.0, 1.0)  # pixels: Gaussian blur of the texture, coarse to fine
_REFINE_ITERATIONS = 10  # Gauss-Newton iterations per level at most
_ESTIMATE_ITERATIONS = 30  # the same for coarse estimates (method "clouds") none of which converged in fewer
_REFINE_STEP = 0.01  # pixels: converged when a step of the last level moves the surface by less in the view
_COARSE = 10.0  # coarser levels stop at this many times the step
_OBSERVABLE = 3e-3  # point-to-plane information below this share of the largest is dropped (unobservable)
_CONSTRAINED = 10.0  # directions with less information than this times the prior's are not updated
_PRIOR = (0.4, 0.002)  # standard deviation of a recorded pose (robot and hand-eye): degrees, metres
_COARSE_PRIOR = (5.0, 0.01)  # standard deviation of a coarse pose estimate (method "clouds"): degrees, metres
_MODEL_RESIDUAL = 0.5  # pixels: an estimated camera model fitting the clouds worse is refused
_PLANE_SAMPLES = 5000  # points (a random subsample) a view's dominant plane is searched on
_PLANE_TRIALS = 300  # RANSAC trials of the dominant plane
_PLANE_TOLERANCE = 0.002  # metres: points this close to a plane are on it (range noise ~1-3 mm; relief >= 10 mm)
_PLANE_FITS = 5  # least-squares fits of the dominant plane to its points at most
_HEIGHT_CELLS = 256  # side of the height maps (cells) correlated for the coarse pose
_HEIGHT_SPAN = 0.05  # metres: heights off the plane are clipped to +- this
_MIN_RELIEF = 0.02  # share of a view's points off its dominant plane (by the tolerance) that method "clouds" needs
_CELL_SPACING = 2.0  # height map cells span at least this many times the median spacing of neighbouring points
_EXTENSION = 8.0  # cells: Gaussian scale of the smooth extension of a height map over its empty cells
_TURN_STEP = 3.0  # degrees: turns about the plane's normal tried, over the whole circle, then refined
_CANDIDATES = 6  # coarse poses refined at most (the highest peaks of the correlation over the turn)
_CANDIDATE_SHARE = 0.3  # a peak lower than this share of the highest is no candidate
_MIN_PAIRS = 50  # fewer point-to-plane pairs: the view is refused
_MIN_TEXTURE = 300  # fewer texture pairs: that term is left out
# A view whose estimated pose leaves a texture deviation above this many times the median of the
# item's other views' is searched again from every other view (a symmetric layout can make the
# chain of views land on a wrong candidate whose geometry agrees: val-bare-raw seed 0, scene view
# v02, 28 px off with 2x the others' deviation).
_TEXTURE_OUTLIER = 1.5
_HUBER = 1.345  # Huber threshold, robust standard deviations
_MAD_SCALE = 1.4826  # median absolute deviation to standard deviation (normal distribution)
_REMAP_ROW = 1024  # positions per row of the maps given to cv2.remap
_SMOOTH_ROWS = 64  # rows per band of the range smoothing
_BAND = 16384  # pixels per band of the full-frame kernels (bilinear, maps): their buffers stay in the cache
_FEATURE_MARGIN = 4  # pixels: no keypoint this close to an invalid pixel or the border
_CLIP = 3.0  # local standard deviations mapped to the ends of the 8-bit range
_RIGID_TOLERANCE = 1e-4  # |R^T R - I| of a pose (poses written with ~5 digits pass; 1e-4 rad ~ 0.05 mm at 0.5 m)
_MAGSAC_ITERATIONS = 10000
_MAGSAC_CONFIDENCE = 0.9999
_MAP_ATTRS = {
    "map_x": {"units": "pixel", "long_name": "sensor column of the reference pixel's surface point in each view"},
    "map_y": {"units": "pixel", "long_name": "sensor row of the reference pixel's surface point in each view"},
}


# ---------------------------------------------------------------------------------------------
# numpy kernels


def _bilinear(image: np.ndarray, col: np.ndarray, row: np.ndarray) -> np.ndarray:
    """NaN-aware bilinear samples of multi-channel images at sub-pixel array positions.

    Parameters
    ----------
    image : (..., C, H, W) ndarray
        C channels sampled at the same positions (one set of indices and weights
        for all); NaN marks a missing value; H, W >= 2.
    col, row : (..., h, w) ndarray
        Array positions (0 = first column / row), leading dims broadcasting
        against ``image``'s; NaN = no sample.

    Returns
    -------
    (..., C, h, w) ndarray of float64
        NaN where the position is NaN or outside ``[0, W - 1] x [0, H - 1]``, or
        where a neighbour with a non-zero weight is NaN (a missing pixel never
        bleeds into its neighbours, and nothing is extrapolated).
    """
    lead = np.broadcast_shapes(image.shape[:-3], col.shape[:-2], row.shape[:-2])
    image = np.broadcast_to(image, (*lead, *image.shape[-3:]))
    col, row = (np.broadcast_to(value, (*lead, *value.shape[-2:])) for value in (col, row))
    total = np.empty((*lead, image.shape[-3], *col.shape[-2:]))
    # in bands of rows of one image at a time, whose buffers stay in the cache
    rows = max(1, _BAND // col.shape[-1])
    for index in np.ndindex(lead):
        flat = np.ascontiguousarray(image[index]).reshape(image.shape[-3], -1)
        for top in range(0, col.shape[-2], rows):
            band = slice(top, top + rows)
            total[(*index, slice(None), band)] = _bilinear_band(
                flat, image.shape[-2:], col[index][band], row[index][band]
            )
    return total


def _bilinear_band(flat: np.ndarray, size: tuple[int, int], col: np.ndarray, row: np.ndarray) -> np.ndarray:
    """:func:`_bilinear` of one image ``flat`` (C, H * W) of ``size`` (H, W) at positions (h, w); (C, h, w)."""
    height, width = size
    with np.errstate(invalid="ignore"):
        inside = (col >= 0) & (col <= width - 1) & (row >= 0) & (row <= height - 1)
    # in float64 whatever the positions' type: the weights are products of the fractions
    fc, fr = (np.where(inside, value, 0.0).astype(np.float64, copy=False) for value in (col, row))
    # c0, r0: the top left neighbour, as floats (exact integers)
    c0, r0 = np.floor(fc), np.floor(fr)
    total = np.empty((len(flat), *col.shape))
    if np.array_equal(c0, fc) and np.array_equal(r0, fr):
        # whole pixels (the reference view's own map): a weight of 1 on one neighbour and 0 on the others gives its
        # value + 0.0 (an unweighted missing neighbour is left out, and the sum starts from +0.0)
        at = (r0 * width + c0).astype(np.intp)
        for channel, values in enumerate(flat):
            np.add(np.take(values, at), 0.0, out=total[channel])
        np.copyto(total, np.nan, where=~inside)
        return total
    np.minimum(c0, width - 2, out=c0)
    np.minimum(r0, height - 2, out=r0)
    base = (r0 * width + c0).astype(np.intp)
    fc -= c0
    fr -= r0
    gc, gr = 1.0 - fc, 1.0 - fr
    terms = [(0, gr * gc), (1, gr * fc), (width, fr * gc), (width + 1, fr * fc)]
    total[...], values = 0.0, np.empty(col.shape)
    for channel in range(len(flat)):
        for offset, weight in terms:
            # the indices are in range; mode="raise" would buffer the output (~3x slower)
            np.take(flat[channel, offset:], base, out=values, mode="clip")
            total[channel] += np.multiply(values, weight, out=values)
    # a NaN neighbour made its sample NaN even with a zero weight: sum those again without it
    with np.errstate(invalid="ignore"):
        again = np.flatnonzero(np.isnan(total) & inside)
    channel, pixel = np.divmod(again, inside.size)
    at = base.ravel()[pixel] + channel * flat.shape[1]
    redone = np.zeros(again.size)
    for offset, weight in terms:
        weight = weight.ravel()[pixel]
        redone += np.where(weight > 0, flat.ravel()[at + offset] * weight, 0.0)
    total.ravel()[again] = redone
    np.copyto(total, np.nan, where=~inside)
    return total


def _warp_kernel(*arrays: np.ndarray, origin: tuple[int, int], count: int) -> np.ndarray:
    """:func:`_bilinear` of several images at once (their weights computed once) at sensor positions.

    ``arrays``: ``count`` images (..., H, W) whose first pixel is sensor ``origin``
    (row, col), the maps' columns and rows (..., h, w), and optionally a valid
    mask (..., H, W) of the images. Returns (..., count, h, w) of float64.
    """
    shape = np.broadcast_shapes(*(np.shape(image) for image in arrays[:count]))
    map_x, map_y, *valid = arrays[count:]
    # Only the span of rows and columns the positions read is stacked in float64 (a roi's maps read a
    # part of the item's grid). The positions on it are the same numbers: subtracting a whole number
    # of pixels from a position to its right is exact, and those to its left are outside either way.
    (top, bottom), (left, right) = (
        _read_span(positions - first, size) for positions, first, size in zip((map_y, map_x), origin, shape[-2:])
    )
    part = (..., slice(top, bottom), slice(left, right))
    images = np.empty((*shape[:-2], count, bottom - top, right - left))
    for layer, image in enumerate(arrays[:count]):
        images[..., layer, :, :] = np.asarray(image)[part]
    if valid:
        np.copyto(images, np.nan, where=~np.asarray(valid[0], dtype=bool)[part][..., None, :, :])
    return _bilinear(images, map_x - (origin[1] + left), map_y - (origin[0] + top))


def _read_span(positions: np.ndarray, size: int) -> tuple[int, int]:
    """Return the first and the end (>= first + 2) of the pixels of an axis that bilinear samples read.

    ``positions``: array positions on an axis of ``size`` pixels. From the floor of the smallest
    finite position to the floor of the largest plus two, within the axis; all of it when no
    position is finite.
    """
    finite = positions[np.isfinite(positions)]
    if not finite.size:
        return 0, size
    first = int(np.clip(np.floor(finite.min()), 0, size - 2))
    return first, int(np.clip(np.floor(finite.max()) + 2, first + 2, size))


def _outside_to_nan(col: np.ndarray, row: np.ndarray, columns: np.ndarray, rows: np.ndarray) -> None:
    """Set positions outside the sensor span ``[first, last]`` of ``columns`` / ``rows`` to NaN, in place."""
    with np.errstate(invalid="ignore"):
        outside = (col < columns[0]) | (col > columns[-1]) | (row < rows[0]) | (row > rows[-1])
    col[outside] = np.nan
    row[outside] = np.nan


def _smooth_range(points: np.ndarray, window: int, tolerance: float, relative: float) -> np.ndarray:
    """Average each point's range over the neighbours of its window on the same surface.

    Parameters
    ----------
    points : (H, W, 3) ndarray of float64, metres
        Camera frame; NaN = invalid.
    window : int
        Odd side of the square neighbourhood; 1 returns ``points``.
    tolerance, relative : float
        A neighbour counts when its range is within ``max(tolerance, relative * r)``
        of the centre's range ``r``.

    Returns
    -------
    (H, W, 3) ndarray of float64
        The points moved along their rays to the mean range (noise along the ray
        shrinks by up to ``window``).
    """
    if window == 1:
        return points
    height, width = points.shape[:2]
    half = window // 2
    distance = _norm(points)
    padded = np.pad(distance, half, constant_values=np.nan)
    gap = np.maximum(tolerance, relative * distance)
    # Most pixels have every valid neighbour on their surface (the extremes of the window's valid ranges within the
    # gap: |n - r| rounds monotonically in n, so they decide it exactly). Their sum adds every neighbour, an invalid
    # one as 0.0 (which leaves a sum of ranges as it is): plain sums over the frame, in the same order as the
    # masked sums of the other pixels, which run on those pixels only.
    kernel = np.ones((window, window), np.uint8)
    centre = (slice(half, half + height), slice(half, half + width))
    known = np.isfinite(padded)
    with np.errstate(invalid="ignore"):
        whole = cv2.dilate(np.where(known, padded, -np.inf), kernel)[centre] - distance <= gap
        whole &= distance - cv2.erode(np.where(known, padded, np.inf), kernel)[centre] <= gap
    ranges = np.where(known, padded, 0.0)
    count = cv2.boxFilter(known.view(np.uint8), cv2.CV_32S, (window, window), normalize=False)[centre]
    count = count.astype(np.min_scalar_type(window * window))
    total = np.zeros_like(distance)
    # in bands of rows whose buffers stay in the cache across the window's offsets
    for top in range(0, height, _SMOOTH_ROWS):
        rows = slice(top, min(top + _SMOOTH_ROWS, height))
        for dy in range(window):
            for dx in range(window):
                total[rows] += ranges[rows.start + dy : rows.stop + dy, dx : dx + width]
    some = np.flatnonzero(~whole)
    corner = some // width * padded.shape[1] + some % width  # the window's first pixel in the padded frame
    centred, within = distance.ravel()[some], gap.ravel()[some]
    partial, counted = np.zeros(some.size), np.zeros(some.size, count.dtype)
    neighbour, apart, near = np.empty(some.size), np.empty(some.size), np.empty(some.size, bool)
    with np.errstate(invalid="ignore"):
        for dy in range(window):
            for dx in range(window):
                # the indices are in range; mode="raise" is ~3x slower
                np.take(padded.ravel(), corner + (dy * padded.shape[1] + dx), out=neighbour, mode="clip")
                np.abs(np.subtract(neighbour, centred, out=apart), out=apart)
                near = np.less_equal(apart, within, out=near)
                # + 0.0 leaves the sum as it is (it is never -0.0); a masked add is ~2x slower
                partial += np.where(near, neighbour, 0.0)
                counted += near
    total.ravel()[some] = partial
    count.ravel()[some] = counted
    with np.errstate(invalid="ignore", divide="ignore"):
        return points * (total / count / distance)[..., None]


def _norm(vectors: np.ndarray) -> np.ndarray:
    """Return the length of vectors (..., 3), as ``np.linalg.norm(vectors, axis=-1)`` does it, ~4x faster."""
    x, y, z = (vectors[..., axis] for axis in range(3))
    return np.sqrt(x * x + y * y + z * z)


def _project(points: np.ndarray, transform: np.ndarray, camera: CameraModel):
    """Sensor positions and ranges of points in another camera.

    Parameters
    ----------
    points : (H, W, 3) ndarray, metres
        Camera frame of camera A.
    transform : (4, 4) ndarray
        From camera A's frame to camera B's.
    camera : CameraModel
        Camera B's.

    Returns
    -------
    col, row : (H, W) ndarray of float64
        Sensor column and row in camera B; NaN behind it or for NaN points.
    distance : (H, W) ndarray of float64, metres
        Range of each point from camera B's centre.
    """
    local = points @ transform[:3, :3].T + transform[:3, 3]
    return *camera.project(local), _norm(local)


def _nearest(image: np.ndarray, col: np.ndarray, row: np.ndarray) -> np.ndarray:
    """Nearest-pixel samples of ``image`` (H, W) at array positions inside it; NaN where a position is NaN."""
    known = np.isfinite(col) & np.isfinite(row)
    c = np.rint(np.where(known, col, 0.0)).astype(np.intp)
    r = np.rint(np.where(known, row, 0.0)).astype(np.intp)
    r *= image.shape[1]
    r += c
    return np.where(known, np.take(image, r), np.nan)


def _pose_map(points, transform, camera, view_distance, columns, rows, tolerance, relative):
    """Map of one view by the poses, with the occlusion test.

    Parameters
    ----------
    points : (h, w, 3) ndarray, metres
        Reference pixels' points, reference camera frame (NaN = invalid).
    transform : (4, 4) ndarray
        Reference camera frame to the view's camera frame.
    camera : CameraModel
    view_distance : (h, w) ndarray, metres
        The ranges of the view's own measured points on its cropped grid.
    columns, rows : (w,), (h,) ndarray of int
        Sensor indices of the cropped grid.
    tolerance, relative : float
        The view measures something closer than the projected point by more
        than ``max(tolerance, relative * range)``: the point is occluded.

    Returns
    -------
    col, row : (h, w) ndarray of float64
        Sensor positions in the view; NaN where not seen.
    diagnostics : dict
        ``mapped`` and ``occluded`` (fractions of the reference pixels) and
        ``range_rms`` (metres): rms of measured minus projected range over the
        mapped pixels with a measurement, a check of the poses.
    """
    col, row, residual = (np.empty(points.shape[:2]) for _ in range(3))
    hidden = np.empty(points.shape[:2], bool)
    # in bands of rows whose buffers stay in the cache
    step = max(1, _BAND // points.shape[1])
    for top in range(0, points.shape[0], step):
        band = slice(top, top + step)
        col[band], row[band], expected = _project(points[band], transform, camera)
        _outside_to_nan(col[band], row[band], columns, rows)
        np.subtract(_nearest(view_distance, col[band] - columns[0], row[band] - rows[0]), expected, out=residual[band])
        with np.errstate(invalid="ignore"):
            np.less(residual[band], -np.maximum(tolerance, relative * expected), out=hidden[band])
    col[hidden] = np.nan
    row[hidden] = np.nan
    seen = np.isfinite(col) & np.isfinite(residual)
    diagnostics = {
        "mapped": float(np.isfinite(col).mean()),
        "occluded": float(hidden.mean()),
        "range_rms": float(np.sqrt(np.mean(residual[seen] ** 2))) if seen.any() else float("nan"),
    }
    return col, row, diagnostics


def _rigid(twist: np.ndarray) -> np.ndarray:
    """Return the rigid transform (4, 4) of a twist (6,): rotation vector (radians), then translation."""
    out = np.eye(4)
    out[:3, :3] = cv2.Rodrigues(np.asarray(twist[:3], dtype=np.float64))[0]
    out[:3, 3] = twist[3:]
    return out


def _twist(transform: np.ndarray) -> np.ndarray:
    """Return the twist (6,) of a rigid transform (4, 4): inverse of :func:`_rigid`."""
    return np.concatenate([cv2.Rodrigues(transform[:3, :3])[0].ravel(), transform[:3, 3]])


def _point_to_plane(transform, source, target, normals, camera, grid, tolerance, relative):
    """Point-to-plane residuals and Jacobian of a view's points against the reference surface.

    Projective data association: each source point, moved into the reference
    camera's frame, is paired with the reference pixel it projects to (nearest).

    Parameters
    ----------
    transform : (4, 4) ndarray
        The view's camera frame to the reference camera's (current estimate).
    source : (N, 3) ndarray, metres
        The view's points, its camera frame.
    target, normals : (h, w, 3) ndarray
        Reference points (metres) and unit normals on the reference grid; NaN
        where undefined (invalid, depth edges).
    camera : CameraModel
    grid : (columns, rows)
        Sensor indices of the reference grid.
    tolerance, relative : float
        Pairs farther apart along the normal than ``max(tolerance, relative *
        range)`` are rejected (different surfaces, e.g. across a depth step).

    Returns
    -------
    jacobian : (M, 6) ndarray
        Of the residuals with respect to a twist applied to the view's points in
        its own frame (rotation vector, translation).
    residual : (M,) ndarray, metres
        Signed distance of each kept pair along the reference normal.
    """
    # np.dot and np.take: ~10x faster than matmul and fancy indexing on (N, 3) arrays
    moved = np.dot(source, transform[:3, :3].T) + transform[:3, 3]
    col, row = (np.rint(value, out=value) for value in camera.project(moved, (grid[1][0], grid[0][0])))
    height, width = target.shape[:2]
    with np.errstate(invalid="ignore"):
        found = np.flatnonzero((col >= 0) & (col < width) & (row >= 0) & (row < height))
    at = row[found].astype(np.intp) * width + col[found].astype(np.intp)
    moved = np.take(moved, found, axis=0)
    normal = np.take(normals.reshape(-1, 3), at, axis=0)
    residual = np.einsum("ij,ij->i", normal, moved - np.take(target.reshape(-1, 3), at, axis=0))
    distance = np.sqrt(np.einsum("ij,ij->i", moved, moved))
    with np.errstate(invalid="ignore"):
        keep = np.abs(residual) <= np.maximum(tolerance, relative * distance)
    kept = np.flatnonzero(keep)
    local_normal = np.dot(np.take(normal, kept, axis=0), transform[:3, :3])
    return _twist_jacobian(np.take(source, found[kept], axis=0), local_normal, local_normal), residual[kept]


def _twist_jacobian(first: np.ndarray, second: np.ndarray, last: np.ndarray) -> np.ndarray:
    """Return ``np.hstack([np.cross(first, second), last])`` (M, 6) of (M, 3) arrays: the same values, fewer copies."""
    out = np.empty((len(first), 6))
    # np.cross's own products and differences, in its order
    for axis, (one, two) in enumerate(((1, 2), (2, 0), (0, 1))):
        np.multiply(first[:, one], second[:, two], out=out[:, axis])
        out[:, axis] -= first[:, two] * second[:, one]
    out[:, 3:] = last
    return out


def _remap(image: np.ndarray, col: np.ndarray, row: np.ndarray) -> np.ndarray:
    """Bilinear samples (N, C) of a float32 image (H, W, C <= 4) at array positions (N,) by OpenCV; NaN outside."""
    # cv2.remap takes maps of fewer than 2**15 rows and columns: lay the positions out in rows
    count = col.size
    if not count:  # no position (a level without textured samples): cv2.remap refuses empty maps
        return np.empty((0, image.shape[-1]), image.dtype)
    padded = -(-count // _REMAP_ROW) * _REMAP_ROW
    maps = []
    for value in (col, row):
        laid = np.full(padded, -1.0, np.float32)
        laid[:count] = value
        maps.append(laid.reshape(-1, _REMAP_ROW))
    nan = (np.nan,) * image.shape[-1]
    out = cv2.remap(image, *maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=nan)
    return out.reshape(padded, -1)[:count]


def _texture_residuals(transform, points, texture, sampled, camera, origin, tolerance, relative):
    """Texture residuals and Jacobian of reference pixels against a view (direct image alignment).

    Parameters
    ----------
    transform : (4, 4) ndarray
        The reference camera frame to the view's (current estimate).
    points : (N, 3) ndarray, metres
        Reference points, reference camera frame.
    texture : (N,) ndarray
        The reference texture at those pixels (finite: pixels without one give no residual).
    sampled : (H, W, 4) ndarray of float32
        The view's texture, its column and row derivatives and its measured
        range (metres), on its own grid (:func:`_sampled`); NaN = missing.
    camera : CameraModel
        The view's.
    origin : (row, col)
        Sensor position of the view grid's first pixel.
    tolerance, relative : float
        The view must measure the point's range within ``max(tolerance,
        relative * range)`` (else it is occluded or off the surface).

    Returns
    -------
    jacobian : (M, 6) ndarray
        Of the residuals with respect to a twist applied to the view's points in
        its own frame (as in :func:`_point_to_plane`).
    residual : (M,) ndarray
        The view's texture at the projected point minus the reference's.
    """
    local = np.dot(points, transform[:3, :3].T) + transform[:3, 3]
    col, row = (np.nan_to_num(value, copy=False, nan=-1.0) for value in camera.project(local, origin))
    value, d_col, d_row, measured = _remap(sampled, col, row).T
    distance = np.sqrt(np.einsum("ij,ij->i", local, local))
    with np.errstate(invalid="ignore"):
        keep = np.abs(measured - distance) <= np.maximum(tolerance, relative * distance)
    keep &= np.isfinite(value) & np.isfinite(d_col) & np.isfinite(d_row)
    kept = np.flatnonzero(keep)
    local = np.take(local, kept, axis=0)
    # derivative of the texture at the projection with respect to the point (view frame)
    gradient = camera.gradient(local, d_col[kept], d_row[kept])
    return _twist_jacobian(gradient, local, -gradient), value[kept] - texture[kept]


def _interior(distance: np.ndarray, tolerance: float, relative: float) -> np.ndarray:
    """Distance (pixels, float32) of each pixel from the nearest invalid pixel or range jump.

    A jump: two neighbours (along a row or column) whose ranges differ by more
    than ``max(tolerance, relative * range)``; both count as edge pixels.
    """
    smooth = np.isfinite(distance)
    with np.errstate(invalid="ignore"):
        # NaN where the range is: its differences are NaN too, and mark no jump
        gap = np.maximum(relative * distance, tolerance)
        for axis in (0, 1):
            ahead, behind = (slice(None),) * axis + (slice(1, None),), (slice(None),) * axis + (slice(None, -1),)
            difference = np.subtract(distance[ahead], distance[behind])
            jump = np.greater(np.abs(difference, out=difference), np.minimum(gap[ahead], gap[behind]))
            no_jump = np.logical_not(jump, out=jump)
            smooth[ahead] &= no_jump
            smooth[behind] &= no_jump
    return cv2.distanceTransform(smooth.view(np.uint8), cv2.DIST_L2, 5)


def _correlated(sigma: float, stride: int) -> float:
    """Count the samples per independent one of white noise blurred by ``sigma``, sampled every ``stride`` pixels.

    The blurred noise is correlated as ``exp(-d^2 / (4 sigma^2))`` at a distance
    of ``d`` pixels: the count is its sum over the sample lattice.
    """
    reach = int(np.ceil(8.0 * sigma / stride))
    offsets = stride * np.arange(-reach, reach + 1)
    return float(np.sum(np.exp(-(offsets**2) / (4.0 * sigma**2))) ** 2)


def _blurred(image: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur (in the image's dtype) over the finite pixels; NaN where less than half the weight is finite."""
    known = np.isfinite(image)
    weight = cv2.GaussianBlur(known.astype(image.dtype), (0, 0), sigma)
    total = cv2.GaussianBlur(np.where(known, image, 0.0), (0, 0), sigma)
    with np.errstate(divide="ignore", invalid="ignore"):
        np.divide(total, weight, out=total)
    np.copyto(total, np.nan, where=weight < 0.5)  # the weights are finite
    return total


def _sampled(texture: np.ndarray, distance: np.ndarray, sigma: float) -> np.ndarray:
    """Stack what :func:`_texture_residuals` samples: texture blurred by ``sigma``, its derivatives, range (float32)."""
    blurred = _blurred(texture, sigma)
    by_row, by_col = np.empty_like(blurred), np.empty_like(blurred)
    # np.gradient's differences (central, one-sided at the edges), in place
    for target, axis in ((by_row, 0), (by_col, 1)):
        values, derivative = np.moveaxis(blurred, axis, 0), np.moveaxis(target, axis, 0)
        np.subtract(values[2:], values[:-2], out=derivative[1:-1])
        derivative[1:-1] /= 2.0
        np.subtract(values[1], values[0], out=derivative[0])
        np.subtract(values[-1], values[-2], out=derivative[-1])
    # one interleaving pass (assigning the channels of an (H, W, 4) array one by one is ~3x slower)
    return cv2.merge([np.asarray(channel, dtype=np.float32) for channel in (blurred, by_col, by_row, distance)])


def _median(values: np.ndarray) -> np.floating:
    """Return ``np.median`` of values (M,) >= 1 without NaN, bit for bit, in their dtype (~6x faster).

    One partition at the middle (np.median partitions at three places, one to find NaNs);
    the mean of the middle values as ``np.mean`` sums them, from +0.0.
    """
    middle = values.size // 2
    part = np.partition(values, middle)
    if values.size % 2:
        return part[middle] + 0.0
    return (part[:middle].max() + part[middle] + 0.0) / 2


def _robust_deviation(residual: np.ndarray) -> float:
    """Return the standard deviation of residuals (M,) from their median absolute deviation; NaN when none."""
    return _MAD_SCALE * float(_median(np.abs(residual - _median(residual)))) if residual.size else float("nan")


def _robust_normal_equations(
    jacobian: np.ndarray, residual: np.ndarray, deviation: float
) -> tuple[np.ndarray, np.ndarray]:
    """Huber-weighted normal matrix (6, 6) and gradient (6,), residuals scaled by their robust ``deviation``.

    ``deviation`` is :func:`_robust_deviation` of ``residual`` (the caller has it already).
    """
    scale = max(deviation, np.finfo(np.float32).eps)
    size = np.abs(residual) / scale
    weight = np.where(size <= _HUBER, 1.0, _HUBER / np.maximum(size, _HUBER)) / scale**2
    weighted = jacobian * weight[:, None]
    return weighted.T @ jacobian, weighted.T @ residual


def _observable(matrix: np.ndarray, gradient: np.ndarray, units: np.ndarray):
    """Restrict normal equations to the directions they constrain well.

    In units where every twist component moves the surface alike (``units``:
    metres per unit of each component), the eigenvectors of the normal matrix
    whose eigenvalue is below :data:`_OBSERVABLE` times the largest are dropped
    with their information and their part of the gradient.

    Returns
    -------
    matrix : (6, 6) ndarray
    gradient : (6,) ndarray
    """
    scaled = matrix / np.outer(units, units)
    values, vectors = np.linalg.eigh(scaled)
    kept = vectors[:, values >= _OBSERVABLE * values[-1]]
    projector = kept @ kept.T
    return projector @ scaled @ projector * np.outer(units, units), units * (projector @ (gradient / units))


def _regularised_step(matrix, gradient, prior, correction):
    """Gauss-Newton step with a Gaussian prior on the correction, in the directions the data constrain.

    In units of the prior's standard deviations, the directions (eigenvectors
    of the data's normal matrix) with less than :data:`_CONSTRAINED` times the
    prior's information are left as they are.

    Parameters
    ----------
    matrix, gradient : (6, 6), (6,) ndarray
        The data's normal equations.
    prior : (6,) ndarray
        Inverse variances of the correction.
    correction : (6,) ndarray
        The correction so far (twist).

    Returns
    -------
    step : (6,) ndarray
    count : int
        Directions updated.
    """
    spread = 1.0 / np.sqrt(prior)
    values, vectors = np.linalg.eigh(matrix * np.outer(spread, spread))
    kept = values >= _CONSTRAINED
    whitened = vectors[:, kept].T @ (spread * (gradient + prior * correction))
    return -spread * (vectors[:, kept] @ (whitened / (values[kept] + 1.0))), int(kept.sum())


def _refine_pose(start, geometric, textured, correlation, prior, units, tolerance, iterations):
    """Refine a view's pose against the reference view's: Gauss-Newton, regularised toward the recorded pose.

    The unknown is a correction of the view's pose: a twist (rotation vector,
    translation) applied to its points in its own frame (the refined pose is
    the recorded one times it). Each iteration sums the normal equations of

    - point-to-plane ICP (:func:`_point_to_plane`): the view's points against
      the reference surface, paired by projective association. A plane fixes
      only its distance and tilt; the steps and noise of a real surface pull
      the other directions weakly but with a bias, so this term keeps only the
      directions it constrains well (:func:`_observable`);
    - direct alignment of the surface texture (:func:`_texture_residuals`),
      which fixes the motions along the surface, at the blur levels of
      :data:`_REFINE_LEVELS` (coarse to fine); its information is divided by
      the number of residuals per independent one (blurred noise);

    each Huber-weighted on its robust scale, and a Gaussian prior on the
    correction (the recorded pose's uncertainty). Directions the data
    constrain less than :data:`_CONSTRAINED` times as well as the prior are not
    moved (:func:`_regularised_step`): on a surface without usable texture the
    shift and rotation along it keep their recorded values.

    Parameters
    ----------
    start : (4, 4) ndarray
        The view's camera frame to the reference camera's, from the recorded poses.
    geometric : callable
        ``geometric(transform)`` -> (jacobian, residual) of :func:`_point_to_plane`.
    textured : callable
        ``textured(transform, level)`` -> (jacobian, residual) of :func:`_texture_residuals`
        (``transform`` the view-to-reference one) at a level of :data:`_REFINE_LEVELS`.
    correlation : sequence of float
        Per level, the texture residuals per independent one (their noise is
        blurred): the texture term's information is divided by it.
    prior : (6,) ndarray
        Inverse variances of the correction's twist (rotation, translation).
    units : (6,) ndarray
        Metres of surface motion per unit of each twist component.
    tolerance : float, metres
        Converged when a step of the last level moves the surface by less
        (coarser levels: :data:`_COARSE` times more).
    iterations : int
        Per level at most.

    Returns
    -------
    transform : (4, 4) ndarray
        The refined view-to-reference transform.
    info : dict
        ``iterations`` (in all), ``converged`` (also when ``settled``: the last level's
        steps hopped without falling below ``tolerance`` but the last two stayed within
        :data:`_COARSE` times it, a tenth of a pixel), and of the last iteration
        ``pairs`` and ``texture_pairs`` (residuals of each kind), their robust
        standard deviations ``shape_deviation_mm`` and ``texture_deviation``
        (in the texture's local standard deviations) and ``constrained``
        (directions updated).
    """
    transform, info, converged = start, {"iterations": 0}, False
    for level in range(len(_REFINE_LEVELS)):
        last = level == len(_REFINE_LEVELS) - 1
        motions = []  # surface motion of each step of this level, metres
        for _ in range(iterations):
            (shape_jacobian, shape_residual), (texture_jacobian, texture_residual) = (
                geometric(transform),
                textured(transform, level),
            )
            deviations = _robust_deviation(shape_residual), _robust_deviation(texture_residual)
            info = {
                **info,
                "pairs": shape_residual.size,
                "texture_pairs": texture_residual.size,
                "shape_deviation_mm": 1e3 * deviations[0],
                "texture_deviation": deviations[1],
            }
            if shape_residual.size < _MIN_PAIRS:
                return transform, {**info, "converged": False, "constrained": 0}
            matrix, gradient = _observable(
                *_robust_normal_equations(shape_jacobian, shape_residual, deviations[0]), units
            )
            if texture_residual.size >= _MIN_TEXTURE:
                texture_matrix, texture_gradient = _robust_normal_equations(
                    texture_jacobian, texture_residual, deviations[1]
                )
                matrix = matrix + texture_matrix / correlation[level]
                gradient = gradient + texture_gradient / correlation[level]
            step, info["constrained"] = _regularised_step(
                matrix, gradient, prior, _twist(np.linalg.solve(start, transform))
            )
            transform = transform @ _rigid(step)
            info["iterations"] += 1
            motions.append(float(np.max(np.abs(step * units))))
            converged = motions[-1] <= tolerance * (1.0 if last else _COARSE)
            if converged:
                break
    # Projective pairs change as the pose moves: steps can hop around the optimum by a few hundredths of a
    # pixel for ever. Settled: the last two steps of the last level within the coarse levels' bound.
    settled = not converged and len(motions) >= 2 and max(motions[-2:]) <= tolerance * _COARSE
    return transform, {**info, "converged": converged or settled, "settled": settled}


def _texture(intensity: np.ndarray, valid: np.ndarray, sigma: float, dtype=np.float64) -> np.ndarray:
    """Surface texture: log intensity minus its local mean, over its local standard deviation.

    Distance, angle and instrument act on the intensity as smooth factors, so
    this leaves the texture at the same contrast everywhere, also on weakly
    textured surfaces beside strong edges.

    Parameters
    ----------
    intensity : (H, W) ndarray
        Camera intensity.
    valid : (H, W) ndarray of bool
    sigma : float, pixels
        Scale of the Gaussian windows of the local mean and standard deviation
        (normalised over valid pixels).
    dtype : numpy float type
        Of the normalisation weights; the computation runs in the wider of it
        and the intensity's type (float32 blurs run ~10x faster than float64).

    Returns
    -------
    (H, W) ndarray
        In local standard deviations; NaN on invalid pixels and non-positive intensities.
    """
    usable = valid & (intensity > 0)
    unusable = ~usable
    # in place, in the buffers of the operations' results: the same operations, fewer passes over memory
    level = np.where(usable, intensity, 1.0)
    np.log(level, out=level)  # 0.0 where unusable
    weight = cv2.GaussianBlur(usable.astype(dtype), (0, 0), sigma)
    np.maximum(weight, np.finfo(dtype).tiny, out=weight)
    detail = np.divide(cv2.GaussianBlur(level, (0, 0), sigma), weight)
    np.subtract(level, detail, out=detail)
    np.copyto(detail, 0.0, where=unusable)
    spread = np.divide(cv2.GaussianBlur(detail * detail, (0, 0), sigma), weight)
    np.sqrt(spread, out=spread)
    np.maximum(spread, np.finfo(np.float32).eps, out=spread)
    np.divide(detail, spread, out=spread)
    np.copyto(spread, np.nan, where=unusable)
    return spread


def _feature_image(intensity: np.ndarray, valid: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Make an 8-bit image of the surface texture (:func:`_texture`) and the mask where keypoints may lie.

    Parameters
    ----------
    intensity : (H, W) ndarray
        Camera intensity.
    valid : (H, W) ndarray of bool
    sigma : float, pixels
        Scale of the local normalisation.

    Returns
    -------
    image : (H, W) ndarray of uint8
        +-3 local standard deviations span 0..255; mid-grey on invalid pixels.
    mask : (H, W) ndarray of uint8
        255 at least :data:`_FEATURE_MARGIN` pixels from invalid pixels and the border.
    """
    score = _texture(intensity, valid, sigma)
    usable = np.isfinite(score)
    scaled = (np.where(usable, score, 0.0) + _CLIP) * (255.0 / (2.0 * _CLIP))
    image = np.where(usable, np.clip(scaled, 0.0, 255.0), 127.5).astype(np.uint8)
    kernel = np.ones((2 * _FEATURE_MARGIN + 1,) * 2, np.uint8)
    mask = cv2.erode(usable.astype(np.uint8) * 255, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    return image, mask


def _keypoints(image: np.ndarray, mask: np.ndarray, detector: str) -> tuple[np.ndarray, np.ndarray | None]:
    """Keypoint positions (N, 2) (column, row; array coords, float32) and descriptors of one image."""
    keypoints, descriptors = DETECTORS[detector][0]().detectAndCompute(image, mask)
    positions = np.array([keypoint.pt for keypoint in keypoints], dtype=np.float32).reshape(-1, 2)
    return positions, descriptors


def _match(reference: tuple, view: tuple, norm: int, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """Ratio-test matches between two keypoint sets: positions (M, 2) in the reference and the view."""
    (ref_pos, ref_desc), (view_pos, view_desc) = reference, view
    if ref_desc is None or view_desc is None or len(ref_desc) < 2 or len(view_desc) < 2:
        return np.empty((0, 2), np.float32), np.empty((0, 2), np.float32)
    pairs = cv2.BFMatcher(norm).knnMatch(ref_desc, view_desc, k=2)
    table = np.array([(p[0].queryIdx, p[0].trainIdx, p[0].distance, p[1].distance) for p in pairs if len(p) == 2])
    keep = table[:, 2] < ratio * table[:, 3] if table.size else np.zeros(0, bool)
    return ref_pos[table[keep, 0].astype(np.intp)], view_pos[table[keep, 1].astype(np.intp)]


def _apply_homography(h: np.ndarray, col: np.ndarray, row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Image of positions under a homography ``h`` (3, 3); NaN where they map to or beyond infinity."""
    w = h[2, 0] * col + h[2, 1] * row + h[2, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        front = w > 0
        u = np.where(front, (h[0, 0] * col + h[0, 1] * row + h[0, 2]) / w, np.nan)
        v = np.where(front, (h[1, 0] * col + h[1, 1] * row + h[1, 2]) / w, np.nan)
    return u, v


def _fit_homography(src: np.ndarray, dst: np.ndarray, threshold: float) -> tuple[np.ndarray | None, np.ndarray]:
    """Robust homography ``dst ~ H src`` (USAC MAGSAC++) and the inlier mask (M,) bool."""
    if len(src) < 4:
        return None, np.zeros(len(src), bool)
    matrix, inliers = cv2.findHomography(
        src, dst, cv2.USAC_MAGSAC, threshold, maxIters=_MAGSAC_ITERATIONS, confidence=_MAGSAC_CONFIDENCE
    )
    if matrix is None:
        return None, np.zeros(len(src), bool)
    return matrix, inliers.ravel().astype(bool)


# ---------------------------------------------------------------------------------------------
# helpers on the ingest cube


def _sensor_indices(coord: xr.DataArray, name: str) -> np.ndarray:
    """Return the values of a ``y``/``x`` coordinate, checked to be >= 2 contiguous sensor indices."""
    values = np.asarray(coord.values)
    if values.size < 2 or not np.array_equal(values, values[0] + np.arange(values.size)):
        raise ValueError(f"{name} must be >= 2 contiguous sensor indices (a crop of the sensor), got {values!r:.80}")
    return values


def _options(method: str, options: Mapping, auto: bool) -> dict:
    """Update the defaults of ``method`` by ``options``; unknown names raise TypeError."""
    defaults = HOMOGRAPHY_OPTIONS if method == "homography" else POSE_OPTIONS
    allowed = {**HOMOGRAPHY_OPTIONS, **POSE_OPTIONS} if auto else defaults
    unknown = sorted(set(options) - set(allowed))
    if unknown:
        raise TypeError(f"registration_maps(method={method!r}): unknown options {unknown}; known: {sorted(allowed)}")
    chosen = {**defaults, **{key: value for key, value in options.items() if key in defaults}}
    if method == "homography" and chosen["detector"] not in DETECTORS:
        raise ValueError(f"detector {chosen['detector']!r} is not known; expected one of {sorted(DETECTORS)}")
    smooth = chosen.get("smooth", 1)
    if int(smooth) != smooth or smooth < 1 or smooth % 2 == 0:
        raise ValueError(f"smooth must be an odd integer >= 1, got {chosen['smooth']!r}")
    for bound in ("max_translation", "max_rotation"):
        if bound in chosen and not chosen[bound] > 0:
            raise ValueError(f"{bound} must be > 0, got {chosen[bound]!r}")
    return chosen


def _poses_usable(ingest: xr.Dataset) -> str | None:
    """Why the poses method cannot run on ``ingest``, or None when it can."""
    if "pose" not in ingest:
        return "no view carries a pose"
    finite = np.isfinite(np.asarray(ingest["pose"].values)).all(axis=(1, 2))
    if not finite.all():
        missing = [str(view) for view, ok in zip(ingest["view"].values, finite) if not ok]
        return f"views {missing} carry no pose"
    return None


def _check_poses(poses: np.ndarray, views, item: str) -> None:
    """Every pose is a rigid transform (rotation orthonormal, det +1, last row 0 0 0 1)."""
    for view, pose in zip(views, poses):
        rotation = pose[:3, :3]
        rigid = np.allclose(rotation.T @ rotation, np.eye(3), atol=_RIGID_TOLERANCE) and np.linalg.det(rotation) > 0
        if not rigid or not np.allclose(pose[3], [0.0, 0.0, 0.0, 1.0]):
            raise RegistrationError(
                f"item {item!r}, view {view!r}: the pose is not a rigid camera-to-world transform "
                f"(rotation must be orthonormal with det +1, last row 0 0 0 1): {pose.tolist()}"
            )


def _camera_model(ingest: xr.Dataset, xyz: np.ndarray, grid, item: str) -> tuple[CameraModel, dict]:
    """Return the camera model of the poses methods and its description.

    campaign.yaml's intrinsics when they give the lens distortion; else the
    model fitted to the clouds (:func:`~surffin.method.camera_model.fit_camera_model`),
    refused when it misses their pixels by more than :data:`_MODEL_RESIDUAL`.
    The description: ``source`` (``"given"`` or ``"estimated"``), ``fx``,
    ``fy``, ``cx``, ``cy``, ``distortion`` and ``residual_px``, the rms
    distance (pixels) between the pixels of the views' valid points and the
    model's projections of them (:func:`~surffin.method.camera_model.model_residual`);
    when intrinsics without distortion were given, ``given_residual_px``: theirs.
    """
    intrinsics = ingest.attrs.get("camera", {}).get("intrinsics")
    if intrinsics and intrinsics.get("distortion"):
        camera = CameraModel.from_intrinsics(intrinsics)
        return camera, {"source": "given", **camera.as_dict(), "residual_px": model_residual(camera, xyz, *grid)}
    try:
        camera, residual = fit_camera_model(xyz, *grid)
    except ValueError as error:
        raise RegistrationError(f"item {item!r}: no camera model: {error}") from None
    if not residual <= _MODEL_RESIDUAL:
        # NaN: the fitted lens model folds back before some of the points (it projects them nowhere)
        misses = f"misses their pixels by {residual:.2f} px rms" if np.isfinite(residual) else "projects some nowhere"
        raise RegistrationError(
            f"item {item!r}: the camera model fitted to the views' clouds {misses} (at most {_MODEL_RESIDUAL} px "
            f"rms): give camera.intrinsics with their distortion in campaign.yaml"
        )
    described = {"source": "estimated", **camera.as_dict(), "residual_px": residual}
    if intrinsics:
        described["given_residual_px"] = model_residual(CameraModel.from_intrinsics(intrinsics), xyz, *grid)
    return camera, described


def _plane_frame(points: np.ndarray) -> np.ndarray:
    """Return the frame (4, 4) of the dominant plane of points (N, 3), camera frame, by RANSAC and least squares.

    The plane with most points within :data:`_PLANE_TOLERANCE` (RANSAC), fitted
    again to its points by least squares until they stay the same (at most
    :data:`_PLANE_FITS` times).

    Columns: two in-plane axes (the first along the camera's x axis), the
    normal toward the camera, and the origin where the optical axis meets the
    plane; it takes plane coordinates (along, across, height) to the camera frame.
    """
    rng = np.random.default_rng(0)
    sample = points[rng.choice(len(points), min(len(points), _PLANE_SAMPLES), replace=False)]
    first, second, third = (sample[rng.integers(0, len(sample), _PLANE_TRIALS)] for _ in range(3))
    normals = np.cross(second - first, third - first)
    with np.errstate(invalid="ignore", divide="ignore"):
        normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
        counts = np.abs(sample @ normals.T - np.einsum("ij,ij->i", normals, first)) <= _PLANE_TOLERANCE
    best = int(np.argmax(counts.sum(axis=0)))
    normal, centroid, inliers = normals[best], first[best], counts[:, best]
    for _ in range(_PLANE_FITS):
        centroid = sample[inliers].mean(axis=0)
        normal = np.linalg.svd(sample[inliers] - centroid, full_matrices=False)[2][2]
        previous, inliers = inliers, np.abs((sample - centroid) @ normal) <= _PLANE_TOLERANCE
        if np.array_equal(inliers, previous):
            break
    normal = -normal if normal @ centroid > 0 else normal
    along = np.array([1.0, 0.0, 0.0]) - normal[0] * normal
    along /= np.linalg.norm(along)
    frame = np.eye(4)
    frame[:3, :3] = np.stack([along, np.cross(normal, along), normal], axis=-1)
    frame[:3, 3] = (normal @ centroid / normal[2]) * np.array([0.0, 0.0, 1.0])
    return frame


def _height_map(points: np.ndarray, frame: np.ndarray, cell: float) -> np.ndarray:
    """Return the mean height (metres, float32) of points (N, 3) over a plane's square grid of cells; NaN where none.

    Cell ``(row, col)`` spans ``[(col - n / 2) cell, (col + 1 - n / 2) cell)`` along the plane's first
    axis (:func:`_plane_frame`), ``n`` = :data:`_HEIGHT_CELLS`; heights clipped to +- :data:`_HEIGHT_SPAN`.
    """
    local = (points - frame[:3, 3]) @ frame[:3, :3]
    col, row = (np.floor(local[:, axis] / cell + _HEIGHT_CELLS / 2).astype(np.intp) for axis in (0, 1))
    inside = (col >= 0) & (col < _HEIGHT_CELLS) & (row >= 0) & (row < _HEIGHT_CELLS)
    at = row[inside] * _HEIGHT_CELLS + col[inside]
    height = np.clip(local[inside, 2], -_HEIGHT_SPAN, _HEIGHT_SPAN)
    total = np.bincount(at, height, _HEIGHT_CELLS**2)
    count = np.bincount(at, None, _HEIGHT_CELLS**2)
    with np.errstate(invalid="ignore", divide="ignore"):
        return (total / count).reshape(_HEIGHT_CELLS, _HEIGHT_CELLS).astype(np.float32)


def _extended(image: np.ndarray) -> np.ndarray:
    """Fill the NaN cells of a height map smoothly from the known ones, and remove the mean (float32).

    A NaN cell takes the Gaussian-weighted mean (:data:`_EXTENSION` cells) of the
    known cells around it (the median far from any): the edge of the surface a
    view saw leaves no step, which would correlate with itself between views.
    """
    known = np.isfinite(image)
    weight = cv2.GaussianBlur(known.astype(np.float64), (0, 0), _EXTENSION)
    total = cv2.GaussianBlur(np.where(known, image, 0.0).astype(np.float64), (0, 0), _EXTENSION)
    with np.errstate(invalid="ignore", divide="ignore"):
        around = np.where(weight > 1e-9, total / weight, np.nanmedian(image))
    out = np.where(known, image, around)
    return (out - out.mean()).astype(np.float32)


def _turned(image: np.ndarray, degrees: float) -> np.ndarray:
    """Return ``image`` (n, n) turned by ``degrees`` about its centre (content at p goes to R p); 0 outside."""
    angle = np.deg2rad(degrees)
    rotation = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    centre = np.full(2, (image.shape[0] - 1) / 2.0)
    affine = np.hstack([rotation, (centre - rotation @ centre)[:, None]])
    return cv2.warpAffine(image, affine, image.shape[::-1], flags=cv2.INTER_LINEAR, borderValue=0.0)


def _coarse_transforms(reference, view, reference_frame, view_frame, tolerance: float, where: str) -> list:
    """Estimate the transform from the reference camera's frame to a view's from their clouds alone: candidates.

    Each cloud's dominant plane (:func:`_plane_frame`) fixes its tilt and
    distance (at least :data:`_MIN_RELIEF` of the points must lie off it);
    the turn about the plane's normal and the shift along it are those that
    best superpose the two height maps of the surface over the plane
    (:func:`_height_map`): phase correlation of the view's map with the
    reference's turned in steps of :data:`_TURN_STEP` over the whole circle;
    the peaks of the correlation over the turn (at most :data:`_CANDIDATES`,
    each at least :data:`_CANDIDATE_SHARE` of the highest: a symmetric surface
    has several) are refined in a sixth of the step; the shift along the
    normal is the median height difference.

    Parameters
    ----------
    reference, view : (h, w, 3) ndarray, metres
        The two views' points, each in its camera frame; NaN = invalid.
    reference_frame, view_frame : (4, 4) ndarray
        Of their dominant planes (:func:`_plane_frame`).
    tolerance : float, metres
        Points within it of a plane are on it.
    where : str
        Starts the RegistrationError of a failure.

    Returns
    -------
    list of (transform, diagnostics)
        Highest correlation first: ``transform`` (4, 4) and ``coarse_turn_deg``
        (about the plane's normal) and ``coarse_response`` (the phase
        correlation's peak, 0..1).
    """
    clouds = [points.reshape(-1, 3) for points in (reference, view)]
    clouds = [cloud[np.isfinite(cloud).all(axis=-1)] for cloud in clouds]
    frames = [reference_frame, view_frame]
    relief = [
        np.mean(np.abs((cloud - frame[:3, 3]) @ frame[:3, 2]) > tolerance) for cloud, frame in zip(clouds, frames)
    ]
    if min(relief) < _MIN_RELIEF:
        raise RegistrationError(
            f"{where}: only {100 * min(relief):.1f} % of a view's points lie off its dominant plane by more than "
            f"tolerance={tolerance} m (at least {100 * _MIN_RELIEF:.0f} %): without relief the clouds do not fix the "
            f"view's pose; give the views poses (method='poses') or use method='homography'"
        )
    spans = [np.percentile(np.abs((cloud - frame[:3, 3]) @ frame[:3, :2]), 99) for cloud, frame in zip(clouds, frames)]
    # the cells hold a few points each (else the empty ones make a pattern that correlates with itself)
    spacing = max(
        np.nanmedian(np.linalg.norm(np.diff(points, axis=axis), axis=-1))
        for points in (reference, view)
        for axis in (0, 1)
    )
    cell = max(2.0 * max(spans) / _HEIGHT_CELLS, _CELL_SPACING * spacing)
    maps = [_height_map(cloud, frame, cell) for cloud, frame in zip(clouds, frames)]
    filled = [_extended(_blurred(image, 1.0)) for image in maps]
    window = cv2.createHanningWindow(filled[0].shape[::-1], cv2.CV_32F)

    def correlate(degrees: float):
        # a copy: OpenCV 5's phaseCorrelate multiplies its inputs by the window in place
        return cv2.phaseCorrelate(_turned(filled[0], degrees), filled[1].copy(), window)

    turns = np.arange(0.0, 360.0, _TURN_STEP)
    responses = np.array([correlate(degrees)[1] for degrees in turns])
    peaks = np.flatnonzero((responses >= np.roll(responses, 1)) & (responses >= np.roll(responses, -1)))
    peaks = peaks[np.argsort(-responses[peaks])]
    peaks = peaks[responses[peaks] >= _CANDIDATE_SHARE * responses[peaks[0]]][:_CANDIDATES]
    centres = (np.stack(np.meshgrid(np.arange(_HEIGHT_CELLS), np.arange(_HEIGHT_CELLS)), -1) + 0.5) * cell
    centres = centres.reshape(-1, 2) - _HEIGHT_CELLS / 2 * cell
    candidates = []
    for peak in peaks:
        turn = max(turns[peak] + np.linspace(-_TURN_STEP, _TURN_STEP, 13), key=lambda degrees: correlate(degrees)[1])
        (shift_col, shift_row), response = correlate(turn)
        angle = np.deg2rad(turn)
        motion = np.eye(4)
        motion[:2, :2] = [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
        motion[:2, 3] = cell * np.array([shift_col, shift_row])
        # the reference's cells moved into the view's plane: the median height difference is the shift along the normal
        moved = centres @ motion[:2, :2].T + motion[:2, 3]
        col, row = (np.floor(moved[:, axis] / cell + _HEIGHT_CELLS / 2).astype(np.intp) for axis in (0, 1))
        inside = (col >= 0) & (col < _HEIGHT_CELLS) & (row >= 0) & (row < _HEIGHT_CELLS)
        difference = maps[1][row[inside], col[inside]] - maps[0].ravel()[inside]
        if np.isfinite(difference).any():
            motion[2, 3] = np.nanmedian(difference)
            transform = frames[1] @ motion @ np.linalg.inv(frames[0])
            candidates.append((transform, {"coarse_turn_deg": float(turn % 360.0), "coarse_response": float(response)}))
    if not candidates:
        raise RegistrationError(
            f"{where}: the view's surface does not overlap the reference view's (no cell of both height maps at any "
            f"coarse pose): do the views show one surface? give them poses (method='poses')"
        )
    return candidates


def _identity(grid: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Sensor (column, row) of every pixel of a grid given by its columns and rows, float64 (h, w) each."""
    columns, rows = grid
    return tuple(np.meshgrid(columns.astype(np.float64), rows.astype(np.float64)))


def _part(grid: tuple[np.ndarray, np.ndarray], window: Roi | None, item: str) -> tuple[slice, slice]:
    """Return the (rows, columns) slices of the grid's pixels inside the sensor ``window``: all without one."""
    if window is None:
        return slice(None), slice(None)
    columns, rows = grid
    try:
        inside = window.clip(Roi.spanning(rows, columns))
    except ValueError as exc:
        raise ValueError(f"item {item!r}: the window to map holds no pixel of the grid ({exc})") from None
    first = (rows[0], columns[0])
    return slice(inside.y[0] - first[0], inside.y[1] - first[0]), slice(inside.x[0] - first[1], inside.x[1] - first[1])


def _pose_refiner(ingest, xyz, reference, distance, points, ref, grid, opts, camera, recorded):
    """Build the pose refinement of the poses methods (:func:`_refine_pose`).

    Parameters
    ----------
    ingest : Dataset
        The item's ingest cube (``intensity``, ``valid``, attrs ``camera``).
    xyz : (view, h, w, 3) ndarray, metres
        Every view's points, its camera frame, as stored (float32 or float64); NaN = invalid.
    reference : (h, w, 3) ndarray of float64, metres
        The reference view's points.
    distance : callable
        ``distance(index)``: the ranges (h, w) of view ``index``'s points, metres.
    points : (h, w, 3) ndarray, metres
        The reference view's points, range averaged (:func:`_smooth_range`).
    ref : int
        The reference view.
    grid : (columns, rows)
        Sensor indices of the grid.
    opts : dict
        The poses method's options.
    camera : CameraModel
    recorded : bool
        The starting poses are recorded ones: a prior toward them (:data:`_PRIOR`)
        and the bounds ``max_translation`` and ``max_rotation`` of the
        correction. Else they are the coarse estimates of
        :func:`_coarse_transforms`: a broad prior (:data:`_COARSE_PRIOR`) and
        no bounds.

    Returns
    -------
    callable
        ``refine(index, transform, where, iterations=10)``: the
        reference-to-view ``transform`` (4, 4) of view ``index`` refined (at
        most ``iterations`` per level), and its diagnostics; RegistrationError
        starting with ``where`` when the refinement fails or moves it too far.
    """
    intensity = np.asarray(ingest["intensity"].values)
    valid = np.asarray(ingest["valid"].values, dtype=bool)
    tolerances = opts["tolerance"], opts["relative"]
    stride = max(1, round(np.sqrt(points.shape[0] * points.shape[1] / _REFINE_SAMPLES)))
    # contiguous: the point-to-plane pairs gather its rows every iteration
    normals = np.ascontiguousarray(plane_normals(reference, _REFINE_WINDOW))
    target = np.where(np.isfinite(normals), points, np.nan)
    # texture samples whose normalisation and blur windows keep off depth edges: the edges move
    # with the parallax between views, and the surfaces beside them are seen differently (at the samples only)
    inside = np.minimum(
        cv2.distanceTransform(np.isfinite(normals[..., 0]).astype(np.uint8), cv2.DIST_L2, 5)[::stride, ::stride],
        _interior(_norm(points), *tolerances)[::stride, ::stride],
    )
    texture = _texture(intensity[ref], valid[ref], _REFINE_CONTRAST, np.float32)
    sample = points[::stride, ::stride].reshape(-1, 3)
    known = np.isfinite(sample).all(axis=-1)
    sample = sample[known]
    # per level, the samples with a texture (the others never give a texture residual) and their texture
    texture_samples = []
    for blur in _REFINE_LEVELS:
        values = np.where(inside > _REFINE_CONTRAST + blur, _blurred(texture, blur)[::stride, ::stride], np.nan)
        values = values.ravel()[known]
        texture_samples.append((sample[np.isfinite(values)], values[np.isfinite(values)]))
    origin = (grid[1][0], grid[0][0])
    correlation = [_correlated(blur, stride) for blur in _REFINE_LEVELS]
    spread = _PRIOR if recorded else _COARSE_PRIOR
    advice = (
        "check the view and its pose, or map with the recorded poses (refine=False)"
        if recorded
        else "do the views show one surface? give them poses (method='poses') or use method='homography'"
    )
    prior = 1.0 / np.repeat([np.deg2rad(spread[0]), spread[1]], 3) ** 2

    @cache
    def view_data(index: int):
        """Return a view's sampled points, texture stacks (:func:`_sampled`) per level and median range."""
        source = xyz[index][::stride, ::stride].reshape(-1, 3).astype(np.float64)
        view_distance = distance(index)
        view_texture = _texture(intensity[index], valid[index], _REFINE_CONTRAST, np.float32)
        view_inside = _interior(view_distance, *tolerances)
        sampled_distance = view_distance.astype(np.float32)  # the levels' stacks hold it in float32
        sampled = [
            _sampled(np.where(view_inside > _REFINE_CONTRAST + blur, view_texture, np.nan), sampled_distance, blur)
            for blur in _REFINE_LEVELS
        ]
        measured = view_distance[~np.isnan(view_distance)]
        scale = float(_median(measured)) if measured.size else float("nan")  # np.nanmedian's value
        return source[np.isfinite(source).all(axis=-1)], sampled, scale

    def refine(index: int, relative: np.ndarray, where: str, iterations: int = _REFINE_ITERATIONS):
        source, sampled, scale = view_data(index)  # scale: metres of surface motion per radian
        start = np.linalg.inv(relative)
        transform, info = _refine_pose(
            start,
            lambda current: _point_to_plane(current, source, target, normals, camera, grid, *tolerances),
            lambda current, level: _texture_residuals(
                np.linalg.inv(current), *texture_samples[level], sampled[level], camera, origin, *tolerances
            ),
            correlation,
            prior,
            np.repeat([scale, 1.0], 3),
            _REFINE_STEP * scale / max(camera.fx, camera.fy),
            iterations,
        )
        correction = np.linalg.solve(start, transform)
        twist = _twist(correction)
        moved = {
            "correction_mm": 1e3 * float(np.linalg.norm(twist[3:])),
            "correction_deg": float(np.rad2deg(np.linalg.norm(twist[:3]))),
        }
        if info["pairs"] < _MIN_PAIRS:
            raise RegistrationError(
                f"{where}: only {info['pairs']} of the view's points lie on the reference surface within "
                f"max(tolerance, relative * range): too few to refine its pose; {advice}"
            )
        if not info["converged"]:
            raise RegistrationError(
                f"{where}: the pose refinement did not converge in {info['iterations']} iterations "
                f"(correction so far {moved['correction_mm']:.2f} mm, {moved['correction_deg']:.3f} deg); {advice}"
            )
        bounded = (
            moved["correction_mm"] <= 1e3 * opts["max_translation"] and moved["correction_deg"] <= opts["max_rotation"]
        )
        if recorded and not bounded:
            raise RegistrationError(
                f"{where}: the pose refinement moves the view by {moved['correction_mm']:.2f} mm and "
                f"{moved['correction_deg']:.3f} deg, beyond max_translation={opts['max_translation']} m or "
                f"max_rotation={opts['max_rotation']} deg: the recorded pose is far off (units, camera.hand_eye?) "
                f"or the refinement locked onto another surface"
            )
        return np.linalg.inv(transform), {**moved, "correction": correction.tolist(), **info}

    return refine


def _chosen(candidates: list, refine, index: int, where: str) -> tuple[np.ndarray, dict]:
    """Choose a view's pose among the coarse candidates of :func:`_coarse_transforms`, each refined by ``refine``.

    Among the candidates whose refinement converged (in :data:`_REFINE_ITERATIONS`
    iterations per level; when none does, all are tried again with
    :data:`_ESTIMATE_ITERATIONS`) with at least half the most point-to-plane
    pairs of any (the geometry agrees), the one whose texture
    agrees best (the smallest ``texture_deviation``; without a texture term the
    smallest ``shape_deviation_mm``): a symmetric relief has several
    candidates that only the texture tells apart. A pose whose refinement
    leaves directions free (a plane without texture) is refused.

    Returns
    -------
    transform : (4, 4) ndarray
        The reference camera frame to the view's.
    diagnostics : dict
        The coarse and refinement diagnostics of the chosen candidate and
        ``candidates`` (how many were refined).
    """
    refined, failures = [], []
    for iterations in (_REFINE_ITERATIONS, _ESTIMATE_ITERATIONS):
        for transform, coarse in candidates:
            try:
                transform, info = refine(index, transform, where, iterations)
            except RegistrationError as error:
                failures.append(str(error))
                continue
            refined.append((transform, {**coarse, **info, "candidates": len(candidates)}))
        if refined:
            break
    if not refined:
        raise RegistrationError(
            f"{where}: none of the {len(candidates)} coarse poses estimated from the clouds could be refined; "
            f"the first: {failures[-len(candidates)]}"
        )
    most = max(info["pairs"] for _, info in refined)
    agreeing = [(transform, info) for transform, info in refined if info["pairs"] >= 0.5 * most]
    textured = all(info["texture_pairs"] >= _MIN_TEXTURE for _, info in agreeing)
    transform, info = min(agreeing, key=lambda pair: pair[1]["texture_deviation" if textured else "shape_deviation_mm"])
    if info["constrained"] < 6:
        raise RegistrationError(
            f"{where}: the clouds fix only {info['constrained']} of the 6 directions of the view's pose (a plane "
            f"without usable texture?): give the views poses (method='poses') or use method='homography'"
        )
    return transform, info


def _pose_estimator(xyz: np.ndarray, ref: int, views: list, item: str, tolerance: float, refine):
    """Build the estimate of the views' poses from their clouds alone (method ``"clouds"``).

    A view is aligned (:func:`_coarse_transforms`) with the view nearest to it
    in orientation among those nearer the reference view than itself (the
    reference view, or one already estimated: the angle between two views is
    that between the normals of their dominant planes), so that views far from
    the reference view are reached in smaller steps; the candidates are then
    refined against the reference view and one chosen (:func:`_chosen`). When
    none of them refines, the candidates aligned with the reference view and
    the views already estimated are tried instead.

    Parameters
    ----------
    xyz : (view, h, w, 3) ndarray, metres
        Every view's points, its camera frame; NaN = invalid.
    ref : int
        The reference view.
    views : list of str
    item : str
    tolerance : float, metres
        Of :func:`_coarse_transforms`.
    refine : callable
        Of :func:`_pose_refiner`.

    Returns
    -------
    callable
        ``estimated(index)``: the reference-to-view transform (4, 4) of view
        ``index`` and its diagnostics (those of :func:`_chosen`, ``pose``: the
        view's camera-to-reference-camera transform, and ``aligned_with``: the
        view its coarse pose was found against; ``texture_outlier`` when its first
        pose's texture deviation was an outlier among the item's views, which a search
        from every other view then tried to better, ``searched_again`` when it did).
        RegistrationError naming the item and view when it fails.
    """
    clouds = [points.reshape(-1, 3) for points in xyz]
    clouds = [cloud[np.isfinite(cloud).all(axis=-1)] for cloud in clouds]
    for view, cloud in zip(views, clouds):
        if len(cloud) < _MIN_PAIRS:
            raise RegistrationError(
                f"item {item!r}, view {view!r}: {len(cloud)} valid points, too few to estimate the pose from the clouds"
            )
    frames = [_plane_frame(cloud) for cloud in clouds]
    normals = np.array([frame[:3, 2] for frame in frames])
    angles = np.arccos(np.clip(normals @ normals.T, -1.0, 1.0))
    found = {}

    def searched(index: int, anchors: list[int], where: str) -> tuple[np.ndarray, dict]:
        # the candidates aligned with each anchor view (its estimated pose), refined, one chosen
        candidates = [
            (
                coarse @ (np.eye(4) if anchor == ref else estimated(anchor)[0]),
                {**details, "aligned_with": views[anchor]},
            )
            for anchor in anchors
            for coarse, details in _coarse_transforms(
                xyz[anchor], xyz[index], frames[anchor], frames[index], tolerance, where
            )
        ]
        transform, info = _chosen(candidates, refine, index, where)
        return transform, {**info, "pose": np.linalg.inv(transform).tolist()}

    def estimated(index: int) -> tuple[np.ndarray, dict]:
        if index not in found:
            where = f"item {item!r}, view {views[index]!r}"
            nearer = [other for other in range(len(views)) if angles[other, ref] < angles[index, ref]]
            base = min(nearer, key=lambda other: angles[other, index]) if nearer else ref
            try:
                found[index] = searched(index, [base], where)
            except RegistrationError:
                # no candidate from the chain's step refined: from the reference view and the views estimated
                others = [anchor for anchor in (ref, *found) if anchor != base]
                if not others:
                    raise
                found[index] = searched(index, others, where)
        return found[index]

    def checked(index: int) -> tuple[np.ndarray, dict]:
        # a pose whose texture agrees far worse than the other views' is searched again from every view
        transform, info = estimated(index)
        if index in rechecked or "texture_deviation" not in info:
            return transform, info
        rechecked.add(index)
        others = [
            estimated(other)[1].get("texture_deviation") for other in range(len(views)) if other not in (ref, index)
        ]
        others = [value for value in others if value is not None]
        if not others or info["texture_deviation"] <= _TEXTURE_OUTLIER * float(np.median(others)):
            return transform, info
        found[index] = transform, {**info, "texture_outlier": True}
        where = f"item {item!r}, view {views[index]!r}"
        # every view but the one the first pose was aligned with (its candidates were tried), the reference view too
        anchors = [anchor for anchor in range(len(views)) if anchor != index and views[anchor] != info["aligned_with"]]
        try:
            transform, again = searched(index, anchors, where)
        except RegistrationError:  # no better pose from there: the first one stays
            return found[index]
        if again["texture_deviation"] < info["texture_deviation"]:
            found[index] = transform, {**again, "texture_outlier": True, "searched_again": True}
        return found[index]

    rechecked: set[int] = set()
    return checked


def _pose_mapper(ingest: xr.Dataset, ref: int, item: str, grid, opts: dict, part, estimate: bool = False):
    """Build the poses methods: a function of a view index giving (col, row, diagnostics), and the camera's attrs.

    The maps cover the ``part`` (rows, columns slices) of the grid; the poses come from all of it.

    The views' recorded poses, refined against the reference view when
    ``opts["refine"]``, or with ``estimate`` their poses relative to the
    reference view estimated from the clouds (:func:`_pose_estimator`), always refined.
    """
    views = [str(view) for view in ingest["view"].values]
    # The points as stored, each view's in float64 when it is used: the camera model's samples, the
    # reference view and each view's ranges (a float64 copy of the whole cube costs ~4x more, in fresh pages).
    xyz = np.asarray(ingest["xyz"].transpose("view", "y", "x", "axis").values)
    camera, described = _camera_model(ingest, xyz, grid, item)
    reference = xyz[ref].astype(np.float64)
    points = _smooth_range(reference, opts["smooth"], opts["tolerance"], opts["relative"])
    if not estimate:
        poses = np.asarray(ingest["pose"].values, dtype=np.float64)
        _check_poses(poses, views, item)

    @cache
    def distance(index: int) -> np.ndarray:
        """Return the ranges (h, w) of view ``index``'s points, metres (its refinement and its map use them)."""
        return _norm(xyz[index].astype(np.float64))

    refined = opts["refine"] or estimate  # a coarse estimate alone registers no better than to a few mm
    refine = (
        _pose_refiner(ingest, xyz, reference, distance, points, ref, grid, opts, camera, not estimate)
        if refined
        else None
    )
    estimated = (
        _pose_estimator(xyz.astype(np.float64), ref, views, item, opts["tolerance"], refine) if estimate else None
    )
    target = (grid[0][part[1]], grid[1][part[0]])

    def one(index: int):
        if index == ref:
            unmoved = {"correction_mm": 0.0, "correction_deg": 0.0, "correction": np.eye(4).tolist()}
            return *_identity(target), {"mapped": 1.0, "occluded": 0.0, "range_rms": 0.0, **(unmoved if refine else {})}
        if estimate:
            transform, found = estimated(index)
        else:
            transform, found = np.linalg.solve(poses[index], poses[ref]), {}
            if refine is not None:
                transform, found = refine(index, transform, f"item {item!r}, view {views[index]!r}")
        col, row, diagnostics = _pose_map(
            points[part], transform, camera, distance(index), *grid, opts["tolerance"], opts["relative"]
        )
        return col, row, {**diagnostics, **found}

    return one, {"camera_model": described}


def _roi_mask(roi: Mapping | None, grid, item: str) -> np.ndarray | None:
    """255 inside a sensor roi ``{"y": [y0, y1], "x": [x0, x1]}`` (half-open) on the grid, uint8 (h, w)."""
    if roi is None:
        return None
    columns, rows = grid
    inside = ((rows >= roi["y"][0]) & (rows < roi["y"][1]))[:, None] & (
        (columns >= roi["x"][0]) & (columns < roi["x"][1])
    )[None, :]
    if not inside.any():
        raise RegistrationError(
            f"item {item!r}: roi {dict(roi)} does not overlap the grid (sensor rows "
            f"{rows[0]}..{rows[-1]}, columns {columns[0]}..{columns[-1]})"
        )
    return inside.astype(np.uint8) * 255


def _homography_mapper(ingest: xr.Dataset, ref: int, item: str, grid, opts: dict, part):
    """Build the homography method: a function of a view index giving (col, row, diagnostics) on ``part`` of a grid."""
    views = [str(view) for view in ingest["view"].values]
    intensity = np.asarray(ingest["intensity"].values)
    valid = np.asarray(ingest["valid"].values, dtype=bool)
    offset = np.array([grid[0][0], grid[1][0]], dtype=np.float32)
    norm = DETECTORS[opts["detector"]][1]
    images = [_feature_image(intensity[k], valid[k], opts["contrast_sigma"]) for k in range(len(views))]
    roi = _roi_mask(opts["roi"], grid, item)
    if roi is not None:
        images[ref] = (images[ref][0], images[ref][1] & roi)
    features = [_keypoints(image, mask, opts["detector"]) for image, mask in images]
    target = (grid[0][part[1]], grid[1][part[0]])

    def one(index: int):
        if index == ref:
            return *_identity(target), {"keypoints": len(features[ref][0])}
        src, dst = _match(features[ref], features[index], norm, opts["ratio"])
        where = f"item {item!r}, view {views[index]!r} (reference view {views[ref]!r})"
        if len(src) < opts["min_matches"]:
            raise RegistrationError(
                f"{where}: only {len(src)} keypoint matches ({opts['detector']}, ratio {opts['ratio']}; "
                f"min_matches={opts['min_matches']}): too little common texture for a homography; "
                f"give the views poses (method='poses'), use method='clouds' or lower min_matches"
            )
        src, dst = src + offset, dst + offset
        matrix, inliers = _fit_homography(src, dst, opts["threshold"])
        if inliers.sum() < opts["min_inliers"]:
            raise RegistrationError(
                f"{where}: only {int(inliers.sum())} of {len(src)} matches fit one homography "
                f"(threshold {opts['threshold']} px; min_inliers={opts['min_inliers']}): the surface may not be "
                f"planar or the matches are wrong; use method='poses' or lower min_inliers"
            )
        u, v = _apply_homography(matrix, src[inliers, 0], src[inliers, 1])
        col, row = _apply_homography(matrix, *_identity(target))
        _outside_to_nan(col, row, *grid)
        return (
            col,
            row,
            {
                "keypoints": len(features[index][0]),
                "matches": len(src),
                "inliers": int(inliers.sum()),
                "rms": float(np.sqrt(np.mean((u - dst[inliers, 0]) ** 2 + (v - dst[inliers, 1]) ** 2))),
                "homography": matrix.tolist(),
            },
        )

    return one, {}


# ---------------------------------------------------------------------------------------------
# public functions


def registration_maps(
    ingest: xr.Dataset, *, method: str = "auto", reference: str | None = None, window: Roi | None = None, **options
) -> xr.Dataset:
    """Where each view sees the surface point of every reference pixel.

    Parameters
    ----------
    ingest : Dataset
        An ingest cube (:func:`surffin.io.ingest.build_cube`): ``xyz`` (view, y,
        x, axis) metres, camera frame, NaN = invalid (the poses method);
        ``intensity`` and ``valid`` (view, y, x) (the homography method);
        ``pose`` (view, row, col) camera-to-world, metres; ``y``/``x`` are
        contiguous sensor indices. Attrs ``item``, ``reference_view`` and
        ``camera`` (optional ``intrinsics``: ``fx``, ``fy``, ``cx``, ``cy``,
        ``distortion``). Computed eagerly (the images are small).
    method : {"auto", "poses", "clouds", "homography"}
        ``"auto"`` takes ``"poses"`` when every view has a pose, else
        ``"clouds"`` (poses estimated from the clouds), and when that fails
        ``"homography"``.
    reference : str, optional
        The view whose grid the maps are on; default ``ingest.attrs
        ["reference_view"]``, else the first view.
    window : Roi, optional
        The reference pixels to map (sensor ranges, clipped to the grid); default all. The
        poses and homographies are found on the whole grid all the same: only the maps shrink.
    **options
        Of the method used, with the defaults of :data:`POSE_OPTIONS` and
        :data:`HOMOGRAPHY_OPTIONS`; with ``"auto"`` either set is accepted.
        Poses: ``tolerance`` (metres) and ``relative``: the view measuring a
        range shorter than the point's by more than ``max(tolerance, relative
        * range)`` at its nearest pixel hides the point (the same test decides
        which neighbours are on one surface for smoothing, and which point
        pairs the pose refinement keeps); ``smooth``: odd window (pixels) over
        which the reference range is averaged (1 = the raw points);
        ``refine`` (bool): refine each view's pose against the reference
        view's before mapping (the recorded poses need only be right to a few
        mm and tenths of a degree; ``"clouds"`` always refines); ``max_translation`` (metres) and
        ``max_rotation`` (degrees): a correction beyond either is refused.
        Homography: ``detector`` (a key of :data:`DETECTORS`),
        ``ratio`` (Lowe's test), ``threshold`` (MAGSAC++ inlier threshold,
        pixels), ``min_matches``, ``min_inliers``, ``contrast_sigma`` (pixels,
        scale of the local contrast normalisation of the log intensity the
        keypoints are found on), ``roi`` (``{"y": [y0, y1], "x": [x0, x1]}``,
        half-open sensor ranges: reference keypoints only there, to choose the
        plane a homography registers).

    Returns
    -------
    Dataset
        ``map_x``, ``map_y`` (view, y, x) float32 over the ``window``, pixels: sensor column and
        row in each view of the surface point seen by reference pixel (y, x);
        NaN where that view does not see it (outside its cropped grid, behind
        it, occluded, or, with poses, where the reference pixel has no valid
        point). The reference view maps to itself. Attrs: ``item``,
        ``method``, ``reference_view``, ``parameters`` (the options used) and
        ``diagnostics``: per view, for ``"homography"`` ``keypoints``,
        ``matches`` (after the ratio test), ``inliers``, ``rms`` (inlier
        reprojection, pixels) and ``homography`` (3 x 3, reference sensor
        coordinates to the view's); for ``"poses"`` ``mapped`` and
        ``occluded`` (fractions of the reference pixels mapped) and ``range_rms``
        (metres, measured minus projected range where mapped: checks the
        poses), and with ``refine`` ``correction`` (4 x 4: the refined
        camera-to-world pose is the recorded one times it; identity for the
        reference view), ``correction_mm`` and ``correction_deg`` (its
        translation and rotation angle), ``iterations``, ``pairs`` and
        ``texture_pairs`` (point-to-plane and texture residuals in the last
        iteration; the texture term needs 300), their robust standard
        deviations ``shape_deviation_mm`` and ``texture_deviation``, and
        ``constrained`` (pose directions the data fixed; 6 on a textured
        surface, 3 on a plane without usable texture); for ``"clouds"`` the
        same (``correction`` then corrects the coarse estimate) and ``pose``
        (4 x 4, the view's camera frame to the reference camera's),
        ``coarse_turn_deg``, ``coarse_response``, ``candidates`` and
        ``aligned_with`` (:func:`_pose_estimator`). For ``"poses"`` and
        ``"clouds"`` the attr ``camera_model``: ``source`` (``"given"``:
        intrinsics with distortion, or ``"estimated"`` from the clouds), ``fx``,
        ``fy``, ``cx``, ``cy``, ``distortion`` and ``residual_px`` (rms distance
        between the views' pixels and the model's projections of their points;
        with intrinsics without distortion also ``given_residual_px``, theirs).

    Raises
    ------
    RegistrationError
        Naming the item and view: too few matches or inliers (homography),
        poses requested but missing or not rigid, a pose refinement that does
        not converge or corrects a pose beyond ``max_translation`` /
        ``max_rotation``, clouds that do not fix a view's pose, a camera model
        fitted to the clouds that misses their pixels by more than 0.5 px,
        unknown reference view.
    ValueError, TypeError
        Unknown method or option, or non-contiguous ``y``/``x``.
    """
    if method not in METHODS:
        raise ValueError(f"method {method!r} is not known; expected one of {METHODS}")
    item = str(ingest.attrs.get("item", "?"))
    views = [str(view) for view in ingest["view"].values]
    reference = reference if reference is not None else ingest.attrs.get("reference_view", views[0])
    if reference not in views:
        raise RegistrationError(f"item {item!r}: reference view {reference!r} is not one of its views {views}")
    why_not = _poses_usable(ingest)
    chosen = method if method != "auto" else ("poses" if why_not is None else "clouds")
    if chosen == "poses" and why_not is not None:
        raise RegistrationError(
            f"item {item!r}: method='poses' needs a pose for every view, but {why_not}; method='clouds' "
            f"estimates the poses from the views' clouds"
        )
    grid = (_sensor_indices(ingest["x"], "x"), _sensor_indices(ingest["y"], "y"))
    part = _part(grid, window, item)
    build = {"poses": _pose_mapper, "clouds": partial(_pose_mapper, estimate=True), "homography": _homography_mapper}

    def maps_by(chosen: str):
        opts = _options(chosen, options, auto=method == "auto")
        mapper, described = build[chosen](ingest, views.index(reference), item, grid, opts, part)
        return opts, described, *zip(*(mapper(index) for index in range(len(views))))

    try:
        opts, described, cols, rows, diagnostics = maps_by(chosen)
    except RegistrationError as error:
        if not (method == "auto" and chosen == "clouds"):
            raise
        try:
            chosen, (opts, described, cols, rows, diagnostics) = "homography", maps_by("homography")
        except RegistrationError as second:
            raise RegistrationError(
                f"item {item!r} has no poses, and neither registration without them worked: from the clouds, {error}; "
                f"by homography, {second}"
            ) from None
    dims = ("view", "y", "x")
    return xr.Dataset(
        {
            "map_x": (dims, np.stack(cols).astype(np.float32), _MAP_ATTRS["map_x"]),
            "map_y": (dims, np.stack(rows).astype(np.float32), _MAP_ATTRS["map_y"]),
        },
        coords={"view": ingest["view"].values, "y": ingest["y"].values[part[0]], "x": ingest["x"].values[part[1]]},
        attrs={
            "item": item,
            "method": chosen,
            "reference_view": reference,
            "parameters": opts,
            "diagnostics": dict(zip(views, diagnostics)),
            **described,
        },
    )


def warp(data: xr.DataArray, maps: xr.Dataset, *, valid: xr.DataArray | None = None) -> xr.DataArray:
    """Resample every view of an image cube onto the reference grid.

    Parameters
    ----------
    data : (view, y, x) DataArray
        Any per-view image on the views' own (cropped) grids; ``y``/``x`` are
        contiguous sensor indices. NaN = missing. Numpy- or dask-backed.
    maps : Dataset
        From :func:`registration_maps`: ``map_x``, ``map_y`` (view, y, x),
        sensor positions; its views must equal ``data``'s.
    valid : (view, y, x) DataArray of bool, optional
        On ``data``'s grid; False pixels count as missing.

    Returns
    -------
    (view, y, x) DataArray
        On the maps' grid, float (``data``'s float dtype, else float64), attrs
        of ``data``: bilinear interpolation of each view at its map positions.
        NaN where the map is NaN, where the position lies outside the view's
        grid, and where any neighbour with a non-zero weight is missing (never
        extrapolated, no bleeding of missing pixels). Lazy on dask input.
    """
    return _warped([data], maps, valid)[0]


def _warped(images: list[xr.DataArray], maps: xr.Dataset, valid: xr.DataArray | None) -> list[xr.DataArray]:
    """:func:`warp` of images on one grid at once: their interpolation weights are computed once."""
    for name, arr in (*(("data", image) for image in images), ("valid", valid)):
        if arr is not None and set(arr.dims) != {"view", "y", "x"}:
            raise ValueError(f"warp: {name} must have dims (view, y, x), got {arr.dims}")
    data = images[0]
    if list(data["view"].values) != list(maps["view"].values):
        raise ValueError(
            f"warp: data views {list(data['view'].values)} differ from the maps' {list(maps['view'].values)}"
        )
    origin = (int(_sensor_indices(data["y"], "data y")[0]), int(_sensor_indices(data["x"], "data x")[0]))
    source = {"y": "source_y", "x": "source_x"}
    args = [*(image.rename(source) for image in images), maps["map_x"], maps["map_y"]]
    core = [*(["source_y", "source_x"] for _ in images), ["y", "x"], ["y", "x"]]
    if valid is not None:
        args.append(valid.rename(source))
        core.append(["source_y", "source_x"])
    out = xr.apply_ufunc(
        partial(_warp_kernel, origin=origin, count=len(images)),
        *args,
        input_core_dims=core,
        output_core_dims=[["layer", "y", "x"]],
        dask="parallelized",
        output_dtypes=[np.float64],
        dask_gufunc_kwargs={"allow_rechunk": True, "output_sizes": {"layer": len(images)}},
    )
    warped = []
    for layer, image in enumerate(images):
        dtype = image.dtype if np.issubdtype(image.dtype, np.floating) else np.float64
        one = out.isel(layer=layer).astype(dtype)
        one.attrs = dict(image.attrs)
        warped.append(one.transpose("view", "y", "x").rename(image.name))
    return warped


def register(ds: xr.Dataset, maps: xr.Dataset) -> xr.Dataset:
    """Warp an item's reflectance and AOI onto the reference grid.

    Parameters
    ----------
    ds : Dataset
        ``reflectance`` and ``aoi`` (view, y, x) (radians), NaN = missing, on
        the views' own grids; an optional ``valid`` (view, y, x) masks both.
    maps : Dataset
        From :func:`registration_maps` for the same item.

    Returns
    -------
    Dataset
        ``reflectance`` and ``aoi`` (view, y, x) on the reference grid (their
        attrs kept), ``valid`` (view, y, x) bool where both are finite, and
        ``map_x``, ``map_y``. Attrs: those of ``ds`` and of ``maps``.
    """
    missing = [name for name in ("reflectance", "aoi") if name not in ds]
    if missing:
        raise ValueError(f"register: the dataset lacks {missing}; it needs reflectance and aoi (view, y, x)")
    mask = ds["valid"] if "valid" in ds else None
    reflectance, aoi = _warped([ds["reflectance"], ds["aoi"]], maps, mask)
    valid = (np.isfinite(reflectance) & np.isfinite(aoi)).assign_attrs(
        long_name="registered pixel has reflectance and AOI"
    )
    # one Dataset built at once: each added variable would align the whole Dataset again
    variables = {"reflectance": reflectance, "aoi": aoi, "valid": valid, "map_x": maps["map_x"], "map_y": maps["map_y"]}
    return xr.Dataset(variables, attrs={**ds.attrs, **maps.attrs})


def registration_error(maps: xr.Dataset, u_ref: xr.DataArray, v_ref: xr.DataArray) -> xr.DataArray:
    """Registration error of maps against the truth of the synthetic camera.

    Parameters
    ----------
    maps : Dataset
        From :func:`registration_maps`.
    u_ref, v_ref : (view, y, x) DataArray, pixels
        Truth (``<campaign>-truth/<item>.zarr``): for every pixel of each view's
        grid (any contiguous sensor range, usually the full sensor), the sensor
        column and row in the reference view of the surface point it sees; NaN
        where the reference view does not see it.

    Returns
    -------
    (view, y, x) DataArray of float64, pixels
        Distance in the reference image between each reference pixel and the
        truth position of the point the maps send it to (truth interpolated
        bilinearly at the map position); NaN where the map or the truth is NaN.
    """
    u = warp(u_ref.astype(np.float64), maps)
    v = warp(v_ref.astype(np.float64), maps)
    error = np.hypot(u - maps["x"], v - maps["y"])
    return error.rename("registration_error").assign_attrs(units="pixel", long_name="registration error vs truth")
