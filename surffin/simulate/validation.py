"""Validation campaigns: synthetic designs that differ from the ``paper`` preset.

The ``paper`` preset follows the paper's specimens and acquisition; a method
tuned on it may not hold elsewhere. These campaigns come from an independent
description of what a camera model produced: classes whose mean n differ by only
7-9 % and whose R0 ranges overlap (separated by n plus spatial variability),
within-class spreads like the paper's (R0 7-10 %, n 3-4 % over 5-95 % of the
smoothed pixels; :func:`~surffin.simulate.presets.class_material`), 48 wall views
(distances 0.30-1.00 m, tilts 0-30 deg) and 3 panel views, specimens 20 x 20 cm,
10-20 mm thick on a darker board, seen at 0.45 m with centre angles of incidence
1.5, 11, 20, 29 and 39 deg, scenes 15 cm farther at angles about 5 deg apart
from those with the specimens turned by 90/180/270 deg, intensity noise 2 % plus
a floor of 5 counts, and range noise 0.9 mm at 1500 counts growing as
``1/sqrt(I)`` up to 3 mm on weak returns. None of the paper's fitted numbers
nor its roughness relation goes in; the specimens carry no roughness.

Every campaign uses the paper's camera (640 x 480, fx 565, fy 579) and no
repeat calibration set. The campaigns of :data:`IMPERFECT` are seen by a real
camera: ``val-plaster`` with each of its imperfections alone, all together, and
raw files without poses or intrinsics, and ``val-curved`` with all of them
(:mod:`~surffin.simulate.imperfections`).
``benchmarks/bench_validation.py`` renders them at several seeds and scores the
method against their truth; ``surffin simulate --validation NAME`` renders one.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from surffin.simulate.camera import PinholeCamera
from surffin.simulate.imperfections import Imperfections, named_imperfections
from surffin.simulate.presets import (
    Preset,
    SceneLayout,
    Specimen,
    another_piece,
    board_material,
    class_material,
)

__all__ = ["FORMATS", "IMPERFECT", "UNITS", "VALIDATION", "Validation"]

#: Values of ``fmt``: one view file form for all views, or ``mixed`` (npz, ply, raw in turn).
FORMATS = ("npz", "ply", "raw", "mixed")
#: Units of xyz in npz and ply view files.
UNITS = ("m", "mm")

_CAMERA = PinholeCamera(width=640, height=480, fx=565.0, fy=579.0)
_CROP = ((80, 400), (80, 560))
# 8 distances x 6 tilts = 48 wall views.
_WALL_DISTANCES = tuple(np.round(np.linspace(0.30, 1.00, 8), 6).tolist())
_WALL_TILTS = (0.0, 6.0, 12.0, 18.0, 24.0, 30.0)
_SPECIMEN_TILTS = (1.5, 11.0, 20.0, 29.0, 39.0)
# The scenes' angles of incidence at their centre, about 5 deg from the specimens'.
_SCENE_TILTS = (6.5, 16.0, 25.0, 34.0, 44.0)
_SCENE_DISTANCE = 0.60
_ROTATIONS = (90.0, 180.0, 270.0, 180.0)

# Class name, R0, n, grain (relative), thickness (m). Neighbouring mean n differ by 7-9 %;
# the R0 means lie within 5 % of each other, so that their ranges (2.5 % relative spread
# each, about 8 % over 5-95 %) overlap; the grain grows as n falls.
_PLASTER = (
    ("P1", 0.80, 1.12, 0.010, 0.010),
    ("P2", 0.82, 1.03, 0.018, 0.013),
    ("P3", 0.79, 0.95, 0.026, 0.017),
    ("P4", 0.81, 0.88, 0.034, 0.020),
)
_CONCRETE = (
    ("C1", 0.50, 1.08, 0.015, 0.012),
    ("C2", 0.49, 1.00, 0.025, 0.016),
    ("C3", 0.51, 0.925, 0.035, 0.020),
)


@dataclass(frozen=True)
class Validation:
    """A validation campaign: its design and how its files are written.

    Attributes
    ----------
    preset : Preset
    fmt : {"npz", "ply", "raw", "mixed"}
        View file form (:func:`~surffin.simulate.acquire.simulate_campaign`).
    units : {"m", "mm"}
        Unit of xyz in npz and ply files.
    poses : bool
        Write the camera poses (npz: inside, ply and raw: sidecars).
    imperfections : Imperfections
        The real camera's imperfections rendered; default none.
    """

    preset: Preset
    fmt: str = "npz"
    units: str = "m"
    poses: bool = True
    imperfections: Imperfections = Imperfections()


def _specimens(kind: str, table: tuple) -> tuple[Specimen, ...]:
    """One specimen per class of ``table``, named for its class, without a roughness."""
    return tuple(
        Specimen(name, name, None, class_material(f"{kind}-{name}", R0, n, grain), thickness)
        for name, R0, n, grain, thickness in table
    )


def _other_pieces(specimens: tuple[Specimen, ...], thicknesses: tuple[float, ...]) -> tuple[Specimen, ...]:
    """Second pieces (``<name>-b``) of the specimens' classes, textures and thicknesses of their own."""
    return tuple(
        another_piece(specimen, "b", thickness) for specimen, thickness in zip(specimens, thicknesses, strict=True)
    )


def _plaster() -> Preset:
    """Four plaster-like classes on a darker board; one scene of the training specimens at 0.60 m."""
    return Preset(
        name="val-plaster",
        camera=_CAMERA,
        crop=_CROP,
        intensity_noise=0.02,
        intensity_noise_max=0.02,
        intensity_floor=5.0,
        noise_reference=1500.0,
        depth_noise=0.0009,
        depth_noise_max=0.003,
        wall_distances=_WALL_DISTANCES,
        wall_tilts=_WALL_TILTS,
        reference_views=3,
        repeat_calibration=False,
        board=board_material(R0=0.33),
        specimens=_specimens("plaster", _PLASTER),
        specimen_size=0.20,
        specimen_distance=0.45,
        specimen_tilts=_SPECIMEN_TILTS,
        scene_rotations=_ROTATIONS,
        scene_distance=_SCENE_DISTANCE,
        scene_tilts=_SCENE_TILTS,
    )


def _concrete() -> Preset:
    """Three darker concrete-like classes on a darker board; the training specimens and second pieces."""
    specimens = _specimens("concrete", _CONCRETE)
    return replace(
        _plaster(),
        name="val-concrete",
        crop=None,
        board=board_material(R0=0.25),
        specimens=specimens,
        scenes=(
            SceneLayout(specimens, _ROTATIONS[:3], _SCENE_DISTANCE, _SCENE_TILTS),
            SceneLayout(
                _other_pieces(specimens, (0.018, 0.011, 0.014)), (270.0, 90.0, 180.0), _SCENE_DISTANCE, _SCENE_TILTS
            ),
        ),
    )


def _other_specimens() -> Preset:
    """val-plaster whose scene holds second pieces of the classes, not the training specimens."""
    plaster = _plaster()
    pieces = _other_pieces(plaster.specimens, (0.015, 0.011, 0.019, 0.012))
    scene = SceneLayout(pieces, _ROTATIONS, _SCENE_DISTANCE, _SCENE_TILTS)
    return replace(plaster, name="val-other-specimens", scenes=(scene,))


# Signed radii (m, + convex) of the curved campaigns' tops: the training specimens P1-P4, and the
# scene's other pieces of the classes, each bent otherwise than its class's specimen. A convex top
# must drop less than its thickness at its edges (20 cm wide: 16.5 mm at 0.3 m).
_SPECIMEN_RADII = (-0.3, 1.0, 0.5, 0.3)
_PIECE_RADII = (0.6, -0.4, 0.4, -1.0)


def _curved() -> Preset:
    """val-other-specimens on cylindrical panels: specimens and scene pieces of other radii, 0.3-1 m."""
    plaster = _other_specimens()
    (layout,) = plaster.scene_layouts
    specimens = tuple(replace(s, radius=r) for s, r in zip(plaster.specimens, _SPECIMEN_RADII, strict=True))
    pieces = tuple(replace(s, radius=r) for s, r in zip(layout.pieces, _PIECE_RADII, strict=True))
    return replace(plaster, name="val-curved", specimens=specimens, scenes=(replace(layout, pieces=pieces),))


# Imperfect val-plaster campaigns: name -> (standard imperfections, fmt, units, poses).
_IMPERFECT = {
    "val-distortion": ("unknown-distortion", "npz", "m", True),
    "val-known-distortion": ("distortion", "npz", "m", True),
    "val-pose-error": ("pose", "npz", "m", True),
    "val-mixed-pixels": ("mixed", "npz", "m", True),
    "val-saturation": ("saturation", "npz", "m", True),
    "val-systematics": ("systematics", "npz", "m", True),
    "val-all": ("all", "npz", "m", True),
    "val-signed-raw": ("signed-raw,settings", "raw", "mm", True),
    "val-bare-raw": ("no-intrinsics", "raw", "mm", False),
}


def _campaigns() -> dict[str, Validation]:
    plaster = _plaster()
    imperfect = {
        name: Validation(replace(plaster, name=name), fmt, units, poses, named_imperfections(names))
        for name, (names, fmt, units, poses) in _IMPERFECT.items()
    }
    return {
        "val-plaster": Validation(plaster),
        "val-concrete": Validation(_concrete(), fmt="ply", units="mm"),
        "val-other-specimens": Validation(_other_specimens()),
        "val-reference": Validation(replace(plaster, name="val-reference", reference_view=2), fmt="mixed"),
        "val-far": Validation(
            replace(plaster, name="val-far", scene_distance=0.75, scene_tilts=(9.0, 17.0, 27.0, 36.0, 46.0))
        ),
        "val-raw": Validation(replace(plaster, name="val-raw"), fmt="raw", units="mm"),
        "val-curved": Validation(_curved()),
        **imperfect,
        "val-curved-all": Validation(
            replace(_curved(), name="val-curved-all"), imperfections=named_imperfections("all")
        ),
    }


#: The validation campaigns by name:
#:
#: - ``val-plaster``: four plaster-like classes (R0 0.79-0.82, n 1.12, 1.03, 0.95, 0.88),
#:   10-20 mm thick, on a board of R0 0.33; npz in m, the paper's crop; one scene of
#:   the training specimens at 0.60 m.
#: - ``val-concrete``: three darker concrete-like classes (R0 0.49-0.51, n 1.08, 1.00,
#:   0.925) on a board of R0 0.25; binary PLY in mm with pose sidecars, no crop; two
#:   scenes at 0.60 m: the training specimens, and second pieces (own textures and
#:   thicknesses) turned otherwise.
#: - ``val-other-specimens``: val-plaster whose scene holds second pieces of the four
#:   classes (own textures and thicknesses), not the training specimens.
#: - ``val-reference``: val-plaster with the third view (index 2) as every item's
#:   reference view, files mixed npz/ply/raw.
#: - ``val-far``: val-plaster with the scene at 0.75 m and angles of 9-46 deg.
#: - ``val-raw``: val-plaster as Helios raw buffers (mm).
#: - ``val-curved``: val-other-specimens on cylindrical panels: the specimens' tops of radius
#:   -0.3, 1.0, 0.5 and 0.3 m (+ convex), the scene's second pieces of 0.6, -0.4, 0.4 and -1.0 m
#:   (each class bent otherwise in the scene than in training); ``val-curved-all`` adds every
#:   imperfection of ``val-all``.
#: - :data:`IMPERFECT`, val-plaster through a real camera
#:   (:data:`~surffin.simulate.imperfections.STANDARD`): ``val-distortion`` (k1 -0.12,
#:   k2 0.05, campaign.yaml giving the pinhole intrinsics only), ``val-known-distortion``
#:   (the distortion given), ``val-pose-error`` (recorded poses 1 mm and 0.2 deg off),
#:   ``val-mixed-pixels``, ``val-saturation`` (2000 counts, given), ``val-systematics``
#:   (3 % outside eq. 5), ``val-all`` (the distortion unknown, the pose error, mixed pixels
#:   and the systematics), ``val-signed-raw`` (Coord3D_ABCY16s with settings sidecars and
#:   camera.match_settings) and ``val-bare-raw`` (raw files without poses or intrinsics).
VALIDATION: dict[str, Validation] = _campaigns()
#: Names of the validation campaigns that render a real camera's imperfections.
IMPERFECT = tuple(name for name, validation in VALIDATION.items() if validation.imperfections.any)
