"""Render and write a synthetic campaign with its ground truth.

:func:`simulate_campaign` renders the acquisitions of
:func:`~surffin.simulate.plan.plan_campaign` one view at a time, writes them as
a campaign (CAMPAIGN.md layout) and, outside it, the truth stores of
:mod:`~surffin.simulate.truth`; ``campaign.yaml`` comes last. The repeat
calibration set (``Preset.repeat_calibration``) is written into its own folders
(:data:`~surffin.simulate.plan.REPEAT_FOLDERS`), which ``campaign.yaml`` does not
name: it is no view of any item, only a second calibration of the same camera.

The camera's imperfections (:class:`~surffin.simulate.imperfections.Imperfections`)
change what the files say, never the truth: the views are rendered through the
true lens from the true poses, and the truth stores hold the true geometry.
"""

from __future__ import annotations

import dataclasses
import io
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from surffin.errors import CampaignError
from surffin.io.files import write_atomically
from surffin.io.store import provenance, write_store
from surffin.io.viewfile import META_SUFFIX, VIEW_SUFFIXES, sidecar_path, write_view
from surffin.simulate.camera import PinholeCamera
from surffin.simulate.imperfections import Imperfections, perturb_pose
from surffin.simulate.instrument import Instrument, draw_instrument, observe
from surffin.simulate.plan import Acquisition, plan_campaign
from surffin.simulate.presets import PRESETS, Preset
from surffin.simulate.scene import Geometry, Scene, keyed_rng, render
from surffin.simulate.truth import (
    instrument_truth,
    item_truth,
    reference_coordinates,
    scene_truth_label,
)
from surffin.simulate.validation import FORMATS, UNITS

__all__ = ["simulate_campaign"]

_CYCLE = ("npz", "ply", "raw")
_PROGRESS_STEPS = 10
#: File name of a scene's truth labels, in its views folder.
_SCENE_TRUTH = "truth.npz"


def _inscribed_roi(mask: np.ndarray, where: str) -> dict[str, list[int]]:
    """Shrink the bounding box of ``mask`` evenly until every pixel inside is True; return it as a roi."""
    rows = np.flatnonzero(mask.any(axis=1))
    columns = np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        raise CampaignError(f"{where}: the roi face is not visible in the reference view; change the preset")
    y0, y1, x0, x1 = rows[0], rows[-1] + 1, columns[0], columns[-1] + 1
    while y0 < y1 and x0 < x1 and not mask[y0:y1, x0:x1].all():
        y0, y1, x0, x1 = y0 + 1, y1 - 1, x0 + 1, x1 - 1
    if y0 >= y1 or x0 >= x1:
        raise CampaignError(f"{where}: no rectangle fits inside the roi face; change the preset")
    return {"y": [int(y0), int(y1)], "x": [int(x0), int(x1)]}


def _roi(acquisition: Acquisition, reference: Geometry, margin: float) -> dict[str, list[int]]:
    """Pixels of the acquisition's roi face at least ``margin`` from its edges, as a roi."""
    face = [face.name for face in acquisition.faces].index(acquisition.roi_face)
    mask = (reference.face == face) & (reference.edge_distance >= margin)
    return _inscribed_roi(mask, f"{acquisition.folder} ({acquisition.roi_face})")


def _check_repeat_panel(acquisition: Acquisition, reference: Geometry, roi: dict[str, list[int]]) -> None:
    """Refuse a repeat panel pose from which the panel does not fill the roi of ``campaign.yaml``."""
    face = [face.name for face in acquisition.faces].index(acquisition.roi_face)
    rows, columns = slice(*roi["y"]), slice(*roi["x"])
    if not (reference.face[rows, columns] == face).all():
        raise CampaignError(
            f"{acquisition.folder}: the reference panel does not fill the roi {roi} in the repeat calibration "
            f"views; lower the preset's repeat_shift, repeat_turn or roll"
        )


def _file_names(acquisition: Acquisition, fmt: str) -> list[str]:
    """Names of the view files of an acquisition, in view order."""
    forms = (_CYCLE[index % len(_CYCLE)] if fmt == "mixed" else fmt for index in range(len(acquisition.stems)))
    return [f"{stem}.{form}" for stem, form in zip(acquisition.stems, forms)]


def _npz_bytes(**arrays: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.savez(buffer, allow_pickle=False, **arrays)
    return buffer.getvalue()


class _Progress:
    """Views rendered / total, on stderr, about every tenth of the way."""

    def __init__(self, total: int):
        self.total = total
        self.done = 0
        self.step = max(1, total // _PROGRESS_STEPS)
        self.start = time.perf_counter()

    def advance(self) -> None:
        self.done += 1
        if self.done % self.step == 0 or self.done == self.total:
            elapsed = time.perf_counter() - self.start
            print(f"simulate: {self.done}/{self.total} views rendered ({elapsed:.1f} s)", file=sys.stderr)


@dataclasses.dataclass(frozen=True)
class _Run:
    """What every acquisition of one simulate_campaign call shares."""

    preset: Preset
    seed: int
    camera: PinholeCamera
    instrument: Instrument
    imperfections: Imperfections
    fmt: str
    units: str
    poses: bool
    directory: Path
    truth: Path
    parameters: dict
    textures: dict
    progress: _Progress


def _acquire(acquisition: Acquisition, run: _Run) -> Geometry:
    """Render, observe and write every view of an acquisition, and its truth store.

    Returns
    -------
    Geometry
        Noise-free rendering of the reference view (``acquisition.reference``).
    """
    camera, imperfections = run.camera, run.imperfections
    scene = Scene(acquisition.faces, run.seed, run.textures)
    folder = run.directory / acquisition.folder
    folder.mkdir(parents=True, exist_ok=True)
    per_view = []
    reference_pose = acquisition.poses[acquisition.reference]
    views = zip(acquisition.stems, _file_names(acquisition, run.fmt), acquisition.poses)
    for index, (stem, name, pose) in enumerate(views):
        geometry = render(scene, camera, pose)
        rng = keyed_rng(run.seed, "view", acquisition.name, stem)
        xyz, intensity = observe(geometry, run.instrument, run.preset, rng, imperfections)
        recorded = pose if imperfections.pose_error is None else perturb_pose(pose, *imperfections.pose_error, rng)
        write_view(
            folder / name,
            xyz,
            intensity.astype(np.float32),
            units=run.units,
            pose=recorded if run.poses else None,
            abcy16=_abcy16(imperfections),
        )
        if imperfections.settings:
            settings = json.dumps(dict(imperfections.settings)).encode("utf-8")
            write_atomically(sidecar_path(folder / name, META_SUFFIX), settings)
        run.progress.advance()
        if index == acquisition.reference:
            reference = geometry
        if acquisition.has_truth:
            u_ref, v_ref = reference_coordinates(scene, camera, reference_pose, geometry)
            per_view.append((geometry.aoi, u_ref, v_ref))
    if acquisition.has_truth:
        aoi, u_ref, v_ref = (np.stack(arrays) for arrays in zip(*per_view))
        store = item_truth(acquisition, run.preset, reference, aoi, u_ref, v_ref)
        write_store(store.assign_attrs(provenance("simulate", run.parameters)), run.truth / f"{acquisition.name}.zarr")
    return reference


def _views_entry(acquisition: Acquisition) -> dict:
    """Return ``views``, and ``reference`` unless it is the first view (campaign.yaml's default)."""
    entry = {"views": acquisition.folder}
    if acquisition.reference != 0:
        entry["reference"] = acquisition.reference_stem
    return entry


def _describe(acquisition: Acquisition, reference: Geometry, run: _Run) -> dict:
    """Describe an acquisition by its campaign.yaml entry (writing a scene's truth file)."""
    preset = run.preset
    if acquisition.kind == "wall":
        return {"wall": acquisition.folder}
    if acquisition.kind == "reference":
        roi = _roi(acquisition, reference, preset.label_margin)
        return {"reference": {"views": acquisition.folder, "reflectance": float(preset.reference.R0), "roi": roi}}
    if acquisition.kind == "specimen":
        specimen = acquisition.specimen
        entry = {
            "class": specimen.cls,
            **_views_entry(acquisition),
            "roi": _roi(acquisition, reference, preset.label_margin),
        }
        if specimen.roughness_mm is not None:
            entry["roughness_mm"] = specimen.roughness_mm
        return entry
    truth = f"{acquisition.folder}/{_SCENE_TRUTH}"
    label = scene_truth_label(reference, preset.label_margin)
    write_atomically(run.directory / truth, _npz_bytes(label=label, classes=np.array(preset.classes)))
    return {**_views_entry(acquisition), "truth": truth}


def _check_target(directory: Path, truth: Path, plan: list[Acquisition], fmt: str) -> None:
    """Refuse to write over a campaign, or beside view files this campaign would not write."""
    existing = directory / "campaign.yaml"
    if existing.exists():
        raise CampaignError(
            f"{existing}: a campaign already exists here; simulate_campaign never overwrites one, "
            f"choose a new or empty directory"
        )
    if truth.resolve().is_relative_to(directory.resolve()):
        raise ValueError(f"truth directory {truth} lies inside the campaign {directory}; choose a path outside it")
    for acquisition in plan:
        folder = directory / acquisition.folder
        if not folder.is_dir():
            continue
        planned = {*_file_names(acquisition, fmt), _SCENE_TRUTH if acquisition.kind == "scene" else None}
        stale = sorted(
            entry.name
            for entry in folder.iterdir()
            if entry.suffix in VIEW_SUFFIXES and not entry.name.startswith(".") and entry.name not in planned
        )
        if stale:
            raise CampaignError(
                f"{folder}: holds view files this campaign would not write ({', '.join(stale[:5])}"
                f"{', ...' if len(stale) > 5 else ''}), left by another run; remove the folder or choose "
                f"another directory"
            )


def _abcy16(imperfections: Imperfections) -> dict | None:
    """Return the ABCY16 encoding of raw files: signed when asked, else None (the camera's usual one)."""
    return None if imperfections.signed_raw is None else {"signed": True, "scale": imperfections.signed_raw}


def _camera_entry(camera: PinholeCamera, units: str, imperfections: Imperfections, fmt: str) -> dict:
    """Return campaign.yaml's ``camera`` section: what the imperfections let the files say of the camera."""
    entry = {"width": camera.width, "height": camera.height, "units": units}
    if imperfections.intrinsics != "none":
        entry["intrinsics"] = camera.intrinsics()
        if imperfections.intrinsics == "pinhole":
            entry["intrinsics"].pop("distortion", None)
    if fmt in ("raw", "mixed") and imperfections.signed_raw is not None:
        entry["abcy16"] = _abcy16(imperfections)
    if imperfections.saturation is not None and imperfections.saturation_known:
        entry["saturation"] = float(imperfections.saturation)
    if imperfections.match_settings:
        entry["match_settings"] = [name for name, _ in imperfections.settings]
    return entry


def _resolve_preset(preset: str | Preset) -> Preset:
    if isinstance(preset, Preset):
        return preset
    if preset not in PRESETS:
        raise ValueError(f"preset {preset!r} is not known; expected one of {sorted(PRESETS)} or a Preset")
    return PRESETS[preset]


def simulate_campaign(
    directory: str | os.PathLike,
    preset: str | Preset = "paper",
    seed: int = 0,
    *,
    fmt: str = "npz",
    units: str = "m",
    poses: bool = True,
    truth: str | os.PathLike | None = None,
    imperfections: Imperfections | None = None,
) -> Path:
    """Render a synthetic campaign with known truth.

    Parameters
    ----------
    directory : path-like
        The campaign directory, created if missing. It must not hold a
        ``campaign.yaml`` (a campaign is never overwritten), nor view files of
        another run in the folders this campaign writes.
    preset : str or Preset
        A name of :data:`~surffin.simulate.presets.PRESETS` (``"paper"``,
        ``"tiny"``) or a :class:`Preset` (e.g. a ``dataclasses.replace`` variant).
    seed : int
        Same seed, same preset and options: byte-identical files. Every view,
        texture and the instrument draw from their own keyed random stream, so
        a view does not depend on which other views are rendered.
    fmt : {"npz", "ply", "raw", "mixed"}
        View file form; ``mixed`` takes npz, ply, raw in turn within every item.
    units : {"m", "mm"}
        Unit of xyz and pose translations in npz and ply files (raw is always mm).
    poses : bool
        Write each view's camera-to-world pose (npz: inside; ply, raw: sidecar).
    truth : path-like, optional
        Folder of the truth stores; default ``<directory>-truth``, beside the
        campaign (never inside it).
    imperfections : Imperfections, optional
        The real camera's imperfections to render; default none (an ideal
        camera). The truth stays the true geometry.

    Returns
    -------
    Path
        The campaign's ``campaign.yaml``, written last and atomically: its
        presence means the campaign is complete.

    Raises
    ------
    CampaignError
        ``directory`` already holds a campaign, or stale view files.
    ValueError
        Unknown preset, format or units, a negative seed, ``truth`` inside
        ``directory``, or signed raw files asked of a campaign without raw files.
    """
    preset = _resolve_preset(preset)
    if fmt not in FORMATS:
        raise ValueError(f"fmt {fmt!r} is not a view file form; expected one of {FORMATS}")
    if units not in UNITS:
        raise ValueError(f"units {units!r} are not supported; expected one of {UNITS}")
    if int(seed) != seed or seed < 0:
        raise ValueError(f"seed {seed!r} must be an integer >= 0")
    seed = int(seed)
    imperfections = imperfections or Imperfections()
    if imperfections.signed_raw is not None and fmt not in ("raw", "mixed"):
        raise ValueError(f"signed raw files need fmt 'raw' or 'mixed', got fmt {fmt!r}")
    directory = Path(directory)
    truth = Path(truth) if truth is not None else directory.resolve().with_name(directory.resolve().name + "-truth")
    plan = plan_campaign(preset, seed)
    _check_target(directory, truth, plan, fmt)

    camera = dataclasses.replace(preset.camera, distortion=imperfections.distortion)
    instrument = draw_instrument(
        camera, preset.coef_mean, preset.coef_variability, preset.gain, keyed_rng(seed, "instrument")
    )
    parameters = {"preset": dataclasses.asdict(preset), "seed": seed, "fmt": fmt, "units": units, "poses": poses}
    if imperfections.any:
        parameters["imperfections"] = dataclasses.asdict(imperfections)
    write_store(
        instrument_truth(instrument, preset, imperfections.systematics).assign_attrs(
            provenance("simulate", parameters)
        ),
        truth / "instrument.zarr",
    )
    run = _Run(
        preset=preset,
        seed=seed,
        camera=camera,
        instrument=instrument,
        imperfections=imperfections,
        fmt=fmt,
        units=units,
        poses=poses,
        directory=directory,
        truth=truth,
        parameters=parameters,
        textures={},
        progress=_Progress(sum(len(acquisition.poses) for acquisition in plan)),
    )
    config: dict = {
        "name": f"synthetic {preset.name} campaign, seed {seed}",
        "camera": _camera_entry(camera, units, imperfections, fmt),
    }
    if preset.crop is not None:
        config["crop"] = {"y": list(preset.crop[0]), "x": list(preset.crop[1])}
    config.update(calibration={}, specimens={}, scenes={})
    for acquisition in plan:
        reference = _acquire(acquisition, run)
        if acquisition.repeat:
            if acquisition.kind == "reference":
                _check_repeat_panel(acquisition, reference, config["calibration"]["reference"]["roi"])
            continue
        entry = _describe(acquisition, reference, run)
        if acquisition.kind in ("wall", "reference"):
            config["calibration"].update(entry)
        else:
            config[f"{acquisition.kind}s"][acquisition.name] = entry
    path = directory / "campaign.yaml"
    write_atomically(path, yaml.safe_dump(config, sort_keys=False, default_flow_style=None).encode("utf-8"))
    return path
