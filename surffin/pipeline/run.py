"""Entry points of the workflow's jobs: campaign or stores in, one complete output out.

Each function here is what one workflow rule runs; they are plain Python and
usable without snakemake. :func:`run_stage` runs any stage of the table
(:mod:`surffin.pipeline.table`) whose inputs are stores: it opens them, runs the
stage under the chosen dask scheduler with progress in the log, and writes the
output store atomically with its provenance and the stage's code version.
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np

from surffin.grid import Roi
from surffin.io.files import write_json
from surffin.io.store import DEFAULT_CHUNKS, StoreCache, load_store, open_store, provenance, write_store
from surffin.io.zarrread import store_sizes
from surffin.method.stages import roughness_stage
from surffin.pipeline.jobs import dask_scheduler, logging_to
from surffin.pipeline.table import STAGES, stage_of

__all__ = [
    "run_default_campaign",
    "run_ingest",
    "run_stage",
    "run_calibration",
    "run_training",
    "run_summary",
    "run_roughness_relation",
    "run_roughness_map",
]

log = logging.getLogger("surffin")

#: The input stores a process's stage jobs loaded, kept for its next jobs: a worker running an item's
#: stages one after another (:func:`surffin.pipeline.jobs.in_worker`'s ``affinity``) reads each of the
#: item's stores once, and the calibration once for all items. A worker per core keeps up to 256 MiB
#: (a few items in flight and the calibration; 512 read no fewer stores in a 48-specimen run).
_LOADED = StoreCache(max_bytes=256 * 2**20)

#: Percentiles of each specimen's pixel n whose span over the specimens the roughness relation supports.
SUPPORT_PERCENTILES = (2, 98)


def _write(ds, output, chunks, stage: str) -> Path:
    """Write a stage's store with its code version (:data:`surffin.pipeline.table.STAGES`)."""
    start = time.perf_counter()
    ds.attrs["surffin_code_version"] = STAGES[stage].version
    path = write_store(ds, output, chunks=chunks)
    log.info("wrote %s in %.2f s", path, time.perf_counter() - start)
    return path


# Jobs read the campaign without checking every view file's header (check_views=False): that
# costs ~3 ms a file, for every item's job, and the files a job reads are checked as they are
# read (viewfile.read_view); `surffin check` and the workflow's start check them all once.


def run_default_campaign(
    directory: str | os.PathLike, *, preset: str, seed: int, log_path: str | os.PathLike | None = None
) -> Path:
    """Render the synthetic campaign a workflow runs by default into ``directory`` (the simulator's ``preset``)."""
    from surffin.simulate import simulate_campaign

    with logging_to(log_path):
        log.info("rendering the default campaign (preset %s, seed %d) into %s", preset, seed, directory)
        return simulate_campaign(directory, preset=preset, seed=seed)


def run_ingest(
    campaign: str | os.PathLike,
    item: str,
    store: str | os.PathLike,
    *,
    chunks: Mapping[str, int] | None = None,
    log_path: str | os.PathLike | None = None,
) -> Path:
    """Read an item's view files and write its ingest store (``ingest/<item>.zarr``)."""
    from surffin.io.campaign import read_campaign
    from surffin.io.ingest import ingest_item

    with logging_to(log_path):
        camp = read_campaign(campaign, require_calibration=False, check_views=False, items=[item])
        ds = ingest_item(camp, item)
        log.info("ingest %s: %d views, cube %s", item, ds.sizes["view"], dict(ds.sizes))
        return _write(ds, store, chunks, "ingest")


def _open_inputs(stores: Mapping[str, str | os.PathLike], chunks: Mapping[str, int] | None) -> dict:
    """Open a stage's input stores: into memory when the item's grid fits in one chunk, else as dask arrays.

    An item no larger than one chunk is one task per array, which dask neither parallelises nor
    bounds in memory, and its graphs cost about a tenth of the chain's CPU (docs/performance.md);
    a larger one keeps its chunks, so that the job's memory follows the chunks, not the item. The
    calibration covers the whole sensor, not the item's crop, and does not decide: the item's size is
    read from its stores' metadata before any is loaded. Stores loaded (by
    :func:`~surffin.io.store.load_store`) are kept for the process's next jobs (:data:`_LOADED`).
    """
    limits = {**DEFAULT_CHUNKS, **(chunks or {})}
    kept = {name: _LOADED.get(path) for name, path in stores.items()}
    sizes = [
        _sizes(path) if kept[name] is None else kept[name].sizes
        for name, path in stores.items()
        if name != "calibration"
    ]
    if all(size.get(dim, 1) <= limits[dim] for size in sizes for dim in ("y", "x")):
        return {name: _LOADED.keep(path) if kept[name] is None else kept[name] for name, path in stores.items()}
    return {name: open_store(path) for name, path in stores.items()}


def _sizes(path: str | os.PathLike) -> Mapping[str, int]:
    """Return the dimension sizes of the store at ``path``: from its metadata, or as xarray opens it."""
    sizes = store_sizes(path)
    return open_store(path, chunks=None).sizes if sizes is None else sizes


def run_stage(
    function: Callable,
    output: str | os.PathLike,
    *,
    stores: Mapping[str, str | os.PathLike],
    params: Mapping | None = None,
    chunks: Mapping[str, int] | None = None,
    scheduler: str | None = None,
    threads: int = 1,
    log_path: str | os.PathLike | None = None,
) -> Path:
    """Run a stage of the table from its input stores to its output store.

    Parameters
    ----------
    function : callable
        The stage's function (:func:`surffin.method.stages.aoi_stage`, ...), a
        ``function`` of :data:`surffin.pipeline.table.STAGES`.
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
        See :func:`surffin.pipeline.jobs.dask_scheduler`.
    log_path : path-like, optional
        The job's log file.

    Raises
    ------
    KeyError
        ``function`` is no stage of the table.
    ValueError
        ``stores`` are not the stage's inputs.
    """
    stage = stage_of(function)
    if set(stores) != set(stage.inputs):
        raise ValueError(f"stage {stage.name} reads the stores {list(stage.inputs)}, got {sorted(stores)}")
    params = dict(params or {})
    with logging_to(log_path), dask_scheduler(scheduler, threads):
        inputs = _open_inputs(stores, chunks)
        log.info("%s: inputs %s, parameters %s", stage.name, {k: str(v) for k, v in stores.items()}, params)
        ds = function(**inputs, **params)
        ds.attrs = {
            **ds.attrs,
            **provenance(stage.name, params, {name: str(path) for name, path in stores.items()}),
        }
        return _write(ds, output, chunks, stage.name)


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
    from surffin.io.campaign import read_campaign
    from surffin.method.calibration import calibrate, calibration_set

    params = dict(params or {})
    with logging_to(log_path):
        camp = read_campaign(campaign, check_views=False)
        views = None if folders is None else calibration_set(camp, folders["wall"], folders["reference"])
        ds = calibrate(camp, calibration=views, **params)
        return _write(ds, output, None, "calibration")


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
            name: (
                load_store(spec["store"], stage="features"),
                spec["class"],
                Roi.from_mapping(spec["roi"]),
            )
            for name, spec in specimens.items()
        }
        ds = training_set(items, max_per_class=max_per_class)
        if extra:
            ds = combine_training(
                ds, *(open_store(path, stage="training") for path in extra), max_per_class=max_per_class
            )
        log.info("training set: %d samples of classes %s", ds.sizes["sample"], ds.attrs["classes"])
        parameters = {"extra": list(extra), "max_per_class": max_per_class}
        ds.attrs = {
            **ds.attrs,
            **provenance("training", parameters, {n: str(s["store"]) for n, s in specimens.items()}),
        }
        return _write(ds, output, {"sample": 1 << 20}, "training")


def run_summary(
    output: str | os.PathLike,
    *,
    features: Mapping[str, Mapping],
    labels: Mapping[str, str | os.PathLike],
    truth: Mapping[str, Mapping],
    log_path: str | os.PathLike | None = None,
) -> Path:
    """Write ``summary.json``: per-item feature statistics, per-scene class fractions and accuracy.

    ``features``, ``labels`` and ``truth`` are those of :func:`surffin.analysis.summary.summarise`.
    """
    from surffin.analysis.summary import summarise

    with logging_to(log_path):
        return write_json(output, summarise(features, labels, truth))


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
    from surffin.analysis.summary import features_region
    from surffin.method.roughness import roughness_relation

    with logging_to(log_path):
        mean_n, spans = {}, []
        for name, spec in specimens.items():
            n = features_region(spec)["n"].values
            n = n[np.isfinite(n)]
            mean_n[name] = float(n.mean()) if n.size else float("nan")
            spans += list(np.percentile(n, SUPPORT_PERCENTILES)) if n.size else []
        relation = roughness_relation(
            mean_n,
            {name: spec["roughness_mm"] for name, spec in specimens.items()},
            n_range=(min(spans), max(spans)) if spans else None,
        )
        log.info(
            "roughness relation over %d specimens: n = %.4f %+.4f roughness_mm, R^2 %.4f",
            len(specimens),
            relation["intercept"],
            relation["slope"],
            relation["r2"],
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
        roughness_stage,
        output,
        stores={"features": features},
        params=params,
        chunks=chunks,
        scheduler=scheduler,
        threads=threads,
        log_path=log_path,
    )
