"""The run's summary: each item's feature statistics, each scene's class fractions and accuracy."""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping

import numpy as np
import xarray as xr

from surffin.grid import Roi
from surffin.io.campaign import read_truth
from surffin.io.store import load_store
from surffin.method.classify import class_fractions, score
from surffin.method.features import select_roi

__all__ = ["feature_statistics", "features_region", "summarise"]

log = logging.getLogger("surffin")


def feature_statistics(ds: xr.Dataset) -> dict:
    """Mean, standard deviation, median and pixel count of each feature."""
    stats = {}
    for name in ("R0", "n", "variability"):
        values = ds[name].values
        finite = values[np.isfinite(values)]
        stats[name] = {"n_pixels": int(finite.size)}
        if finite.size:
            stats[name].update(mean=float(finite.mean()), std=float(finite.std()), median=float(np.median(finite)))
    return stats


def features_region(spec: Mapping) -> xr.Dataset:
    """Load the features store of ``{"store", "roi"}``, cut to its roi when it has one.

    Loaded whole (:func:`~surffin.io.store.load_store`): an item's features are a few MB, read in a
    few ms, and one store's worth of dask chunking and graph costs more than reading it.
    """
    ds = load_store(spec["store"], stage="features")
    roi = Roi.from_mapping(spec["roi"])
    return ds if roi is None else select_roi(ds, roi)


def summarise(
    features: Mapping[str, Mapping],
    labels: Mapping[str, str | os.PathLike],
    truth: Mapping[str, Mapping],
) -> dict:
    """Per-item feature statistics, per-scene class fractions and accuracy (``summary.json``).

    Parameters
    ----------
    features : mapping
        Item name -> ``{"store": features store, "roi": {"y", "x"} or None}``; the
        statistics cover the roi where there is one, else the whole image.
    labels : mapping
        Scene name -> labels store.
    truth : mapping
        Scene name -> ``{"path": truth.npz, "width": int, "height": int}`` for scenes with truth.
    """
    summary = {"items": {}, "scenes": {}}
    for name, spec in features.items():
        summary["items"][name] = {
            "region": "image" if spec["roi"] is None else "roi",
            **feature_statistics(features_region(spec)),
        }
    for name, path in labels.items():
        ds = load_store(path, stage="labels")
        classes = ds["label"].attrs["flag_meanings"].split()
        scene = {"class_fractions": {v: class_fractions(ds[v], classes) for v in ("label", "label_filtered")}}
        if name in truth:
            spec = truth[name]
            truth_label, truth_classes = read_truth(spec["path"], width=spec["width"], height=spec["height"])
            scene["accuracy"] = {
                v: score(ds[v], truth_label, truth_classes, classes) for v in ("label", "label_filtered")
            }
            log.info("%s: accuracy %s", name, {v: s["accuracy"] for v, s in scene["accuracy"].items()})
        summary["scenes"][name] = scene
    return summary
