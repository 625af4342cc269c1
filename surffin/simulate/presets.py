"""Presets of the synthetic camera: what is acquired, how, and with which noise.

A :class:`Preset` is a frozen dataclass; variants are made with
:func:`dataclasses.replace`, e.g.
``replace(PRESETS["tiny"], depth_noise=0, intensity_noise=0, dropout=0)`` for a
noise-free campaign. Angles are in degrees here (they are design numbers),
lengths in metres.

The materials of the named presets follow the paper's plaster specimens
qualitatively (not tuned to its numbers): n falls nearly linearly with
roughness, R0 rises from S1 to S3 and drops for S4 to about S1's level, and the
fine grain of the surface grows with roughness. :func:`class_material` builds a
class from its own means and spreads instead, for designs that must not echo the
paper (:mod:`~surffin.simulate.validation`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from surffin.simulate.camera import PinholeCamera
from surffin.simulate.scene import Material, Texture

__all__ = [
    "PRESETS",
    "Preset",
    "SceneLayout",
    "Specimen",
    "another_piece",
    "board_material",
    "class_material",
    "plaster",
    "scaled_preset",
]

_PAPER_CAMERA = PinholeCamera(width=640, height=480, fx=565.0, fy=579.0)
_TINY_SCALE = 8
# Texture scales of class_material, metres: the cm-scale blotch and mm-scale mottle that
# carry a class's spread of R0 and n (their weights split its variance 64:36), the
# sub-pixel grain that makes the spatial variability, and the period of all three
# (longer than a 0.2 m specimen, so that no texture repeats on one).
_BLOTCH, _MOTTLE, _GRAIN = 0.010, 0.003, 0.0005
_SPLIT = (0.8, 0.6)
_CLASS_PERIOD = 0.3


@dataclass(frozen=True)
class Specimen:
    """A reference specimen of known class.

    Attributes
    ----------
    name : str
        Item name in the campaign (``S1``).
    cls : str
        Class name (``class:`` in campaign.yaml).
    roughness_mm : float or None
        Reference roughness written to campaign.yaml, mm; None writes none.
    material : Material
        What its faces are made of; its name identifies the texture draw, so
        two pieces of one class need two material names.
    thickness : float or None, metres
        Height above the board (of its top's centre); None takes the preset's
        ``specimen_thickness``.
    radius : float or None, metres
        Signed radius of a cylindrical top (a curved panel, bent along its
        in-plane X axis): positive convex, negative concave; None flat. See
        :func:`~surffin.simulate.scene.box_faces`.
    """

    name: str
    cls: str
    roughness_mm: float | None
    material: Material
    thickness: float | None = None
    radius: float | None = None


def plaster(name: str, roughness_mm: float, R0: float, grain_length: float = 0.001) -> Specimen:
    """Make a gypsum plaster specimen whose scattering and grain follow its roughness.

    ``n = 1.30 - 2.4 roughness_mm``; the fine grain of R0 has relative amplitude
    ``0.01 + 0.2 roughness_mm``, plus a 1 % blotch at 4 mm scale; n varies by
    ``0.005 + 0.1 roughness_mm`` at 3 mm scale.

    Parameters
    ----------
    name : str
        Specimen and class name.
    roughness_mm : float
        Surface roughness, mm.
    R0 : float
        Mean reflectance at normal incidence.
    grain_length : float, metres
        Smoothing length of the fine grain.

    Returns
    -------
    Specimen
    """
    period = 0.25
    return Specimen(
        name=name,
        cls=name,
        roughness_mm=roughness_mm,
        material=Material(
            name=f"plaster-{name}",
            R0=R0,
            n=1.30 - 2.4 * roughness_mm,
            R0_texture=(
                Texture(0.01 + 0.2 * roughness_mm, grain_length, period),
                Texture(0.01, 0.004, period),
            ),
            n_texture=(Texture(0.005 + 0.1 * roughness_mm, 0.003, period),),
        ),
    )


def class_material(
    name: str, R0: float, n: float, grain: float, spread: tuple[float, float] = (0.025, 0.0115)
) -> Material:
    """Make a class's material from its own means and within-class spreads.

    R0 varies by ``spread[0]`` (relative standard deviation) and n by
    ``spread[1]`` (relative, so ``n * spread[1]`` absolute), each in a 10 mm
    blotch and a 3 mm mottle (variance split 64:36) that a 7 x 7 pixel
    smoothing at 0.45 m (about 1.1 mm) keeps. ``grain`` adds a 0.5 mm grain of
    R0, which the smoothing largely removes, that makes the class's spatial
    reflectance variability. The default spreads with grains of 0.01-0.035
    give smoothed per-pixel 5-95 % ranges of 7.5-9.5 % in R0 and 3-4 % in n
    (tests/test_simulate.py measures them).

    Parameters
    ----------
    name : str
        Material name (identifies its texture draw).
    R0 : float
        Mean reflectance at normal incidence.
    n : float
        Mean scattering coefficient.
    grain : float
        Relative standard deviation of the fine grain of R0.
    spread : (float, float)
        Relative standard deviations of R0 and n over the cm and mm scales.

    Returns
    -------
    Material
    """
    R0_spread, n_spread = spread
    large, small = _SPLIT
    return Material(
        name=name,
        R0=R0,
        n=n,
        R0_texture=(
            Texture(large * R0_spread, _BLOTCH, _CLASS_PERIOD),
            Texture(small * R0_spread, _MOTTLE, _CLASS_PERIOD),
            Texture(grain, _GRAIN, _CLASS_PERIOD),
        ),
        n_texture=(
            Texture(large * n_spread * n, _BLOTCH, _CLASS_PERIOD),
            Texture(small * n_spread * n, _MOTTLE, _CLASS_PERIOD),
        ),
    )


def another_piece(specimen: Specimen, suffix: str, thickness: float | None = None) -> Specimen:
    """Another physical piece of ``specimen``'s class, with a texture draw of its own.

    Parameters
    ----------
    specimen : Specimen
    suffix : str
        The piece is named ``<name>-<suffix>``, and its material alike.
    thickness : float, metres, optional
        Its own height above the board; default: ``specimen``'s.

    Returns
    -------
    Specimen
        Same class, roughness and material means and textures' design.
    """
    material = replace(specimen.material, name=f"{specimen.material.name}-{suffix}")
    thickness = specimen.thickness if thickness is None else thickness
    return replace(specimen, name=f"{specimen.name}-{suffix}", material=material, thickness=thickness)


def _plasters(grain_length: float) -> tuple[Specimen, ...]:
    """Make the paper's four specimens S1..S4 (roughness of its Table 4)."""
    table = (("S1", 0.0068, 0.80), ("S2", 0.0255, 0.86), ("S3", 0.0532, 0.92), ("S4", 0.1459, 0.81))
    return tuple(plaster(name, roughness, R0, grain_length) for name, roughness, R0 in table)


def board_material(grain_length: float = 0.001, R0: float = 0.45) -> Material:
    """Make the board the specimens lie on: cm-scale blotches (8 %) plus a fine grain (3 %).

    Parameters
    ----------
    grain_length : float, metres
        Smoothing length of the fine grain.
    R0 : float
        Mean reflectance at normal incidence.

    Returns
    -------
    Material
    """
    return Material(
        "board",
        R0=R0,
        n=1.1,
        R0_texture=(Texture(0.08, 0.012, 1.63), Texture(0.03, grain_length, 0.41)),
        n_texture=(Texture(0.02, 0.01, 1.63),),
    )


# Defaults of Preset: a Lambertian wall with a faint texture, the reference panel, the
# board and the paper's four specimens with a 1 mm grain.
_WALL = Material("wall", 0.5, 1.0, R0_texture=(Texture(0.005, 0.01, 1.0),))
_SPECTRALON = Material("spectralon", 0.60, 1.0)
_BOARD = board_material(grain_length=0.001)
_PLASTERS = _plasters(grain_length=0.001)


@dataclass(frozen=True)
class SceneLayout:
    """One scene: pieces on a board, and the views of it.

    Attributes
    ----------
    pieces : tuple of Specimen
        What lies on the board, in rows of two; their classes must be among the
        training specimens'. Pieces other than the training specimens (see
        :func:`another_piece`) need names and material names of their own.
    rotations : tuple of float, degrees
        In-plane rotation of each piece.
    distance : float, metres
        Camera to the scene's centre.
    tilts : tuple of float, degrees
        One view per tilt (angle of incidence at the scene's centre).
    """

    pieces: tuple[Specimen, ...]
    rotations: tuple[float, ...]
    distance: float
    tilts: tuple[float, ...]


@dataclass(frozen=True)
class Preset:
    """Everything that defines a synthetic campaign except the seed.

    Attributes
    ----------
    name : str
    camera : PinholeCamera
    crop : ((int, int), (int, int)) or None
        Half-open sensor ranges ``((y0, y1), (x0, x1))`` written to
        campaign.yaml; None writes no crop (the whole sensor).
    gain : float
        Counts per unit of ``f * R``.
    coef_mean, coef_variability : (5,) tuple of float
        Image mean and relative spatial standard deviation of the instrument
        coefficients A, B (m^2), C, D, E.
    intensity_noise, intensity_noise_max : float
        Relative intensity noise on strong returns, and its cap on weak ones.
    intensity_floor : float
        Additive intensity noise, counts (standard deviation), on top of the
        relative noise.
    noise_reference : float
        Counts above which the relative noise is ``intensity_noise`` and the
        range noise ``depth_noise``; below, both grow as ``1/sqrt(I)`` up to
        ``intensity_noise_max`` and ``depth_noise_max``.
    depth_noise : float, metres
        Range noise along each pixel's ray on strong returns.
    depth_noise_max : float, metres
        Cap of the range noise on weak returns; at most ``depth_noise`` (the
        default) means no growth.
    dropout : float
        Fraction of pixels lost at random.
    min_intensity : float
        Weaker returns (counts) are invalid.
    max_aoi : float, degrees
        Pixels seeing their surface at a more grazing angle are invalid.
    wall : Material
        The calibration wall (Lambertian).
    wall_distances, wall_tilts : tuple of float
        Calibration views: one per (distance, tilt) pair, metres and degrees;
        azimuths follow the golden angle.
    wall_spread : float, metres
        Half side of the square of wall points the calibration views aim at.
    reference : Material
        The reference panel (Lambertian, known reflectance).
    panel_size, panel_thickness : float, metres
    reference_distance : float, metres
        Fronto-parallel distance of the reference views.
    reference_views : int
        Number of reference views (all from the same pose).
    repeat_calibration : bool
        Also render a second calibration set of the same camera, wall and
        panel (same design, slightly different poses, its own noise) into
        folders that ``campaign.yaml`` does not name
        (:data:`~surffin.simulate.plan.REPEAT_FOLDERS`), for repeatability.
    repeat_shift : float, metres
        Largest change of a repeat wall view's target (along each wall axis)
        and distance; the repeat panel views come up to this much closer.
    repeat_turn : float, degrees
        Largest change of a repeat wall view's tilt and azimuth, and tilt of
        the repeat panel views.
    board : Material
        Background of the specimens (class -1).
    specimens : tuple of Specimen
        The training specimens.
    specimen_size, specimen_thickness : float, metres
        Square top face edge, height above the board (of the specimens that do
        not set their own).
    specimen_distance : float, metres
        Camera to specimen centre in the specimen views.
    specimen_tilts : tuple of float, degrees
        One view per tilt.
    reference_view : int
        Index of the reference view of every specimen and scene (0: the first,
        as campaign.yaml assumes by default; otherwise written as the item's
        ``reference``).
    scene_rotations : tuple of float, degrees
        In-plane rotation of each specimen in the default scene, in
        ``specimens`` order; it holds the first ``len(scene_rotations)``
        specimens.
    scene_gap : float, metres
        Between neighbouring pieces of a scene (rows of two).
    scene_distance : float, metres
        Of the default scene.
    scene_tilts : tuple of float, degrees
        Of the default scene.
    scenes : tuple of SceneLayout or None
        The scenes ``T1``, ``T2``, ... in order; None (the default) is one
        scene ``T1`` of the training specimens as ``scene_rotations``,
        ``scene_distance`` and ``scene_tilts`` say (:attr:`scene_layouts`).
    roll : float, degrees
        Largest random roll of the camera about its optical axis.
    label_margin : float, metres
        Truth labels leave out specimen top pixels closer than this to an edge;
        rois keep at least this far inside.
    """

    name: str
    camera: PinholeCamera
    crop: tuple[tuple[int, int], tuple[int, int]] | None
    gain: float = 400.0
    coef_mean: tuple[float, ...] = (0.3, 1.0, -0.25, 0.05, 1.0)
    coef_variability: tuple[float, ...] = (0.0894, 0.0392, 0.0179, 0.0138, 0.0444)
    intensity_noise: float = 0.015
    intensity_noise_max: float = 0.04
    intensity_floor: float = 0.0
    noise_reference: float = 2000.0
    depth_noise: float = 0.0009
    depth_noise_max: float = 0.0
    dropout: float = 0.001
    min_intensity: float = 50.0
    max_aoi: float = 80.0
    wall: Material = _WALL
    wall_distances: tuple[float, ...] = tuple(np.round(np.linspace(0.3, 1.0, 15), 6).tolist())
    wall_tilts: tuple[float, ...] = (0.0, 5.0, 10.0, 15.0, 20.0, 25.0, 30.0)
    wall_spread: float = 0.3
    reference: Material = _SPECTRALON
    panel_size: float = 0.10
    panel_thickness: float = 0.005
    reference_distance: float = 0.5
    reference_views: int = 3
    repeat_calibration: bool = True
    repeat_shift: float = 0.03
    repeat_turn: float = 3.0
    board: Material = _BOARD
    specimens: tuple[Specimen, ...] = _PLASTERS
    specimen_size: float = 0.10
    specimen_thickness: float = 0.01
    specimen_distance: float = 0.35
    specimen_tilts: tuple[float, ...] = (0.0, 10.0, 20.0, 30.0, 40.0)
    reference_view: int = 0
    scene_rotations: tuple[float, ...] = (90.0, 180.0, 270.0, 180.0)
    scene_gap: float = 0.02
    scene_distance: float = 0.50
    scene_tilts: tuple[float, ...] = (5.0, 15.0, 25.0, 35.0, 45.0)
    scenes: tuple[SceneLayout, ...] | None = None
    roll: float = 2.0
    label_margin: float = 0.005

    @property
    def classes(self) -> tuple[str, ...]:
        """Class names in label order (sorted)."""
        return tuple(sorted({specimen.cls for specimen in self.specimens}))

    @property
    def scene_layouts(self) -> tuple[SceneLayout, ...]:
        """The scenes ``T1``, ``T2``, ...: ``scenes``, or the default scene of the training specimens."""
        if self.scenes is not None:
            return self.scenes
        shown = self.specimens[: len(self.scene_rotations)]
        return (SceneLayout(shown, self.scene_rotations, self.scene_distance, self.scene_tilts),)

    def thickness(self, specimen: Specimen) -> float:
        """Height of ``specimen`` above the board, metres: its own, or ``specimen_thickness``."""
        return self.specimen_thickness if specimen.thickness is None else specimen.thickness


def _tiny() -> Preset:
    camera = PinholeCamera(
        width=_PAPER_CAMERA.width // _TINY_SCALE,
        height=_PAPER_CAMERA.height // _TINY_SCALE,
        fx=_PAPER_CAMERA.fx / _TINY_SCALE,
        fy=_PAPER_CAMERA.fy / _TINY_SCALE,
    )
    return Preset(
        name="tiny",
        camera=camera,
        crop=((10, 50), (10, 70)),
        wall_distances=(0.3, 0.55, 0.8, 1.0),
        wall_tilts=(0.0, 10.0, 20.0, 30.0),
        reference_views=2,
        panel_size=0.15,
        reference_distance=0.35,
        board=board_material(grain_length=0.003),
        specimens=_plasters(grain_length=0.002),
        specimen_size=0.15,
        specimen_distance=0.30,
        specimen_tilts=(0.0, 20.0, 40.0),
        scene_distance=0.65,
        scene_tilts=(5.0, 25.0, 45.0),
    )


def scaled_preset(preset: Preset, n_specimens: int) -> Preset:
    """``preset`` with ``n_specimens`` reference specimens, for campaign-scale benchmarks.

    Specimen ``k`` (from 0) repeats the class and material of
    ``preset.specimens[k % K]`` (K specimens in ``preset``) under its own name
    ``<name>-<k // K + 1:02d>`` (``S1-01``, ``S2-01``, ..., ``S1-02``, ...).
    Its material is renamed alike, so it gets its own texture draw; it lies
    at its own place on the board and is seen from its own poses (see
    :func:`~surffin.simulate.plan.plan_campaign`). The scene keeps the first
    ``len(preset.scene_rotations)`` specimens: one of each class for the
    named presets.

    Parameters
    ----------
    preset : Preset
    n_specimens : int
        At least ``len(preset.scene_rotations)``.

    Returns
    -------
    Preset
        Named ``<preset.name>-x<n_specimens>``.
    """
    base = preset.specimens
    if int(n_specimens) != n_specimens or n_specimens < len(preset.scene_rotations):
        raise ValueError(
            f"n_specimens must be an integer >= {len(preset.scene_rotations)} (the specimens of the scene), "
            f"got {n_specimens!r}"
        )
    specimens = tuple(
        another_piece(base[index % len(base)], f"{index // len(base) + 1:02d}") for index in range(int(n_specimens))
    )
    return replace(preset, name=f"{preset.name}-x{int(n_specimens)}", specimens=specimens)


#: The named presets: ``paper`` (the paper's camera and acquisition design) and
#: ``tiny`` (the same structure on an 80 x 60 sensor, for tests).
PRESETS: dict[str, Preset] = {
    "paper": Preset(name="paper", camera=_PAPER_CAMERA, crop=((80, 400), (80, 560))),
    "tiny": _tiny(),
}
