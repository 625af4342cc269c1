"""Pinhole camera geometry of the synthetic depth camera, with optional lens distortion.

The camera frame has OpenCV axes (x right, y down, z forward); a pixel (row v,
column u) looks along ``(x, y, 1)`` with the principal point at the centre of the
sensor: without distortion ``x = (u - cx) / fx``, ``y = (v - cy) / fy``; with it,
the undistorted normalised coordinates whose distorted image (OpenCV's model,
:func:`distort`) is ``((u - cx) / fx, (v - cy) / fy)``. A pose is the camera-to-world transform
``T`` (4, 4) with ``world = T @ [x, y, z, 1]``, translation in metres.

The world frame of the simulator: the wall or board is the plane Z = 0, X to the
right, Y down, Z into the wall, so that surfaces face the camera along -Z.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["PinholeCamera", "distort", "look_at_pose", "to_camera", "undistort", "world_rays"]

_UP_HINT = np.array([0.0, 1.0, 0.0])
# Fixed-point iterations of undistort: stop when no coordinate moves more than this, or after so many.
_UNDISTORT_TOLERANCE = 1e-13
_UNDISTORT_ITERATIONS = 100


def _coefficients(distortion) -> np.ndarray:
    """OpenCV's 4, 5 or 8 distortion coefficients padded to 8: k1, k2, p1, p2, k3, k4, k5, k6."""
    padded = np.zeros(8)
    padded[: len(distortion)] = distortion
    return padded


def _lens(x: np.ndarray, y: np.ndarray, distortion) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Radial factor and tangential shifts of OpenCV's model at undistorted coordinates."""
    k1, k2, p1, p2, k3, k4, k5, k6 = _coefficients(distortion)
    r2 = x * x + y * y
    radial = (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1.0 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    shift_x = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    shift_y = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return radial, shift_x, shift_y


def distort(x: np.ndarray, y: np.ndarray, distortion) -> tuple[np.ndarray, np.ndarray]:
    """Apply OpenCV's radial-tangential lens model to normalised coordinates.

    Parameters
    ----------
    x, y : ndarray
        Undistorted normalised coordinates (``X / Z``, ``Y / Z``).
    distortion : sequence of float
        ``(k1, k2, p1, p2[, k3[, k4, k5, k6]])``.

    Returns
    -------
    x_d, y_d : ndarray of float64
        ``x r + 2 p1 x y + p2 (r^2 + 2 x^2)``, ``y r + p1 (r^2 + 2 y^2) + 2 p2 x y``
        with ``r = (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)``.
    """
    radial, shift_x, shift_y = _lens(x, y, distortion)
    return x * radial + shift_x, y * radial + shift_y


def undistort(x_d: np.ndarray, y_d: np.ndarray, distortion) -> tuple[np.ndarray, np.ndarray]:
    """Invert :func:`distort` by fixed-point iteration (as OpenCV's ``undistortPoints``, to convergence).

    Parameters
    ----------
    x_d, y_d : ndarray
        Distorted normalised coordinates.
    distortion : sequence of float
        ``(k1, k2, p1, p2[, k3[, k4, k5, k6]])``, a lens the iteration converges
        for over the coordinates given (moderate distortion).

    Returns
    -------
    x, y : ndarray of float64
        Undistorted normalised coordinates.

    Raises
    ------
    ValueError
        The iteration does not converge.
    """
    x, y = np.array(x_d, dtype=np.float64), np.array(y_d, dtype=np.float64)
    for _ in range(_UNDISTORT_ITERATIONS):
        radial, shift_x, shift_y = _lens(x, y, distortion)
        x_new, y_new = (x_d - shift_x) / radial, (y_d - shift_y) / radial
        moved = max(np.max(np.abs(x_new - x), initial=0.0), np.max(np.abs(y_new - y), initial=0.0))
        x, y = x_new, y_new
        if moved <= _UNDISTORT_TOLERANCE:
            return x, y
    raise ValueError(f"lens distortion {tuple(distortion)} cannot be inverted over the sensor; use a milder one")


@dataclass(frozen=True)
class PinholeCamera:
    """Pinhole intrinsics of a sensor with the principal point at its centre, and its lens distortion.

    Attributes
    ----------
    width, height : int
        Sensor columns and rows.
    fx, fy : float
        Focal lengths, pixels.
    distortion : tuple of float
        OpenCV ``(k1, k2, p1, p2[, k3[, k4, k5, k6]])``; empty: an ideal lens.
    """

    width: int
    height: int
    fx: float
    fy: float
    distortion: tuple[float, ...] = ()

    @property
    def cx(self) -> float:
        """Principal point column, ``(width - 1) / 2``."""
        return (self.width - 1) / 2.0

    @property
    def cy(self) -> float:
        """Principal point row, ``(height - 1) / 2``."""
        return (self.height - 1) / 2.0

    @property
    def shape(self) -> tuple[int, int]:
        """``(height, width)``."""
        return (self.height, self.width)

    def intrinsics(self) -> dict:
        """``{"fx", "fy", "cx", "cy"}`` as written to campaign.yaml, and ``distortion`` (a list) when there is one."""
        pinhole = {"fx": float(self.fx), "fy": float(self.fy), "cx": self.cx, "cy": self.cy}
        return {**pinhole, "distortion": [float(k) for k in self.distortion]} if self.distortion else pinhole

    def rays(self) -> np.ndarray:
        """Compute the unit viewing rays of all pixels.

        Returns
        -------
        (height, width, 3) ndarray of float64
            Camera frame; ``rays[v, u]`` is the direction of pixel (row v, column u).
        """
        rays = np.empty((self.height, self.width, 3))
        rays[..., 0] = ((np.arange(self.width) - self.cx) / self.fx)[None, :]
        rays[..., 1] = ((np.arange(self.height) - self.cy) / self.fy)[:, None]
        rays[..., 2] = 1.0
        if self.distortion:
            rays[..., 0], rays[..., 1] = undistort(rays[..., 0], rays[..., 1], self.distortion)
        return rays / np.linalg.norm(rays, axis=-1, keepdims=True)

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Image coordinates of points in the camera frame, through the lens distortion if any.

        Parameters
        ----------
        points : (..., 3) ndarray, metres
            Camera frame; z must be positive for a meaningful result.

        Returns
        -------
        u, v : (...) ndarray of float64
            Sub-pixel column and row.
        """
        points = np.asarray(points, dtype=np.float64)
        z = points[..., 2]
        if not self.distortion:
            return self.fx * points[..., 0] / z + self.cx, self.fy * points[..., 1] / z + self.cy
        x, y = distort(points[..., 0] / z, points[..., 1] / z, self.distortion)
        return self.fx * x + self.cx, self.fy * y + self.cy


def look_at_pose(target, distance: float, tilt: float, azimuth: float, roll: float = 0.0) -> np.ndarray:
    """Camera-to-world pose of a camera looking at a point of a wall facing -Z.

    The camera sits at ``target + distance * (sin a cos phi, sin a sin phi, -cos a)``
    for tilt ``a`` (from the wall normal) and azimuth ``phi``, its optical axis
    through ``target``, its image y axis as close to world +Y as the view
    direction allows, then turned by ``roll`` about the optical axis.

    Parameters
    ----------
    target : (3,) array_like, metres
        World point on the optical axis.
    distance : float, metres
        From the camera centre to ``target``.
    tilt, azimuth, roll : float, radians
        ``tilt`` must stay well below pi/2 (the construction needs the optical
        axis not parallel to world Y).

    Returns
    -------
    (4, 4) ndarray of float64
        Camera-to-world transform, translation in metres.
    """
    target = np.asarray(target, dtype=np.float64)
    offset = np.array([np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth), -np.cos(tilt)])
    centre = target + distance * offset
    z_axis = -offset
    x_axis = np.cross(_UP_HINT, z_axis)
    x_axis /= np.linalg.norm(x_axis)
    y_axis = np.cross(z_axis, x_axis)
    cos_r, sin_r = np.cos(roll), np.sin(roll)
    pose = np.eye(4)
    pose[:3, 0] = cos_r * x_axis + sin_r * y_axis
    pose[:3, 1] = -sin_r * x_axis + cos_r * y_axis
    pose[:3, 2] = z_axis
    pose[:3, 3] = centre
    return pose


def world_rays(rays: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Rotate camera-frame directions into the world frame.

    Parameters
    ----------
    rays : (..., 3) ndarray
        Directions in the camera frame.
    pose : (4, 4) ndarray
        Camera-to-world transform.

    Returns
    -------
    (..., 3) ndarray of float64
        The same directions in the world frame.
    """
    return rays @ pose[:3, :3].T


def to_camera(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Express world points in the frame of a camera.

    Parameters
    ----------
    points : (..., 3) ndarray, metres
        World frame.
    pose : (4, 4) ndarray
        Camera-to-world transform of that camera.

    Returns
    -------
    (..., 3) ndarray of float64, metres
        Camera frame.
    """
    return (points - pose[:3, 3]) @ pose[:3, :3]
