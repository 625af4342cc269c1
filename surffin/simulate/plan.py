"""The acquisition design of a synthetic campaign: what the camera sees, and from where."""

from __future__ import annotations

import dataclasses

import numpy as np

from surffin.simulate.camera import look_at_pose
from surffin.simulate.presets import Preset, SceneLayout, Specimen
from surffin.simulate.scene import Face, box_faces, keyed_rng, plane_face

__all__ = ["REPEAT_FOLDERS", "Acquisition", "plan_campaign"]

#: Folders of the repeat calibration set (relative to the campaign directory), which
#: ``campaign.yaml`` does not name: a second calibration of the same camera, for repeatability.
REPEAT_FOLDERS = {"wall": "calibration/repeat/wall", "reference": "calibration/repeat/spectralon"}

_GOLDEN_ANGLE = np.pi * (3.0 - np.sqrt(5.0))
# World X, Y of the specimens' places on the board (specimen k at
# (_SPECIMEN_PITCH * (k - (K-1)/2), _SPECIMEN_ROW)) and of the centre of scene k
# (from 0) at (_SCENE_PITCH * k, _SCENE_ROW): each scene on a patch of board of its own.
_SPECIMEN_PITCH = 0.3
_SPECIMEN_ROW = -0.5
_SCENE_PITCH = 0.6
_SCENE_ROW = 0.5


@dataclasses.dataclass(frozen=True, eq=False)
class Acquisition:
    """One folder of views: a scene seen from a list of poses.

    Attributes
    ----------
    name : str
        Item name (specimens, scenes) or ``wall`` / ``reference``.
    kind : {"wall", "reference", "specimen", "scene"}
    folder : str
        Relative to the campaign directory.
    faces : tuple of Face
        The scene.
    poses : tuple of (4, 4) ndarray
        Camera-to-world, metres, in view order.
    prefix : str
        View names are ``<prefix><index>`` with ``digits`` digits.
    digits : int
    specimen : Specimen or None
        The specimen of a specimen acquisition.
    roi_face : str or None
        Name of the face whose pixels in the reference view make the roi
        (specimens and the reference panel).
    repeat : bool
        Part of the repeat calibration set (wall or reference panel views):
        written to its folder, but not named in ``campaign.yaml``.
    reference : int
        Index of the reference view (whose grid the truth, the roi and the
        scene's truth labels are on).
    """

    name: str
    kind: str
    folder: str
    faces: tuple[Face, ...]
    poses: tuple[np.ndarray, ...]
    prefix: str = "v"
    digits: int = 2
    specimen: Specimen | None = None
    roi_face: str | None = None
    repeat: bool = False
    reference: int = 0

    @property
    def stems(self) -> list[str]:
        """View file stems, in view order (also their name order)."""
        return [f"{self.prefix}{index:0{self.digits}d}" for index in range(len(self.poses))]

    @property
    def reference_stem(self) -> str:
        """Stem of the reference view."""
        return self.stems[self.reference]

    @property
    def has_truth(self) -> bool:
        """Specimens and scenes get a truth store."""
        return self.kind in ("specimen", "scene")


def _rolls(preset: Preset, seed: int, name: str, count: int) -> np.ndarray:
    """Random camera rolls of an acquisition's views, radians."""
    return np.deg2rad(keyed_rng(seed, "roll", name).uniform(-preset.roll, preset.roll, count))


def _wall(preset: Preset, seed: int, repeat: bool = False) -> Acquisition:
    """One view per (distance, tilt) of the design, aimed at random wall points, golden-angle azimuths.

    The repeat set (``repeat``) moves each view of the first set: the target by
    up to ``repeat_shift`` along each wall axis, the distance by up to
    ``repeat_shift``, the tilt and azimuth by up to ``repeat_turn``, with rolls
    of its own.
    """
    name = "repeat-wall" if repeat else "wall"
    design = np.array([(distance, tilt) for distance in preset.wall_distances for tilt in preset.wall_tilts])
    targets = keyed_rng(seed, "targets", "wall").uniform(-preset.wall_spread, preset.wall_spread, (len(design), 2))
    azimuths = np.arange(len(design)) * _GOLDEN_ANGLE
    if repeat:
        move = keyed_rng(seed, "move", name).uniform(-1.0, 1.0, (len(design), 5))
        targets = targets + preset.repeat_shift * move[:, :2]
        design = design + move[:, 2:4] * (preset.repeat_shift, preset.repeat_turn)
        azimuths = azimuths + np.deg2rad(preset.repeat_turn) * move[:, 4]
    rolls = _rolls(preset, seed, name, len(design))
    poses = tuple(
        look_at_pose((x, y, 0.0), distance, np.deg2rad(tilt), azimuth, roll)
        for (distance, tilt), (x, y), azimuth, roll in zip(design, targets, azimuths, rolls)
    )
    digits = max(3, len(str(len(poses) - 1)))
    faces = (plane_face("wall", preset.wall),)
    folder = REPEAT_FOLDERS["wall"] if repeat else "calibration/wall"
    return Acquisition(name, "wall", folder, faces, poses, prefix="w", digits=digits, repeat=repeat)


def _reference(preset: Preset, seed: int, repeat: bool = False) -> Acquisition:
    """Plan the panel on the wall, fronto-parallel, all views from one pose (the panel on the same pixels).

    The repeat set's pose is up to ``repeat_shift`` closer, tilted by up to
    ``repeat_turn`` (random azimuth) and rolled by up to ``roll``, still aimed
    at the panel's centre: the panel only grows and turns a little in the
    image, so the roi of ``campaign.yaml`` stays on it.
    """
    faces = (
        plane_face("wall", preset.wall),
        *box_faces("panel", (0.0, 0.0), preset.panel_size, preset.panel_thickness, 0.0, preset.reference, -1),
    )
    target = (0.0, 0.0, -preset.panel_thickness)
    name, folder, pose = "reference", "calibration/reference", look_at_pose(target, preset.reference_distance, 0.0, 0.0)
    if repeat:
        closer, tilt, azimuth, roll = keyed_rng(seed, "move", "repeat-reference").uniform(0.0, 1.0, 4)
        name, folder = "repeat-reference", REPEAT_FOLDERS["reference"]
        pose = look_at_pose(
            target,
            preset.reference_distance - preset.repeat_shift * closer,
            np.deg2rad(preset.repeat_turn * tilt),
            2.0 * np.pi * azimuth,
            np.deg2rad(preset.roll * (2.0 * roll - 1.0)),
        )
    poses = tuple(pose.copy() for _ in range(preset.reference_views))
    return Acquisition(name, "reference", folder, faces, poses, prefix="r", roi_face="panel.top", repeat=repeat)


def _orbit(preset: Preset, seed: int, name: str, target, distance: float, tilts, turn: float) -> tuple:
    """Poses around a target: one per tilt (degrees), azimuths by the golden angle from ``turn``."""
    rolls = _rolls(preset, seed, name, len(tilts))
    return tuple(
        look_at_pose(target, distance, np.deg2rad(tilt), turn + index * _GOLDEN_ANGLE, roll)
        for index, (tilt, roll) in enumerate(zip(tilts, rolls))
    )


def _specimen(preset: Preset, seed: int, index: int) -> Acquisition:
    """Specimen ``index`` alone on the board, at the image centre of every view."""
    specimen = preset.specimens[index]
    height = preset.thickness(specimen)
    centre = (_SPECIMEN_PITCH * (index - (len(preset.specimens) - 1) / 2.0), _SPECIMEN_ROW)
    label = preset.classes.index(specimen.cls)
    faces = (
        plane_face("board", preset.board),
        *box_faces(specimen.name, centre, preset.specimen_size, height, 0.0, specimen.material, label, specimen.radius),
    )
    target = (*centre, -height)
    poses = _orbit(preset, seed, specimen.name, target, preset.specimen_distance, preset.specimen_tilts, index)
    folder = f"specimens/{specimen.name}"
    return Acquisition(
        specimen.name,
        "specimen",
        folder,
        faces,
        poses,
        specimen=specimen,
        roi_face=f"{specimen.name}.top",
        reference=preset.reference_view,
    )


def _scene(preset: Preset, seed: int, index: int, layout: SceneLayout) -> Acquisition:
    """Scene ``T<index + 1>``: its pieces on the board in rows of two, each turned by its angle.

    The views aim at the scene's centre at the pieces' mean height.
    """
    name = f"T{index + 1}"
    pitch = preset.specimen_size + preset.scene_gap
    middle = (_SCENE_PITCH * index, _SCENE_ROW)
    rows = (len(layout.pieces) + 1) // 2
    faces = [plane_face("board", preset.board)]
    for place, (piece, rotation) in enumerate(zip(layout.pieces, layout.rotations, strict=True)):
        if piece.cls not in preset.classes:
            raise ValueError(f"scene {name}: piece {piece.name} is of class {piece.cls!r}, which no specimen has")
        row, column = divmod(place, 2)
        centre = (middle[0] + pitch * (column - 0.5), middle[1] + pitch * (row - (rows - 1) / 2.0))
        faces += box_faces(
            f"{name}.{piece.name}",
            centre,
            preset.specimen_size,
            preset.thickness(piece),
            np.deg2rad(rotation),
            piece.material,
            preset.classes.index(piece.cls),
            piece.radius,
        )
    target = (*middle, -float(np.mean([preset.thickness(piece) for piece in layout.pieces])))
    turn = len(preset.specimens) + index
    poses = _orbit(preset, seed, name, target, layout.distance, layout.tilts, turn)
    return Acquisition(name, "scene", f"scenes/{name}", tuple(faces), poses, reference=preset.reference_view)


def _check_reference_view(preset: Preset) -> None:
    """Refuse a reference view index that some specimen or scene does not have."""
    counts = [len(preset.specimen_tilts), *(len(layout.tilts) for layout in preset.scene_layouts)]
    if not 0 <= preset.reference_view < min(counts):
        raise ValueError(
            f"reference_view {preset.reference_view!r} must index a view of every specimen and scene "
            f"(0 to {min(counts) - 1})"
        )


def plan_campaign(preset: Preset, seed: int) -> list[Acquisition]:
    """Plan the acquisitions of a campaign: what is in front of the camera, and from where.

    Parameters
    ----------
    preset : Preset
    seed : int
        Seeds the random parts of the design (wall targets, camera rolls).

    Returns
    -------
    list of Acquisition
        The calibration wall, the reference panel, one per specimen (alone on
        the board, at the image centre) and the scenes ``T1``, ``T2``, ... of
        :attr:`Preset.scene_layouts` (by default one, of the first
        ``len(preset.scene_rotations)`` specimens, all of them in the named
        presets); a scene's pieces lie in rows of two, rotated in-plane. Specimen
        and scene views look at the centre of their top faces, with azimuths
        following the golden angle from a different start per item; their
        reference view is ``preset.reference_view``. Last, when
        ``preset.repeat_calibration``, the repeat calibration set: the wall and
        the panel again from slightly different poses, into
        :data:`REPEAT_FOLDERS`.

    Raises
    ------
    ValueError
        ``preset.reference_view`` is not a view of every item, or a scene
        holds a piece of a class no specimen has.
    """
    _check_reference_view(preset)
    specimens = [_specimen(preset, seed, index) for index in range(len(preset.specimens))]
    scenes = [_scene(preset, seed, index, layout) for index, layout in enumerate(preset.scene_layouts)]
    plan = [_wall(preset, seed), _reference(preset, seed), *specimens, *scenes]
    if preset.repeat_calibration:
        plan += [_wall(preset, seed, repeat=True), _reference(preset, seed, repeat=True)]
    return plan
