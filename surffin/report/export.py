"""Results in forms other tools open: label images, class areas, point clouds and a one-page report.

Per scene: ``<scene>-labels.png`` (the filtered labels at sensor resolution, an
indexed PNG whose palette is the figures' class colours, unclassified black),
``<scene>-labels-legend.png``, ``<scene>-classes.csv`` (pixels, fraction and
area in m² per class, and the unclassified area by reason), ``<scene>.ply``
and ``<scene>-report.pdf``; per specimen ``<item>.ply``. A pixel's area is its
footprint on the surface: ``z² cos(α) / (fx fy cos θ)`` for depth ``z``, the
angle ``α`` of its ray to the optical axis and its angle of incidence ``θ``
(the pinhole's solid angle ``cos³α / (fx fy)`` at range ``z / cos α``, over
``cos θ``). The PLY files are binary little-endian with one float32 scalar
field per feature (``scalar_<name>``: CloudCompare's convention, kept as
attributes by Open3D), in the world frame when the reference view has a pose.
Every file is written atomically.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import xarray as xr

from surffin.io.files import write_atomically
from surffin.io.store import load_store, open_store
from surffin.method.camera_model import fit_camera_model
from surffin.method.classify import UNCLASSIFIED, UNCLASSIFIED_REASONS
from surffin.report.canvas import figure, save
from surffin.report.figures import class_colours, label_overlay, reference_view

__all__ = ["PLY_FIELDS", "pixel_area", "class_areas", "label_png", "write_ply", "export_results"]

log = logging.getLogger("surffin")

#: Feature variables written to the PLY files (as ``scalar_<name>``), with the class.
PLY_FIELDS = ("R0", "n", "variability", "class", "R0_uncertainty", "n_uncertainty")


def _focal_lengths(points: np.ndarray, camera: Mapping, y: np.ndarray, x: np.ndarray) -> tuple[float, float]:
    """Return the camera's fx, fy: its intrinsics, else those of the camera model fitted to the organized cloud."""
    intrinsics = camera.get("intrinsics")
    if intrinsics:
        return float(intrinsics["fx"]), float(intrinsics["fy"])
    model, _ = fit_camera_model(points, x, y)
    return model.fx, model.fy


def pixel_area(points: np.ndarray, aoi: np.ndarray, fx: float, fy: float) -> np.ndarray:
    """Each pixel's footprint on the surface, m² (NaN where its point or AOI is unknown).

    Parameters
    ----------
    points : (..., 3) ndarray
        Camera-frame points, metres.
    aoi : (...) ndarray
        Angle of incidence, radians.
    fx, fy : float
        Focal lengths, pixels.
    """
    points = np.asarray(points, dtype=np.float64)
    z = points[..., 2]
    cos_alpha = z / np.linalg.norm(points, axis=-1)
    area = z**2 * cos_alpha / (fx * fy * np.cos(np.asarray(aoi, dtype=np.float64)))
    return np.where((z > 0) & np.isfinite(area), area, np.nan)


def class_areas(label: np.ndarray, reason: np.ndarray, area: np.ndarray, classes: Sequence[str]) -> list[dict]:
    """Rows of the class table: per class, then per reason of the unclassified pixels.

    Each row: ``class``, ``pixels``, ``fraction`` (of all pixels), ``area_m2``
    (summed over the pixels whose area is known) and ``pixels_without_area``.
    """
    rows = [(name, label == index) for index, name in enumerate(classes)]
    rows += [
        (f"unclassified: {name}", (label == UNCLASSIFIED) & (reason == code))
        for code, name in enumerate(UNCLASSIFIED_REASONS, start=1)
    ]
    known = np.isfinite(area)
    return [
        {
            "class": name,
            "pixels": int(mask.sum()),
            "fraction": float(mask.sum() / label.size),
            "area_m2": float(area[mask & known].sum()),
            "pixels_without_area": int((mask & ~known).sum()),
        }
        for name, mask in rows
    ]


def _csv(rows: list[dict]) -> bytes:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(rows[0]), lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return buffer.getvalue().encode()


def _png_bytes(image) -> bytes:
    buffer = io.BytesIO()
    image.save(buffer, format="PNG")
    return buffer.getvalue()


def label_png(label: np.ndarray, classes: Sequence[str]) -> bytes:
    """Encode ``label`` as an indexed PNG: index 0 unclassified (black), ``i + 1`` class ``i`` in its figure colour."""
    from PIL import Image

    colours = class_colours(classes)
    palette = [0, 0, 0] + [round(255 * channel) for name in classes for channel in colours[name][:3]]
    image = Image.fromarray((np.asarray(label) + 1).astype(np.uint8), mode="P")
    image.putpalette(palette)
    return _png_bytes(image)


def _legend(classes: Sequence[str], path: Path) -> Path:
    from matplotlib.patches import Patch

    colours = class_colours(classes)
    handles = [Patch(facecolor=colours[name], label=f"{index + 1}: {name}") for index, name in enumerate(classes)]
    handles.insert(0, Patch(facecolor="black", label="0: unclassified"))
    fig = figure(2.6, 0.35 * len(handles) + 0.5, layout=None)
    fig.legend(handles=handles, loc="center", title="PNG index: class", frameon=False)
    return save(fig, path)


def write_ply(path: Path, points: np.ndarray, fields: Mapping[str, np.ndarray]) -> Path:
    """Write points (N, 3) with float32 scalar fields ``scalar_<name>`` as a binary little-endian PLY, atomically."""
    from plyfile import PlyData, PlyElement

    names = [("x", "f4"), ("y", "f4"), ("z", "f4"), *((f"scalar_{name}", "f4") for name in fields)]
    vertex = np.empty(len(points), dtype=names)
    for axis, name in enumerate("xyz"):
        vertex[name] = points[:, axis]
    for name, values in fields.items():
        vertex[f"scalar_{name}"] = values
    buffer = io.BytesIO()
    PlyData([PlyElement.describe(vertex, "vertex")], byte_order="<", comments=["written by surffin"]).write(buffer)
    write_atomically(path, buffer.getvalue())
    return path


def _cloud(features: xr.Dataset, ingest: xr.Dataset, label: np.ndarray) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Return the reference view's valid points (world frame when posed) and their fields."""
    reference = reference_view(ingest, features["R0"])[0]
    points = reference["xyz"].transpose("y", "x", "axis").values.astype(np.float64)
    ok = reference["valid"].values & np.isfinite(points).all(axis=-1)
    pose = reference["pose"].values if "pose" in reference else np.full((4, 4), np.nan)
    selected = points[ok]
    if np.isfinite(pose).all():
        selected = selected @ pose[:3, :3].T + pose[:3, 3]
    fields = {
        name: (label if name == "class" else features[name].values)[ok].astype(np.float32)
        for name in PLY_FIELDS
        if name == "class" or name in features
    }
    return selected, fields


def _report(
    path: Path, scene: str, labels: xr.Dataset, background: np.ndarray, rows: list[dict], context: Mapping
) -> Path:
    """Draw the scene's one-page PDF: label map over the intensity, class table, accuracy, provenance."""
    fig = figure(8.27, 11.69, layout=None)
    ax = fig.add_axes((0.08, 0.52, 0.84, 0.40))
    label = labels["label_filtered"]
    finite = background[np.isfinite(background)]
    low, high = np.percentile(finite, (1, 99)) if finite.size else (0.0, 1.0)
    extent = (label.x.values[0] - 0.5, label.x.values[-1] + 0.5, label.y.values[-1] + 0.5, label.y.values[0] - 0.5)
    ax.imshow(background, cmap="gray", vmin=low, vmax=high, extent=extent, interpolation="nearest")
    ax.imshow(label_overlay(label.values, context["classes"]), extent=extent, interpolation="nearest")
    ax.set_title(f"scene {scene}: labels after the filter over the reference view's intensity (black: unclassified)")
    ax.set_xlabel("sensor column x (px)")
    ax.set_ylabel("sensor row y (px)")
    table = fig.add_axes((0.08, 0.24, 0.84, 0.22))
    table.axis("off")
    cells = [[r["class"], f"{r['pixels']}", f"{100 * r['fraction']:.2f}", f"{r['area_m2']:.4f}"] for r in rows]
    headers = ["class", "pixels", "share %", "area m²"]
    shown = table.table(cellText=cells, colLabels=headers, colWidths=[0.46, 0.18, 0.18, 0.18], loc="upper center")
    shown.auto_set_font_size(False)
    shown.set_fontsize(8)
    lines = [context["accuracy"], *context["provenance"]]
    fig.text(0.08, 0.20, "\n".join(lines), fontsize=7.5, va="top", family="monospace", wrap=True)
    fig.suptitle(f"surffin: surface finish of scene {scene}")
    return save(fig, path)


def _accuracy_line(scores: Mapping | None) -> str:
    accuracy = (scores or {}).get("accuracy", {}).get("label_filtered")
    if not accuracy:
        return "accuracy: no truth for this scene"
    return (
        f"accuracy against truth (label_filtered): {100 * accuracy['accuracy']:.2f} % of {accuracy['n_scored']} "
        "scored pixels (unclassified counts as wrong)"
    )


def _provenance(labels: xr.Dataset, calibration: Path) -> list[str]:
    lines = [
        f"campaign: {labels.attrs.get('campaign', '?')}",
        f"surffin {labels.attrs.get('surffin_version', '?')}",
        f"labels made with {json.dumps(labels.attrs.get('surffin_parameters'))}",
    ]
    if (calibration / "zarr.json").is_file():
        attrs = open_store(calibration).attrs
        fitted = {key: attrs.get(key) for key in ("scale_k", "reference_reflectance", "surffin_version")}
        lines.append(f"calibration: {calibration} {json.dumps(fitted)}")
    return lines


def _item_store(processed: Path, folder: str, name: str) -> xr.Dataset:
    """Load an item's store into memory (:func:`~surffin.io.store.load_store`)."""
    return load_store(processed / folder / f"{name}.zarr")


def _specimen_ply(name: str, features: xr.Dataset, processed: Path, out: Path, classes: Sequence[str]) -> Path:
    own = classes.index(features.attrs["class"]) if features.attrs.get("class") in classes else UNCLASSIFIED
    label = np.full(features["R0"].shape, own, dtype=np.int16)
    points, fields = _cloud(features, _item_store(processed, "ingest", name), label)
    return write_ply(out / f"{name}.ply", points, fields)


def _scene(name: str, processed: Path, out: Path, classes: Sequence[str], context: Mapping) -> list[Path]:
    labels = _item_store(processed, "labels", name)
    features = _item_store(processed, "features", name)
    ingest = _item_store(processed, "ingest", name)
    label = labels["label_filtered"].values
    reference = reference_view(ingest, labels["label"])[0]
    points = reference["xyz"].transpose("y", "x", "axis").values
    aoi = reference_view(_item_store(processed, "aoi", name), labels["label"])[0]["aoi"].values
    fx, fy = _focal_lengths(points, features.attrs.get("camera", {}), labels.y.values, labels.x.values)
    rows = class_areas(label, labels["unclassified_reason"].values, pixel_area(points, aoi, fx, fy), classes)
    paths = {kind: out / f"{name}{kind}" for kind in ("-classes.csv", "-labels.png", ".ply", "-report.pdf")}
    write_atomically(paths["-classes.csv"], _csv(rows))
    write_atomically(paths["-labels.png"], label_png(label, classes))
    legend = _legend(classes, out / f"{name}-labels-legend.png")
    write_ply(paths[".ply"], *_cloud(features, ingest, label))
    context = {**context, "classes": classes, "provenance": _provenance(labels, context["calibration"])}
    _report(paths["-report.pdf"], name, labels, reference["intensity"].values.astype(np.float64), rows, context)
    return [*paths.values(), legend]


def export_results(
    processed: str | os.PathLike, out: str | os.PathLike, *, calibration: str | os.PathLike | None = None
) -> list[Path]:
    """Write the exports of every scene (``labels/``) and specimen (``features/``) of a processed folder.

    Parameters
    ----------
    processed : path-like
        A processed folder of a complete run (``training.zarr``, and per item
        its ``ingest``, ``aoi`` and ``features`` stores; per scene ``labels``;
        ``summary.json`` and ``calibration.zarr`` when there).
    out : path-like
        The folder written; made if missing. Existing files of the same names are replaced.
    calibration : path-like, optional
        The calibration store the reports name (default ``<processed>/calibration.zarr``).

    Returns
    -------
    list of Path
        The files written.

    Raises
    ------
    StoreError
        A store the export needs is missing or not a store.
    """
    processed, out = Path(processed), Path(out)
    calibration = Path(calibration) if calibration is not None else processed / "calibration.zarr"
    classes = list(open_store(processed / "training.zarr", stage="training").attrs["classes"])
    summary_path = processed / "summary.json"
    summary = json.loads(summary_path.read_text()) if summary_path.is_file() else {}
    scenes = sorted(path.name.removesuffix(".zarr") for path in (processed / "labels").glob("*.zarr"))
    items = sorted(path.name.removesuffix(".zarr") for path in (processed / "features").glob("*.zarr"))
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for name in scenes:
        scores = summary.get("scenes", {}).get(name)
        context = {"accuracy": _accuracy_line(scores), "calibration": calibration}
        written += _scene(name, processed, out, classes, context)
        log.info("export: scene %s written to %s", name, out)
    for name in (item for item in items if item not in scenes):
        features = _item_store(processed, "features", name)
        if features.attrs.get("kind") == "specimen":
            written.append(_specimen_ply(name, features, processed, out, classes))
    log.info("export: %d files in %s", len(written), out)
    return written
