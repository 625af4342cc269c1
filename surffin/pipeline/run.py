"""Stage entry points: campaign or stores in, one complete store out.

Each function here is what one workflow rule runs (through a short script in
``workflow/scripts/``); they are plain Python and usable without snakemake.
:func:`run_stage` serves every per-item stage of :mod:`surffin.method.stages`: it
opens the input stores, runs the stage under the chosen dask scheduler with
progress in the log, and writes the output store atomically with provenance.
:func:`run_item` runs an item's whole chain (ingest to features) in one
process, writing the same stores; :func:`run_items` the chains of a batch of items.
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from surffin.method import stages
from surffin.errors import StoreError
from surffin.grid import Roi
from surffin.io.files import write_json
from surffin.io.store import open_store, provenance, write_store
from surffin.pipeline.jobs import dask_scheduler, logging_to

__all__ = [
    "STAGES",
    "run_ingest",
    "run_stage",
    "ITEM_CHAIN",
    "run_item",
    "run_items",
    "run_calibration",
    "check_calibration",
    "run_training",
    "run_summary",
    "run_roughness_relation",
    "run_roughness_map",
]

log = logging.getLogger("surffin")

#: Percentiles of each specimen's pixel n whose span over the specimens the roughness relation supports.
SUPPORT_PERCENTILES = (2, 98)

#: Per-item stages run by :func:`run_stage`: name -> stage function.
STAGES = {
    "aoi": stages.aoi_stage,
    "reflectance": stages.reflectance_stage,
    "registration": stages.registration_stage,
    "features": stages.features_stage,
    "labels": stages.labels_stage,
    "roughness": stages.roughness_stage,
}

#: An item's chain after its ingest, as :func:`run_item` runs it: (stage, output store,
#: input stores by the stage function's argument names); ``calibration`` is the campaign's.
ITEM_CHAIN = (
    ("aoi", "aoi", ("ingest",)),
    ("reflectance", "reflectance", ("ingest", "aoi", "calibration")),
    ("registration", "registered", ("ingest", "aoi", "reflectance")),
    ("features", "features", ("registered", "reflectance", "aoi")),
)


def _timed_write(ds, output, chunks) -> Path:
    start = time.perf_counter()
    path = write_store(ds, output, chunks=chunks)
    log.info("wrote %s in %.2f s", path, time.perf_counter() - start)
    return path


# Jobs read the campaign without checking every view file's header (check_views=False): that
# costs ~3 ms a file, for every item's job, and the files a job reads are checked as they are
# read (viewfile.read_view); `surffin check` and the workflow's start check them all once.


def _ingest(campaign, item, store, chunks) -> Path:
    from surffin.io.campaign import read_campaign
    from surffin.io.ingest import ingest_item

    start = time.perf_counter()
    camp = read_campaign(campaign, require_calibration=False, check_views=False)
    ds = ingest_item(camp, item)
    log.info("ingest %s: %d views, cube %s", item, ds.sizes["view"], dict(ds.sizes))
    # The cube is in memory: writing it needs no worker threads (nor a dask.distributed
    # client, which dask looks for, importing it, when no scheduler is set).
    with dask_scheduler("synchronous"):
        path = _timed_write(ds, store, chunks)
    log.info("ingest done in %.2f s", time.perf_counter() - start)
    return path


def _stage(stage, output, stores, params, chunks) -> Path:
    start = time.perf_counter()
    inputs = {name: open_store(path) for name, path in stores.items()}
    log.info("%s: inputs %s, parameters %s", stage, {k: str(v) for k, v in stores.items()}, params)
    ds = STAGES[stage](**inputs, **params)
    ds.attrs = {
        **ds.attrs,
        **provenance(stage, params, {name: str(path) for name, path in stores.items()}),
    }
    path = _timed_write(ds, output, chunks)
    log.info("%s done in %.2f s", stage, time.perf_counter() - start)
    return path


def run_ingest(
    campaign: str | os.PathLike,
    item: str,
    store: str | os.PathLike,
    *,
    chunks: Mapping[str, int] | None = None,
    log_path: str | os.PathLike | None = None,
) -> Path:
    """Read an item's view files and write its ingest store (``ingest/<item>.zarr``)."""
    with logging_to(log_path):
        return _ingest(campaign, item, store, chunks)


def run_stage(
    stage: str,
    output: str | os.PathLike,
    *,
    stores: Mapping[str, str | os.PathLike],
    params: Mapping | None = None,
    chunks: Mapping[str, int] | None = None,
    scheduler: str | None = None,
    threads: int = 1,
    log_path: str | os.PathLike | None = None,
) -> Path:
    """Run one per-item stage from its input stores to its output store.

    Parameters
    ----------
    stage : str
        A key of :data:`STAGES`.
    output : path-like
        The output store.
    stores : mapping of str to path-like
        Input stores by the stage function's argument names (``ingest``,
        ``aoi``, ``reflectance``, ``registered``, ``calibration``, ...).
    params : mapping, optional
        Keyword parameters of the stage function; recorded in the store.
    chunks : mapping, optional
        Chunk sizes over ``y``/``x`` of the output store.
    scheduler, threads
        See :func:`dask_scheduler`.
    log_path : path-like, optional
        The job's log file.
    """
    with logging_to(log_path), dask_scheduler(scheduler, threads):
        return _stage(stage, output, stores, dict(params or {}), chunks)


def run_item(
    campaign: str | os.PathLike,
    item: str,
    outputs: Mapping[str, str | os.PathLike],
    *,
    calibration: str | os.PathLike,
    params: Mapping[str, Mapping] | None = None,
    chunks: Mapping[str, int] | None = None,
    scheduler: str | None = None,
    threads: int = 1,
    log_path: str | os.PathLike | None = None,
) -> dict[str, Path]:
    """Run an item's whole chain, ingest to features, in this one process.

    Writes the same five stores as :func:`run_ingest` followed by
    :func:`run_stage` for each step of :data:`ITEM_CHAIN` (each store complete
    before the next stage reads it), but pays the start-up of a process once.

    Parameters
    ----------
    campaign, item
        As for :func:`run_ingest`.
    outputs : mapping of str to path-like
        The stores by name: ``ingest`` and every output name of :data:`ITEM_CHAIN`.
    calibration : path-like
        The calibration store.
    params : mapping of str to mapping, optional
        Each stage's parameters by stage name (a stage not named gets none).
    chunks, scheduler, threads, log_path
        As for :func:`run_stage`.

    Returns
    -------
    dict of str to Path
        The written stores by name.
    """
    return run_items(
        campaign, {item: outputs}, calibration=calibration, params={item: params or {}}, chunks=chunks,
        scheduler=scheduler, threads=threads, log_path=log_path,
    )[item]


def run_items(
    campaign: str | os.PathLike,
    items: Mapping[str, Mapping[str, str | os.PathLike]],
    *,
    calibration: str | os.PathLike,
    params: Mapping[str, Mapping[str, Mapping]] | None = None,
    chunks: Mapping[str, int] | None = None,
    scheduler: str | None = None,
    threads: int = 1,
    log_path: str | os.PathLike | None = None,
) -> dict[str, dict[str, Path]]:
    """Run the chains of several items one after another in this one process (a batch job).

    Each item's chain is :func:`run_item`'s; the process starts, and imports
    its modules, once for all of them.

    Parameters
    ----------
    items : mapping of str to mapping
        Item name -> its stores by name, as ``outputs`` of :func:`run_item`.
    params : mapping of str to mapping, optional
        Item name -> each stage's parameters by stage name (an item not named gets none).
    campaign, calibration, chunks, scheduler, threads, log_path
        As for :func:`run_item`; one log for all the items.

    Returns
    -------
    dict of str to dict of str to Path
        Item name -> the written stores by name.

    Raises
    ------
    ValueError
        Before anything is written, if an item's stores are not named as
        :func:`run_item` needs, parameters name a stage not in the chain, or
        parameters are given for an item not in ``items``.
    """
    params = dict(params or {})
    stages = {stage for stage, _, _ in ITEM_CHAIN}
    names = {"ingest", *(output for _, output, _ in ITEM_CHAIN)}
    problems = []
    if strangers := set(params) - set(items):
        problems.append(f"parameters given for items not in the batch: {sorted(strangers)}")
    for item, outputs in items.items():
        if set(outputs) != names:
            problems.append(f"{item}: outputs must be named {sorted(names)}, got {sorted(outputs)}")
        if unknown := set(params.get(item, {})) - stages:
            problems.append(f"{item}: parameters given for stages not in the chain: {sorted(unknown)}")
    if problems:
        raise ValueError("run_items: " + "; ".join(problems))
    with logging_to(log_path):
        start = time.perf_counter()
        for item, outputs in items.items():
            _item(campaign, item, outputs, calibration, params.get(item, {}), chunks, scheduler, threads)
        if len(items) > 1:
            log.info("batch of %d items done in %.2f s", len(items), time.perf_counter() - start)
        return {item: {name: Path(path) for name, path in outputs.items()} for item, outputs in items.items()}


def _item(campaign, item, outputs, calibration, params, chunks, scheduler, threads) -> None:
    start = time.perf_counter()
    _ingest(campaign, item, outputs["ingest"], chunks)
    # Inputs are recorded as given, as the per-stage rules record theirs.
    stores = {**outputs, "calibration": calibration}
    with dask_scheduler(scheduler, threads):
        for stage, output, inputs in ITEM_CHAIN:
            stores_in = {name: stores[name] for name in inputs}
            _stage(stage, outputs[output], stores_in, dict(params.get(stage, {})), chunks)
    log.info("item %s done in %.2f s", item, time.perf_counter() - start)


def run_calibration(
    campaign: str | os.PathLike,
    output: str | os.PathLike,
    *,
    params: Mapping | None = None,
    folders: Mapping[str, str] | None = None,
    log_path: str | os.PathLike | None = None,
) -> Path:
    """Fit the camera's radiometric calibration from a campaign's wall and panel views.

    ``folders`` (``{"wall", "reference"}``, relative to the campaign directory)
    fits another calibration set of the same camera instead of the campaign's
    ``calibration:`` section, e.g. a repeat set
    (:func:`surffin.method.calibration.calibration_set`).
    """
    from surffin.method.calibration import calibrate, calibration_set
    from surffin.io.campaign import read_campaign

    params = dict(params or {})
    with logging_to(log_path):
        camp = read_campaign(campaign, check_views=False)
        views = None if folders is None else calibration_set(camp, folders["wall"], folders["reference"])
        ds = calibrate(camp, calibration=views, **params)
        return _timed_write(ds, output, None)


def check_calibration(path: str | os.PathLike, campaign) -> None:
    """Check that a calibration store made by another campaign fits this campaign's camera.

    Raises
    ------
    StoreError
        The store is not a calibration, or its sensor grid is not this camera's
        (width x height), so it cannot cover the crop.
    """
    ds = open_store(path, stage="calibration")
    camera = campaign.camera
    grid = (ds.sizes.get("y"), ds.sizes.get("x"))
    if grid != (camera.height, camera.width):
        raise StoreError(
            f"{path}: calibration of a {grid[1]}x{grid[0]} sensor, but {campaign.path} describes a "
            f"{camera.width}x{camera.height} camera; use a calibration of the same camera"
        )
    rows, cols = campaign.crop.slices
    if not bool(ds["coef"].isel(y=rows, x=cols).notnull().any()):
        raise StoreError(f"{path}: no calibrated pixel inside the crop {campaign.crop} of {campaign.path}")


def run_training(
    output: str | os.PathLike,
    *,
    specimens: Mapping[str, Mapping],
    extra: tuple[str, ...] = (),
    max_per_class: int | None = None,
    log_path: str | os.PathLike | None = None,
) -> Path:
    """Pool the specimens' features (and other campaigns' training sets) into ``training.zarr``.

    Feature stores are opened lazily and read one at a time, and each class keeps
    at most ``max_per_class`` samples, so the job's memory does not grow with the
    number of specimens.

    Parameters
    ----------
    specimens : mapping
        Item name -> ``{"store": features store, "class": name, "roi": {"y", "x"} or None}``.
    extra : tuple of path-like
        Training stores of other campaigns to add.
    max_per_class : int, optional
        Cap on the samples of each class (:func:`surffin.method.classify.training_set`).
    """
    from surffin.method.classify import combine_training, training_set

    with logging_to(log_path):
        items = {
            name: (open_store(spec["store"], stage="features"), spec["class"], Roi.from_mapping(spec["roi"]))
            for name, spec in specimens.items()
        }
        ds = training_set(items, max_per_class=max_per_class)
        if extra:
            ds = combine_training(ds, *(open_store(path, stage="training") for path in extra), max_per_class=max_per_class)
        log.info("training set: %d samples of classes %s", ds.sizes["sample"], ds.attrs["classes"])
        parameters = {"extra": list(extra), "max_per_class": max_per_class}
        ds.attrs = {**ds.attrs, **provenance("training", parameters, {n: str(s["store"]) for n, s in specimens.items()})}
        return _timed_write(ds, output, {"sample": 1 << 20})


def _feature_statistics(ds) -> dict:
    """Mean, standard deviation, median and pixel count of each feature."""
    stats = {}
    for name in ("R0", "n", "variability"):
        values = ds[name].values
        finite = values[np.isfinite(values)]
        stats[name] = {"n_pixels": int(finite.size)}
        if finite.size:
            stats[name].update(mean=float(finite.mean()), std=float(finite.std()), median=float(np.median(finite)))
    return stats


def _features_region(spec: Mapping):
    """The features store of ``{"store", "roi"}``, lazily, cut to its roi when it has one."""
    from surffin.method.features import select_roi

    ds = open_store(spec["store"], stage="features")
    roi = Roi.from_mapping(spec["roi"])
    return ds if roi is None else select_roi(ds, roi)


def run_summary(
    output: str | os.PathLike,
    *,
    features: Mapping[str, Mapping],
    labels: Mapping[str, str | os.PathLike],
    truth: Mapping[str, Mapping],
    log_path: str | os.PathLike | None = None,
) -> Path:
    """Write ``summary.json``: per-item feature statistics, per-scene class fractions and accuracy.

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
    from surffin.io.campaign import read_truth
    from surffin.method.classify import class_fractions, score

    with logging_to(log_path):
        summary = {"items": {}, "scenes": {}}
        for name, spec in features.items():
            summary["items"][name] = {
                "region": "image" if spec["roi"] is None else "roi",
                **_feature_statistics(_features_region(spec).compute()),
            }
        for name, path in labels.items():
            ds = open_store(path, stage="labels").compute()
            classes = ds["label"].attrs["flag_meanings"].split()
            scene = {"class_fractions": {v: class_fractions(ds[v], classes) for v in ("label", "label_filtered")}}
            if name in truth:
                spec = truth[name]
                truth_label, truth_classes = read_truth(spec["path"], width=spec["width"], height=spec["height"])
                scene["accuracy"] = {v: score(ds[v], truth_label, truth_classes, classes) for v in ("label", "label_filtered")}
                log.info("%s: accuracy %s", name, {v: s["accuracy"] for v, s in scene["accuracy"].items()})
            summary["scenes"][name] = scene
        return write_json(output, summary)


def run_roughness_relation(
    output: str | os.PathLike,
    *,
    specimens: Mapping[str, Mapping],
    log_path: str | os.PathLike | None = None,
) -> Path:
    """Fit the specimens' relation of mean n and roughness into a JSON file.

    The relation's ``n_range``, where the map is not marked extrapolated, spans
    the specimens' pixels from the lowest 2nd to the highest 98th percentile
    of n (:data:`SUPPORT_PERCENTILES`).

    Parameters
    ----------
    specimens : mapping
        Item name -> ``{"store": features store, "roi": {"y", "x"} or None,
        "roughness_mm": float}``; only specimens with a roughness.
    """
    from surffin.method.roughness import roughness_relation

    with logging_to(log_path):
        mean_n, spans = {}, []
        for name, spec in specimens.items():
            n = _features_region(spec)["n"].values
            n = n[np.isfinite(n)]
            mean_n[name] = float(n.mean()) if n.size else float("nan")
            spans += list(np.percentile(n, SUPPORT_PERCENTILES)) if n.size else []
        relation = roughness_relation(
            mean_n, {name: spec["roughness_mm"] for name, spec in specimens.items()},
            n_range=(min(spans), max(spans)) if spans else None,
        )
        log.info(
            "roughness relation over %d specimens: n = %.4f %+.4f roughness_mm, R^2 %.4f",
            len(specimens), relation["intercept"], relation["slope"], relation["r2"],
        )
        relation["inputs"] = {name: str(spec["store"]) for name, spec in specimens.items()}
        return write_json(output, relation)


def run_roughness_map(
    output: str | os.PathLike,
    *,
    features: str | os.PathLike,
    relation: str | os.PathLike,
    chunks: Mapping[str, int] | None = None,
    scheduler: str | None = None,
    threads: int = 1,
    log_path: str | os.PathLike | None = None,
) -> Path:
    """Write an item's indicative roughness map from its features store and the relation JSON.

    The relation (of :func:`run_roughness_relation`) becomes the stage's
    parameter, so the store records the line it was made with.
    """
    params = {"relation": json.loads(Path(relation).read_text())}
    return run_stage(
        "roughness", output, stores={"features": features}, params=params,
        chunks=chunks, scheduler=scheduler, threads=threads, log_path=log_path,
    )
