"""Ingest: an item's view files as one cube with dims (view, y, x[, axis])."""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import xarray as xr

from surffin.errors import CampaignError
from surffin.grid import Roi
from surffin.io.campaign import Campaign
from surffin.io.store import provenance
from surffin.io.viewfile import View

__all__ = ["ingest_item", "build_cube", "describe_file"]

_CHUNK_BYTES = 1 << 20


def describe_file(path: str | Path) -> dict:
    """Size and SHA-256 of a file, for provenance.

    Returns
    -------
    dict
        ``{"size": bytes, "sha256": hex digest}``.
    """
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(_CHUNK_BYTES), b""):
            digest.update(block)
    return {"size": Path(path).stat().st_size, "sha256": digest.hexdigest()}


def build_cube(views: Sequence[View], crop: Roi) -> xr.Dataset:
    """Stack views into an ingest cube on the cropped sensor grid.

    Parameters
    ----------
    views : sequence of View
        Views of one item, all of the same sensor size, in view order.
    crop : Roi
        Half-open sensor ranges kept; ``y``/``x`` coordinates keep sensor indices.

    Returns
    -------
    Dataset
        ``xyz`` (view, y, x, axis) float32 metres, NaN where invalid;
        ``intensity`` (view, y, x) float32; ``valid`` (view, y, x) bool; and,
        when any view carries a pose, ``pose`` (view, row, col) float64
        camera-to-world in metres (NaN for views without one).
    """
    rows, cols = crop.slices
    stems = [view.path.stem for view in views]
    xyz = np.stack([view.xyz[rows, cols] for view in views]).astype(np.float32)
    intensity = np.stack([view.intensity[rows, cols] for view in views]).astype(np.float32)
    valid = np.stack([view.valid[rows, cols] for view in views])
    coords = {
        "view": stems,
        "y": np.arange(*crop.y),
        "x": np.arange(*crop.x),
        "axis": ["x", "y", "z"],
    }
    ds = xr.Dataset(
        {
            "xyz": (("view", "y", "x", "axis"), xyz, {"units": "m", "long_name": "point in the camera frame"}),
            "intensity": (("view", "y", "x"), intensity, {"units": "1", "long_name": "camera intensity"}),
            "valid": (("view", "y", "x"), valid, {"long_name": "pixel has a valid return"}),
        },
        coords=coords,
    )
    if any(view.pose is not None for view in views):
        nan_pose = np.full((4, 4), np.nan)
        poses = np.stack([nan_pose if view.pose is None else view.pose for view in views])
        ds["pose"] = (("view", "row", "col"), poses, {"units": "m", "long_name": "camera-to-world pose"})
    ds["y"].attrs = {"long_name": "sensor row"}
    ds["x"].attrs = {"long_name": "sensor column"}
    return ds


def ingest_item(campaign: Campaign, name: str) -> xr.Dataset:
    """Read, validate and stack the views of one item of a campaign.

    Parameters
    ----------
    campaign : Campaign
        From :func:`surffin.read_campaign`.
    name : str
        A specimen or scene name of that campaign.

    Returns
    -------
    Dataset
        The cube of :func:`build_cube` with attrs naming the item, its kind,
        class and reference view, the camera, the crop and provenance (surffin
        version, source files with sizes and checksums).
    """
    if name not in campaign.items:
        known = ", ".join(campaign.items) or "none"
        raise CampaignError(f"{campaign.path}: no item named {name!r}; the campaign has: {known}")
    item = campaign.items[name]
    ds = build_cube([campaign.read_view(path) for path in item.views], campaign.crop)
    inputs = {str(path.relative_to(campaign.root)): describe_file(path) for path in item.views}
    ds.attrs = {
        "item": item.name,
        "kind": item.kind,
        "class": item.cls or "",
        "reference_view": item.reference,
        "campaign": campaign.name,
        "camera": {
            "width": campaign.camera.width,
            "height": campaign.camera.height,
            "intrinsics": campaign.camera.intrinsics,
        },
        "crop": {"y": list(campaign.crop.y), "x": list(campaign.crop.x)},
        **provenance("ingest", inputs=inputs),
    }
    return ds
