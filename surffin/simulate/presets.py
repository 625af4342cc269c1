"""Presets of the synthetic camera: what is acquired, how, and with which noise.

A :class:`Preset` is a frozen dataclass; variants are made with
:func:`dataclasses.replace`, e.g.
``replace(PRESETS["tiny"], depth_noise=0, intensity_noise=0, dropout=0)`` for a
noise-free campaign. Angles are in degrees here (they are design numbers),
lengths in metres.

The materials follow the paper's plaster specimens qualitatively (not tuned to
its numbers): n falls nearly linearly with roughness, R0 rises from S1 to S3 and
drops for S4 to about S1's level, and the fine grain of the surface grows with
roughness.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from surffin.simulate.camera import PinholeCamera
from surffin.simulate.scene import Material, Texture

__all__ = ["Specimen", "Preset", "plaster", "scaled_preset", "PRESETS"]

_PAPER_CAMERA = PinholeCamera(width=640, height=480, fx=565.0, fy=579.0)
_TINY_SCALE = 8


@dataclass(frozen=True)
class Specimen:
    """A reference specimen of known class.

    Attributes
    ----------
    name : str
        Item name in the campaign (``S1``).
    cls : str
        Class name (``class:`` in campaign.yaml).
    roughness_mm : float
        Reference roughness written to campaign.yaml, mm.
    material : Material
        What its faces are made of.
    """

    name: str
    cls: str
    roughness_mm: float
    material: Material


def plaster(name: str, roughness_mm: float, R0: float, grain_length: float = 0.001) -> Specimen:
    """A gypsum plaster specimen whose scattering and grain follow its roughness.

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


def _plasters(grain_length: float) -> tuple[Specimen, ...]:
    """The paper's four specimens S1..S4 (roughness of its Table 4)."""
    table = (("S1", 0.0068, 0.80), ("S2", 0.0255, 0.86), ("S3", 0.0532, 0.92), ("S4", 0.1459, 0.81))
    return tuple(plaster(name, roughness, R0, grain_length) for name, roughness, R0 in table)


def _board(grain_length: float) -> Material:
    """The board the specimens lie on: cm-scale blotches (8 %) plus a fine grain (3 %)."""
    return Material(
        "board",
        R0=0.45,
        n=1.1,
        R0_texture=(Texture(0.08, 0.012, 1.63), Texture(0.03, grain_length, 0.41)),
        n_texture=(Texture(0.02, 0.01, 1.63),),
    )


@dataclass(frozen=True)
class Preset:
    """Everything that defines a synthetic campaign except the seed.

    Attributes
    ----------
    name : str
    camera : PinholeCamera
    crop : ((int, int), (int, int))
        Half-open sensor ranges ``((y0, y1), (x0, x1))`` written to campaign.yaml.
    gain : float
        Counts per unit of ``f * R``.
    coef_mean, coef_variability : (5,) tuple of float
        Image mean and relative spatial standard deviation of the instrument
        coefficients A, B (m^2), C, D, E.
    intensity_noise, intensity_noise_max : float
        Relative intensity noise on strong returns, and its cap on weak ones.
    noise_reference : float
        Counts above which the relative noise is ``intensity_noise``; below, it
        grows as ``1/sqrt(I)`` up to ``intensity_noise_max``.
    depth_noise : float, metres
        Range noise along each pixel's ray.
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
    specimen_size, specimen_thickness : float, metres
        Square top face edge, height above the board.
    specimen_distance : float, metres
        Camera to specimen centre in the specimen views.
    specimen_tilts : tuple of float, degrees
        One view per tilt, the first is the reference view.
    scene_rotations : tuple of float, degrees
        In-plane rotation of each specimen in the scene, in ``specimens`` order;
        the scene holds the first ``len(scene_rotations)`` specimens.
    scene_gap : float, metres
        Between neighbouring specimens of the 2 x 2 scene.
    scene_distance : float, metres
    scene_tilts : tuple of float, degrees
    roll : float, degrees
        Largest random roll of the camera about its optical axis.
    label_margin : float, metres
        Truth labels leave out specimen top pixels closer than this to an edge;
        rois keep at least this far inside.
    """

    name: str
    camera: PinholeCamera
    crop: tuple[tuple[int, int], tuple[int, int]]
    gain: float = 400.0
    coef_mean: tuple[float, ...] = (0.3, 1.0, -0.25, 0.05, 1.0)
    coef_variability: tuple[float, ...] = (0.0894, 0.0392, 0.0179, 0.0138, 0.0444)
    intensity_noise: float = 0.015
    intensity_noise_max: float = 0.04
    noise_reference: float = 2000.0
    depth_noise: float = 0.0009
    dropout: float = 0.001
    min_intensity: float = 50.0
    max_aoi: float = 80.0
    wall: Material = Material("wall", 0.5, 1.0, R0_texture=(Texture(0.005, 0.01, 1.0),))
    wall_distances: tuple[float, ...] = tuple(np.round(np.linspace(0.3, 1.0, 15), 6).tolist())
    wall_tilts: tuple[float, ...] = (0.0, 5.0, 10.0, 15.0, 20.0, 25.0, 30.0)
    wall_spread: float = 0.3
    reference: Material = Material("spectralon", 0.60, 1.0)
    panel_size: float = 0.10
    panel_thickness: float = 0.005
    reference_distance: float = 0.5
    reference_views: int = 3
    repeat_calibration: bool = True
    repeat_shift: float = 0.03
    repeat_turn: float = 3.0
    board: Material = _board(grain_length=0.001)
    specimens: tuple[Specimen, ...] = _plasters(grain_length=0.001)
    specimen_size: float = 0.10
    specimen_thickness: float = 0.01
    specimen_distance: float = 0.35
    specimen_tilts: tuple[float, ...] = (0.0, 10.0, 20.0, 30.0, 40.0)
    scene_rotations: tuple[float, ...] = (90.0, 180.0, 270.0, 180.0)
    scene_gap: float = 0.02
    scene_distance: float = 0.50
    scene_tilts: tuple[float, ...] = (5.0, 15.0, 25.0, 35.0, 45.0)
    roll: float = 2.0
    label_margin: float = 0.005

    @property
    def classes(self) -> tuple[str, ...]:
        """Class names in label order (sorted)."""
        return tuple(sorted({specimen.cls for specimen in self.specimens}))


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
        board=_board(grain_length=0.003),
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
    specimens = []
    for index in range(int(n_specimens)):
        template, copy = base[index % len(base)], f"{index // len(base) + 1:02d}"
        material = replace(template.material, name=f"{template.material.name}-{copy}")
        specimens.append(replace(template, name=f"{template.name}-{copy}", material=material))
    return replace(preset, name=f"{preset.name}-x{int(n_specimens)}", specimens=tuple(specimens))


#: The named presets: ``paper`` (the paper's camera and acquisition design) and
#: ``tiny`` (the same structure on an 80 x 60 sensor, for tests).
PRESETS: dict[str, Preset] = {
    "paper": Preset(name="paper", camera=_PAPER_CAMERA, crop=((80, 400), (80, 560))),
    "tiny": _tiny(),
}
