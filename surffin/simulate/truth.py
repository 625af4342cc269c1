"""Ground truth of a synthetic campaign: what later stages are checked against.

``instrument.zarr`` holds the instrument function in the gauge E = 1 that a
perfect calibration on the wall finds (so ``I = scale_k f'(d, theta) R`` holds
exactly without noise) and the un-normalised coefficients (``I = gain f R``);
with residual systematics, also their factor tabulated over distance and angle
of incidence (then ``I = scale_k f'(d, theta) s(d, theta) R``).
Each item's store holds, on the full sensor grid of its reference view, the
surface's R0, n, AOI, distance, class label and face, and for every view the
AOI and where each pixel's surface point lies in the reference image (the
ground truth of co-registration).
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from surffin.simulate.camera import PinholeCamera, to_camera
from surffin.simulate.imperfections import systematic_factor
from surffin.simulate.instrument import TERMS, Instrument
from surffin.simulate.plan import Acquisition
from surffin.simulate.presets import Preset
from surffin.simulate.scene import Geometry, Scene

__all__ = ["instrument_truth", "item_truth", "reference_coordinates", "scene_truth_label"]

# A reference-view ray must meet its surface point within this distance for the
# point to count as visible in the reference view, metres.
_VISIBILITY_TOLERANCE = 1e-6
# Nodes of the systematic factor's table: distances (m) and angles of incidence (rad), fine
# enough for bilinear interpolation to stay within 1e-4 of the factor.
_SYSTEMATIC_DISTANCES = np.round(np.arange(0.05, 3.0 + 1e-9, 0.005), 6)
_SYSTEMATIC_AOIS = np.deg2rad(np.arange(0.0, 90.0 + 1e-9, 0.5))


def reference_coordinates(
    scene: Scene, camera: PinholeCamera, reference_pose: np.ndarray, geometry: Geometry
) -> tuple[np.ndarray, np.ndarray]:
    """Where the surface points a view sees lie in the reference view's image.

    Parameters
    ----------
    scene : Scene
    camera : PinholeCamera
    reference_pose : (4, 4) ndarray
        Camera-to-world pose of the reference view, metres.
    geometry : Geometry
        Noise-free rendering of the view.

    Returns
    -------
    u_ref, v_ref : (height, width) ndarray of float64
        Sub-pixel column and row in the reference image of each pixel's surface
        point; NaN where the pixel sees nothing, or its point falls outside the
        reference sensor or is hidden from the reference camera.
    """
    points = geometry.world_points().reshape(-1, 3)
    local = to_camera(points, reference_pose)
    u, v = camera.project(local)
    inside = (
        (geometry.face.reshape(-1) >= 0)
        & (local[:, 2] > 0)
        & (u >= -0.5)
        & (u <= camera.width - 0.5)
        & (v >= -0.5)
        & (v <= camera.height - 0.5)
    )
    origin = reference_pose[:3, 3]
    offset = points[inside] - origin
    span = np.linalg.norm(offset, axis=-1)
    distance, face, _, _ = scene.trace(origin, offset / span[:, None])
    visible = np.zeros_like(inside)
    visible[inside] = (face == geometry.face.reshape(-1)[inside]) & (np.abs(distance - span) <= _VISIBILITY_TOLERANCE)
    shape = camera.shape
    return np.where(visible, u, np.nan).reshape(shape), np.where(visible, v, np.nan).reshape(shape)


def _attrs(units: str, long_name: str, **extra) -> dict:
    return {"units": units, "long_name": long_name, **extra}


def _sensor_coords(camera: PinholeCamera) -> dict[str, np.ndarray]:
    return {"y": np.arange(camera.height), "x": np.arange(camera.width)}


def scene_truth_label(reference: Geometry, margin: float) -> np.ndarray:
    """Truth labels of a scene: specimen top pixels away from the edges.

    Parameters
    ----------
    reference : Geometry
        Noise-free rendering of the scene's reference view.
    margin : float, metres
        Pixels whose surface point is closer than this to an edge of its face
        (in-plane) are left out: they mix surfaces, and their AOI and features
        come from windows straddling the edge.

    Returns
    -------
    (height, width) ndarray of int16
        Class index, -1 elsewhere.
    """
    return np.where(reference.edge_distance >= margin, reference.label, -1).astype(np.int16)


def item_truth(
    acquisition: Acquisition,
    preset: Preset,
    reference: Geometry,
    aoi: np.ndarray,
    u_ref: np.ndarray,
    v_ref: np.ndarray,
) -> xr.Dataset:
    """Build the truth store of a specimen or scene.

    Parameters
    ----------
    acquisition : Acquisition
        The item's faces, poses and view names.
    preset : Preset
    reference : Geometry
        Noise-free rendering of the reference view (``acquisition.reference``).
    aoi : (view, height, width) ndarray, radians
        Angle of incidence in each view, on that view's own grid.
    u_ref, v_ref : (view, height, width) ndarray, pixels
        :func:`reference_coordinates` of each view.

    Returns
    -------
    Dataset
        ``R0``, ``n``, ``aoi`` (rad), ``distance`` (m), ``label`` (int16, -1 off
        specimen top faces, no edge margin), ``surface`` (int16 face index, -1
        none; attr ``surfaces`` names the faces), ``edge_distance`` (m) on
        (y, x); ``aoi_view``, ``u_ref``, ``v_ref`` on (view, y, x); ``pose``
        (view, row, col), camera-to-world in metres.
    """
    image = ("y", "x")
    cube = ("view", "y", "x")
    classes = preset.classes
    label_attrs = {"flag_values": list(range(len(classes))), "flag_meanings": " ".join(classes)}
    faces = [face.name for face in acquisition.faces]
    return xr.Dataset(
        {
            "R0": (image, reference.R0, _attrs("1", "reflectance at normal incidence")),
            "n": (image, reference.n, _attrs("1", "scattering coefficient")),
            "aoi": (image, reference.aoi, _attrs("rad", "angle of incidence in the reference view")),
            "distance": (image, reference.distance, _attrs("m", "distance from the reference camera")),
            "label": (image, reference.label, _attrs("1", "class index on specimen top faces", **label_attrs)),
            "surface": (image, reference.face.astype(np.int16), _attrs("1", "index of the face seen", surfaces=faces)),
            "edge_distance": (
                image,
                reference.edge_distance,
                _attrs("m", "in-plane distance of the surface point from the nearest edge of its face"),
            ),
            "aoi_view": (cube, aoi, _attrs("rad", "angle of incidence in each view")),
            "u_ref": (cube, u_ref, _attrs("pixel", "column of the surface point in the reference view")),
            "v_ref": (cube, v_ref, _attrs("pixel", "row of the surface point in the reference view")),
            "pose": (("view", "row", "col"), np.stack(acquisition.poses), _attrs("m", "camera-to-world pose")),
        },
        coords={"view": acquisition.stems, **_sensor_coords(preset.camera)},
        attrs={
            "item": acquisition.name,
            "kind": acquisition.kind,
            "reference_view": acquisition.reference_stem,
            "classes": list(classes),
            "label_margin": preset.label_margin,
        },
    )


def instrument_truth(instrument: Instrument, preset: Preset, systematics: float = 0.0) -> xr.Dataset:
    """Build the instrument truth store.

    Parameters
    ----------
    instrument : Instrument
    preset : Preset
        Supplies the wall's and the reference panel's reflectance.
    systematics : float, optional
        Amplitude of the residual systematics the views were rendered with
        (:attr:`~surffin.simulate.imperfections.Imperfections.systematics`); 0: none.

    Returns
    -------
    Dataset
        ``coef`` (term, y, x): A', B', C', D', E' = 1 of
        :meth:`Instrument.calibration`; ``coef_raw`` (term, y, x): A..E with
        ``I = gain f R``; with systematics, ``systematic`` (correction_distance,
        correction_aoi): their factor :func:`~surffin.simulate.imperfections.systematic_factor`
        on a grid of distances 0.05-3 m and angles 0-90 deg, in the layout of a
        calibration's ``correction`` (``I = scale_k f' s R``); attrs ``scale_k``,
        ``gain``, ``rho_wall``, ``rho_reference``, ``systematics``.
    """
    coef, scale_k = instrument.calibration(preset.wall.R0)
    dims = ("term", "y", "x")
    ds = xr.Dataset(
        {
            "coef": (dims, coef, _attrs("1", "instrument function coefficients, gauge E = 1: I = scale_k f R")),
            "coef_raw": (dims, instrument.coef, _attrs("1", "instrument function coefficients: I = gain f R")),
        },
        coords={"term": list(TERMS), **_sensor_coords(preset.camera)},
        attrs={
            "scale_k": scale_k,
            "gain": instrument.gain,
            "rho_wall": preset.wall.R0,
            "rho_reference": preset.reference.R0,
            "systematics": float(systematics),
            "model": "f = (A + B/d^2)(C theta^2 + D theta + E), d in m, theta in rad",
        },
    )
    if not systematics:
        return ds
    table = systematic_factor(_SYSTEMATIC_DISTANCES[:, None], _SYSTEMATIC_AOIS[None, :], systematics)
    return ds.assign(
        systematic=xr.DataArray(
            table,
            dims=("correction_distance", "correction_aoi"),
            coords={
                "correction_distance": ("correction_distance", _SYSTEMATIC_DISTANCES, _attrs("m", "distance")),
                "correction_aoi": ("correction_aoi", _SYSTEMATIC_AOIS, _attrs("rad", "angle of incidence")),
            },
            attrs=_attrs(
                "1",
                "residual instrument systematics: I = scale_k f s R",
                outside="the nodes' range covers every rendered view; clamped to the edge beyond it",
            ),
        )
    )
