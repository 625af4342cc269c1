"""Pinhole camera geometry of the synthetic depth camera.

The camera frame has OpenCV axes (x right, y down, z forward); a pixel (row v,
column u) looks along ``((u - cx) / fx, (v - cy) / fy, 1)`` with the principal
point at the centre of the sensor. A pose is the camera-to-world transform
``T`` (4, 4) with ``world = T @ [x, y, z, 1]``, translation in metres.

The world frame of the simulator: the wall or board is the plane Z = 0, X to the
right, Y down, Z into the wall, so that surfaces face the camera along -Z.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["PinholeCamera", "look_at_pose", "to_camera", "world_rays"]

_UP_HINT = np.array([0.0, 1.0, 0.0])


@dataclass(frozen=True)
class PinholeCamera:
    """Pinhole intrinsics of a sensor with the principal point at its centre.

    Attributes
    ----------
    width, height : int
        Sensor columns and rows.
    fx, fy : float
        Focal lengths, pixels.
    """

    width: int
    height: int
    fx: float
    fy: float

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

    def intrinsics(self) -> dict[str, float]:
        """``{"fx", "fy", "cx", "cy"}`` as written to campaign.yaml."""
        return {"fx": float(self.fx), "fy": float(self.fy), "cx": self.cx, "cy": self.cy}

    def rays(self) -> np.ndarray:
        """Compute the unit viewing rays of all pixels.

        Returns
        -------
        (height, width, 3) ndarray of float64
            Camera frame; ``rays[v, u]`` is the direction of pixel (row v, column u).
        """
        u = (np.arange(self.width) - self.cx) / self.fx
        v = (np.arange(self.height) - self.cy) / self.fy
        rays = np.empty((self.height, self.width, 3))
        rays[..., 0] = u[None, :]
        rays[..., 1] = v[:, None]
        rays[..., 2] = 1.0
        return rays / np.linalg.norm(rays, axis=-1, keepdims=True)

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Image coordinates of points in the camera frame.

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
        return self.fx * points[..., 0] / z + self.cx, self.fy * points[..., 1] / z + self.cy


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
