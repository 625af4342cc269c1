"""The camera model: pinhole with Brown-Conrady lens distortion, and its estimate from organized clouds.

A point ``(x, y, z)`` of the camera frame (OpenCV axes) is seen at the sensor
column and row

    a, b = x / z, y / z,  r2 = a^2 + b^2
    radial = (1 + k1 r2 + k2 r2^2 + k3 r2^3) / (1 + k4 r2 + k5 r2^2 + k6 r2^3)
    col = fx (a radial + 2 p1 a b + p2 (r2 + 2 a^2)) + cx
    row = fy (b radial + p1 (r2 + 2 b^2) + 2 p2 a b) + cy

OpenCV's model (``cv2.projectPoints``) with the coefficients ``[k1, k2, p1, p2[,
k3[, k4, k5, k6]]]`` of ``camera.intrinsics.distortion`` in campaign.yaml. An
organized cloud holds at every valid pixel the point its ray met, so every pixel
is an exact pair of ``(x / z, y / z)`` and its sensor position (the distorted
image of its ray): when a campaign gives no intrinsics, or no distortion,
:func:`fit_camera_model` estimates the model from the clouds themselves, and
:func:`model_residual` checks a model against them.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from functools import cached_property, lru_cache

import numpy as np

__all__ = ["CameraModel", "fit_camera_model", "model_residual"]

_TERMS = 8  # k1, k2, p1, p2, k3, k4, k5, k6
_FITTED = 5  # the distortion terms fitted by fit_camera_model: k1, k2, p1, p2, k3
_SAMPLES = 20000  # about this many pixels (a regular subsample of all views) enter a fit or a residual
_FOLD_SCAN = np.linspace(0.0, 4.0, 4001)[1:]  # r2 (normalised) scanned for the fold of the radial distortion


@dataclass(frozen=True)
class CameraModel:
    """Pinhole intrinsics and OpenCV distortion coefficients of a camera.

    Attributes
    ----------
    fx, fy, cx, cy : float
        Pixels, of the distorted model: the sensor position is
        ``fx * x_distorted + cx`` (column), ``fy * y_distorted + cy`` (row).
    distortion : tuple of float
        ``(k1, k2, p1, p2[, k3[, k4, k5, k6]])`` in OpenCV's order; empty: none.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, ...] = ()

    @classmethod
    def from_intrinsics(cls, intrinsics: Mapping) -> CameraModel:
        """Make the model of ``camera.intrinsics``: ``fx``, ``fy``, ``cx``, ``cy`` and optional ``distortion``."""
        distortion = tuple(float(value) for value in intrinsics.get("distortion") or ())
        if len(distortion) not in (0, 4, 5, 8):
            raise ValueError(f"distortion must have 4, 5 or 8 coefficients (OpenCV order), got {distortion!r}")
        return cls(*(float(intrinsics[key]) for key in ("fx", "fy", "cx", "cy")), distortion)

    def as_dict(self) -> dict:
        """Return ``{"fx", "fy", "cx", "cy", "distortion"}`` (as in campaign.yaml; distortion a list)."""
        return {"fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy, "distortion": list(self.distortion)}

    def coefficients(self) -> np.ndarray:
        """Return the distortion coefficients padded with zeros to all eight terms (8,)."""
        return np.array(self._terms)

    @cached_property
    def _terms(self) -> tuple[np.float64, ...]:
        """The eight coefficients of :meth:`coefficients`, padded once per model (projections use them often)."""
        return tuple(np.pad(np.asarray(self.distortion, dtype=np.float64), (0, _TERMS - len(self.distortion))))

    def fold(self) -> float:
        """Return the largest ``r2 = (x / z)^2 + (y / z)^2`` up to which the radial distortion grows with r.

        Beyond it a polynomial lens model folds back (points far outside the
        field of view would land on the sensor); :meth:`project` sends them
        nowhere. ``inf`` without distortion or when no fold is found up to
        ``r2 = 4`` (63 deg off the axis).
        """
        return _fold(self._terms)

    def project(self, points: np.ndarray, origin: tuple[int, int] = (0, 0)) -> tuple[np.ndarray, np.ndarray]:
        """Return the column and row where camera-frame points are seen.

        Parameters
        ----------
        points : (..., 3) ndarray, camera frame
        origin : (row, col)
            Positions on a grid whose first pixel is this sensor pixel; (0, 0):
            sensor positions.

        Returns
        -------
        col, row : (...) ndarray of float64
            NaN at or behind the camera, for NaN points and beyond the fold of
            the lens model (:meth:`fold`).
        """
        a, b, usable = self._normalised(points)
        xd, yd = self._distorted(a, b)
        col = np.where(usable, self.fx * xd + (self.cx - origin[1]), np.nan)
        row = np.where(usable, self.fy * yd + (self.cy - origin[0]), np.nan)
        return col, row

    def jacobian(self, points: np.ndarray) -> np.ndarray:
        """Return the derivative of (column, row) with respect to the point, (..., 2, 3); NaN where not projected."""
        a, b, by_a, by_b, inverse = self._derivatives(points)
        # a = x / z, b = y / z: da/dpoint = (1, 0, -a) / z, db/dpoint = (0, 1, -b) / z
        out = np.empty((*a.shape, 2, 3))
        for axis, (da, db) in enumerate(zip(by_a, by_b)):
            np.multiply(da, inverse, out=out[..., axis, 0])
            np.multiply(db, inverse, out=out[..., axis, 1])
            np.multiply(-(da * a + db * b), inverse, out=out[..., axis, 2])
        return out

    def gradient(self, points: np.ndarray, d_col: np.ndarray, d_row: np.ndarray) -> np.ndarray:
        """Return the derivative (..., 3) by the point of an image at its projection (chain rule).

        ``d_col``, ``d_row``: the image's derivatives by column and row there. The values of
        ``d_col * jacobian[..., 0, :] + d_row * jacobian[..., 1, :]`` (:meth:`jacobian`), without
        the (..., 2, 3) array.
        """
        a, b, (col_a, row_a), (col_b, row_b), inverse = self._derivatives(points)
        d_col, d_row = (np.asarray(value, dtype=np.float64) for value in (d_col, d_row))
        # the products and sums of jacobian's entries (their operations, in their order), in place
        parts = []
        for image, by_a, by_b in ((d_col, col_a, col_b), (d_row, row_a, row_b)):
            # d_image * (-(by_a * a + by_b * b) * inverse): its part of the derivative by z
            along = by_a * a
            along += by_b * b
            along = -along
            along *= inverse
            along *= image
            by_a *= inverse
            by_a *= image
            by_b *= inverse
            by_b *= image
            parts.append((by_a, by_b, along))
        out = np.empty((*a.shape, 3))
        for axis, (by_col, by_row) in enumerate(zip(*parts)):
            np.add(by_col, by_row, out=out[..., axis])
        return out

    def _derivatives(self, points: np.ndarray):
        """Return what :meth:`jacobian` and :meth:`gradient` are made of.

        ``a``, ``b`` (:meth:`_normalised`), the derivatives (pixels) of (column, row) by ``a``
        and by ``b``, and ``1 / z`` (NaN where not projected). The derivatives are new float64
        arrays (:meth:`gradient` scales them in place).
        """
        a, b, usable = self._normalised(points)
        k1, k2, p1, p2, k3, k4, k5, k6 = self._terms
        r2 = a * a + b * b
        numerator, denominator = _polynomial(r2, k1, k2, k3), _polynomial(r2, k4, k5, k6)
        radial = numerator if k4 == k5 == k6 == 0 else numerator / denominator  # as _radial
        slope = _radial_slope(r2, numerator, denominator, k1, k2, k3, k4, k5, k6)
        slope /= denominator**2
        # the derivatives of the distorted coordinates by a and b (d xd / db = d yd / da), scaled to pixels:
        # mixed = 2 a b slope + 2 p1 a + 2 p2 b, (radial + 2 a a slope + 2 p1 b + 6 p2 a) fx and
        # (radial + 2 b b slope + 6 p1 b + 2 p2 a) fy, each operation as written, in place where its
        # result has the buffer's type (float64, of the coefficients)
        double_a = 2 * a
        mixed = double_a * b * slope
        mixed += 2 * p1 * a
        mixed += 2 * p2 * b
        fx, fy = np.float64(self.fx), np.float64(self.fy)  # float64 whatever the points' type
        along = []
        for out, first, second, scale in (
            (double_a * a * slope, 2 * p1 * b, 6 * p2 * a, fx),
            (2 * b * b * slope, 6 * p1 * b, 2 * p2 * a, fy),
        ):
            out += radial  # radial + ..., in either order the same sum
            out += first
            out += second
            out *= scale
            along.append(out)
        with np.errstate(divide="ignore", invalid="ignore"):
            inverse = np.where(usable, 1.0 / points[..., 2], np.nan)
        return a, b, (along[0], mixed * fy), (mixed * fx, along[1]), inverse

    def _normalised(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return ``x / z``, ``y / z`` (0 where unusable) and where the projection is defined."""
        depth = points[..., 2]
        fold = self.fold() if self.distortion else np.inf
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            usable = depth > 0
            a, b = points[..., 0] / depth, points[..., 1] / depth
            if fold < np.inf:
                usable &= a * a + b * b <= fold  # so a and b are finite
            else:
                usable &= np.isfinite(a) & np.isfinite(b)
        return np.where(usable, a, 0.0), np.where(usable, b, 0.0), usable

    def _distorted(self, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return the distorted normalised coordinates of undistorted ones."""
        if not self.distortion:
            return a, b
        k1, k2, p1, p2, k3, k4, k5, k6 = self._terms
        r2 = a * a + b * b
        radial = _radial(r2, k1, k2, k3, k4, k5, k6)
        # xd = a radial + 2 p1 a b + p2 (r2 + 2 a a) and yd = b radial + p1 (r2 + 2 b b) + 2 p2 a b, each
        # operation as written, in place where its result has the buffer's type (the float64 of the coefficients)
        xd, yd = a * radial, b * radial
        xd += _mixed(p1, a, b)
        xd += p2 * _plus_double_square(r2, a)
        yd += p1 * _plus_double_square(r2, b)
        yd += _mixed(p2, a, b)
        return xd, yd


def _mixed(coefficient, a, b):
    """Return ``2 * coefficient * a * b`` (in one buffer)."""
    out = 2 * coefficient * a
    out *= b
    return out


def _plus_double_square(r2, value):
    """Return ``r2 + 2 * value * value`` (in one buffer; ``r2`` of ``value``'s type)."""
    out = 2 * value
    out *= value
    out += r2
    return out


def _polynomial(r2, c1, c2, c3):
    """Return ``1 + r2 * (c1 + r2 * (c2 + r2 * c3))`` (float64 coefficients), each operation in one buffer.

    The radial factor of the distortion is ``_polynomial(r2, k1, k2, k3) / _polynomial(r2, k4, k5, k6)``.
    """
    out = r2 * c3
    out += c2
    out *= r2
    out += c1
    out *= r2
    out += 1
    return out


def _radial(r2, k1, k2, k3, k4, k5, k6):
    """Return the radial factor of the distortion at ``r2``."""
    numerator = _polynomial(r2, k1, k2, k3)
    if k4 == k5 == k6 == 0:  # a denominator of 1 divides nothing (finite r2): fewer passes over the points
        return numerator
    return numerator / _polynomial(r2, k4, k5, k6)


@lru_cache(maxsize=64)
def _fold(coefficients: tuple[float, ...]) -> float:
    """Return :meth:`CameraModel.fold` of all eight distortion coefficients (cached: a scan of the radial factor)."""
    k1, k2, _, _, k3, k4, k5, k6 = coefficients
    r2 = _FOLD_SCAN
    numerator, denominator = _polynomial(r2, k1, k2, k3), _polynomial(r2, k4, k5, k6)
    # d(r radial)/dr = radial + 2 r2 d(radial)/d(r2) > 0, and the denominator keeps its sign
    slope = _radial_slope(r2, numerator, denominator, k1, k2, k3, k4, k5, k6)
    grows = (numerator * denominator + 2 * r2 * slope > 0) & (denominator > 0)
    stops = np.flatnonzero(~grows)
    return float(r2[stops[0]]) if stops.size else float("inf")


def _radial_slope(r2, numerator, denominator, k1, k2, k3, k4, k5, k6):
    """Return the derivative of the radial factor by ``r2``, times its denominator squared.

    ``numerator`` and ``denominator``: the radial factor's at ``r2`` (:func:`_polynomial`).
    """
    # (k1 + r2 (2 k2 + 3 r2 k3)) denominator - numerator (k4 + r2 (2 k5 + 3 r2 k6)), in place in float64 buffers
    thrice = 3 * r2
    terms = []
    for constant, linear, square, factor in ((k1, k2, k3, denominator), (k4, k5, k6, numerator)):
        out = thrice * square
        out += 2 * linear
        out *= r2
        out += constant
        out *= factor
        terms.append(out)
    terms[0] -= terms[1]
    return terms[0]


def _pairs(xyz: np.ndarray, columns: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return the valid points (N, 3) of a regular subsample of organized clouds and their pixels (N, 2)."""
    stride = max(1, round(np.sqrt(xyz[..., 0].size / _SAMPLES)))
    points = xyz[..., ::stride, ::stride, :]
    cols, rws = np.meshgrid(columns[::stride], rows[::stride])
    sensor = np.broadcast_to(np.stack([cols, rws], axis=-1), (*points.shape[:-1], 2))
    with np.errstate(invalid="ignore"):
        known = points[..., 2] > 0
    for axis in range(3):  # np.isfinite(points).all(axis=-1), ~3x faster
        known &= np.isfinite(points[..., axis])
    return points[known].astype(np.float64, copy=False), sensor[known].astype(np.float64)


def model_residual(model: CameraModel, xyz: np.ndarray, columns: np.ndarray, rows: np.ndarray) -> float:
    """Return the rms (pixels) of the model's projections of organized clouds' points from their pixels.

    Parameters
    ----------
    model : CameraModel
    xyz : (..., h, w, 3) ndarray
        Organized clouds, camera frame; NaN = invalid.
    columns, rows : (w,), (h,) ndarray of int
        Sensor indices of the clouds' grid.

    Returns
    -------
    float
        Over a regular subsample of about 20000 valid pixels; NaN when none.
    """
    return _residual(model, *_pairs(xyz, columns, rows))


def _residual(model: CameraModel, points: np.ndarray, sensor: np.ndarray) -> float:
    """Return :func:`model_residual` of the pairs of :func:`_pairs`."""
    col, row = model.project(points)
    return float(np.sqrt(np.mean((col - sensor[:, 0]) ** 2 + (row - sensor[:, 1]) ** 2))) if len(points) else np.nan


def fit_camera_model(xyz: np.ndarray, columns: np.ndarray, rows: np.ndarray) -> tuple[CameraModel, float]:
    """Estimate the camera model from organized clouds: each valid pixel pairs ``(x / z, y / z)`` with its position.

    ``fx``, ``cx`` (and ``fy``, ``cy``) start from a linear least-squares fit of
    the pinhole; then ``fx``, ``fy``, ``cx``, ``cy`` and the distortion ``k1, k2,
    p1, p2, k3`` are fitted by nonlinear least squares
    (``scipy.optimize.least_squares``) over a regular subsample of about 20000
    valid pixels of all views.

    Parameters
    ----------
    xyz : (..., h, w, 3) ndarray
        Organized clouds, camera frame (any unit); NaN = invalid.
    columns, rows : (w,), (h,) ndarray of int
        Sensor indices of the clouds' grid.

    Returns
    -------
    model : CameraModel
        With five distortion coefficients.
    residual : float
        Rms of the fit, pixels.

    Raises
    ------
    ValueError
        Fewer than 50 valid pixels.
    """
    points, sensor = _pairs(xyz, columns, rows)
    if len(points) < 50:
        raise ValueError(f"only {len(points)} valid pixels: too few to estimate the camera model")
    normalised = points[:, :2] / points[:, 2:]
    start = []
    for axis in (0, 1):
        design = np.stack([normalised[:, axis], np.ones(len(points))], axis=-1)
        start.append(np.linalg.lstsq(design, sensor[:, axis], rcond=None)[0])
    (fx, cx), (fy, cy) = start

    def model_of(parameters: np.ndarray) -> CameraModel:
        return CameraModel(*(float(value) for value in parameters[:4]), tuple(float(value) for value in parameters[4:]))

    distorted = {}  # the distorted coordinates of the last distortion coefficients tried
    # contiguous copies of the columns: the residuals pass over them ~30 times
    undistorted, pixels = ([np.ascontiguousarray(column) for column in pairs.T] for pairs in (normalised, sensor))
    count = len(points)

    def residuals(parameters: np.ndarray) -> np.ndarray:
        # the finite differences' steps in fx, fy, cx and cy leave the distorted coordinates as they are
        key = parameters[4:].tobytes()
        if key not in distorted:
            distorted.clear()
            # unguarded by the fold: a trial model may fold inside the data
            distorted[key] = model_of(parameters)._distorted(*undistorted)
        # f * distorted + c - pixel of the columns, then of the rows
        out = np.empty(2 * count)
        for axis, (coordinate, pixel) in enumerate(zip(distorted[key], pixels)):
            part = out[axis * count : (axis + 1) * count]
            np.multiply(coordinate, parameters[axis], out=part)
            part += parameters[axis + 2]
            part -= pixel
        return out

    from scipy.optimize import least_squares  # 0.4 s to import: kept out of snakemake's start

    fit = least_squares(residuals, np.array([fx, fy, cx, cy, *np.zeros(_FITTED)]), x_scale="jac", method="lm")
    model = model_of(fit.x)
    return model, _residual(model, points, sensor)
