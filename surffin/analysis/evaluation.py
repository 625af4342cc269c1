"""The method against the truth of a synthetic campaign, beside what the data allow.

:func:`evaluate_campaign` runs a whole campaign in this process with the
stage parameters it is given (the workflow's come from :mod:`surffin.pipeline.parameters`):
the calibration, every item's chain, the training set of its specimens and the scenes' labels; then it scores
them against the simulator's truth (``<campaign>-truth``). Beside every item's
features it fits the same data with the true AOI and the true instrument
function (with the residual systematics the camera was rendered with, when the
truth records them), registered with the same maps (the ceiling: what the data
allow), so the gap between the two stays visible. ``benchmarks/bench_validation.py`` prints
it over the validation campaigns and seeds; the test suite asserts lower bounds
on small campaigns.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import numpy as np
import xarray as xr

from surffin.io.campaign import read_campaign, read_truth
from surffin.io.ingest import ingest_item
from surffin.io.store import open_store
from surffin.method.calibration import calibrate, correction_factor, instrument_function, reflectance
from surffin.method.classify import score, training_set
from surffin.method.registration import register
from surffin.method.stages import features_stage, labels_stage, process_item

__all__ = [
    "interior",
    "relative_errors",
    "instrument_response",
    "calibration_error",
    "evaluate_campaign",
    "risk_coverage",
]

#: Distance (m) and angles of incidence (deg) at which :func:`calibration_error` compares instrument functions.
CALIBRATION_CHECK = (0.45, (0.0, 20.0, 40.0))
#: Board pixels closer than this to a specimen (m) are left out of the board's rejection rate.
BOARD_MARGIN = 0.01


def interior(truth: xr.Dataset) -> xr.DataArray:
    """Specimen top pixels at least the truth's label margin from their edges (truth store of an item)."""
    return (truth["label"] >= 0) & (truth["edge_distance"] >= truth.attrs["label_margin"])


def relative_errors(features: xr.Dataset, truth: xr.Dataset) -> dict[str, np.ndarray]:
    """Relative errors of the smoothed R0 and n on the interior pixels of one item that have them.

    Returns
    -------
    dict
        ``R0``, ``n``: 1-D arrays of ``(feature - truth) / truth``; ``missing``: the
        share of interior pixels without both features.
    """
    truth = truth.sel(y=features.y, x=features.x)
    mask = interior(truth).values
    errors = {key: ((features[key].values - truth[key].values) / truth[key].values)[mask] for key in ("R0", "n")}
    finite = np.isfinite(errors["R0"]) & np.isfinite(errors["n"])
    out = {key: value[finite] for key, value in errors.items()}
    out["missing"] = float(1.0 - finite.mean()) if finite.size else float("nan")
    return out


def instrument_response(ds: xr.Dataset, factor: str, crop, distance: float, aoi: float) -> np.ndarray:
    """``k f(d, theta) c(d, theta)`` of every crop pixel at one distance (m) and AOI (rad).

    ``ds`` is a calibration (``factor="correction"``, its residual correction) or
    an instrument truth (``factor="systematic"``, the rendered systematics);
    without that variable c = 1.
    """
    rows, columns = crop.slices
    coef = ds["coef"].transpose("term", "y", "x").values[:, rows, columns]
    d, theta = np.full(coef.shape[1:], distance), np.full(coef.shape[1:], aoi)
    c = correction_factor(ds[factor], d, theta) if factor in ds else 1.0
    return ds.attrs["scale_k"] * instrument_function(coef, d, theta) * c


def calibration_error(calibration: xr.Dataset, instrument: xr.Dataset, crop) -> float:
    """Median relative error over the crop of the fitted ``k f(d, theta) c(d, theta)`` against the true one.

    At :data:`CALIBRATION_CHECK`'s distance, the worst of its angles: what
    every reflectance is divided by. The fitted side includes the calibration's
    residual correction, the true side the rendered systematics
    (:func:`instrument_response`).
    """
    distance, angles = CALIBRATION_CHECK
    worst = 0.0
    for theta in np.deg2rad(angles):
        ratio = instrument_response(calibration, "correction", crop, distance, theta) / instrument_response(
            instrument, "systematic", crop, distance, theta
        )
        worst = max(worst, float(np.nanmedian(np.abs(ratio - 1.0))))
    return worst


def _ceiling_features(item, ingest, chain, instrument, truth, feature_params) -> xr.Dataset:
    """Features of the same data with the true AOI and instrument function, registered with the same maps.

    The true instrument function includes the rendered systematics where the truth records them.
    """
    aoi = truth["aoi_view"].sel(y=ingest.y, x=ingest.x).astype(np.float32).where(ingest["valid"])
    refl = reflectance(
        ingest["intensity"],
        chain["aoi"]["distance"],
        aoi,
        instrument["coef"],
        instrument.attrs["scale_k"],
        instrument.get("systematic"),
    )
    refl = refl.where(ingest["valid"]).astype(np.float32)
    registered = register(
        xr.Dataset({"reflectance": refl, "aoi": aoi}).compute(), chain["registered"][["map_x", "map_y"]]
    )
    # the same variability feature as the method's: its noise model's relative noise, where it has one
    own = xr.Dataset({"reflectance": refl}).merge(chain["reflectance"].drop_vars("reflectance"))
    return features_stage(registered, own, chain["aoi"].assign(aoi=aoi), roi=item.roi, **feature_params).compute()


def _median_abs(parts: Sequence[np.ndarray]) -> float:
    values = np.concatenate(parts)
    return float(np.median(np.abs(values))) if values.size else float("nan")


def _board_rejection(label: xr.DataArray, truth: xr.Dataset, features: xr.Dataset) -> float:
    """Share of a scene's fitted board pixels (away from the specimens) left unclassified."""
    truth = truth.sel(y=label.y, x=label.x)
    board = (truth["surface"] == 0) & (truth["edge_distance"] > BOARD_MARGIN) & np.isfinite(features["R0"])
    count = int(board.sum())
    return float(((label < 0) & board).sum()) / count if count else float("nan")


def evaluate_campaign(
    directory: str | os.PathLike,
    *,
    calibration_params: Mapping,
    aoi_params: Mapping,
    feature_params: Mapping,
    label_params: Mapping,
    method: str,
    max_per_class: int | None,
    truth: str | os.PathLike | None = None,
    progress: Callable[[str], None] | None = None,
) -> dict:
    """Process a synthetic campaign in this process and score it against its truth.

    The workflow's parameters for a configuration are
    :func:`surffin.pipeline.parameters.evaluation_parameters`.

    Parameters
    ----------
    directory : path-like
        A campaign written by :func:`surffin.simulate_campaign`.
    calibration_params : mapping
        Keyword arguments of :func:`surffin.method.calibration.calibrate`.
    aoi_params : mapping
        Of :func:`surffin.method.stages.aoi_stage`.
    feature_params : mapping
        Of :func:`surffin.method.stages.features_stage` (without the item's roi).
    label_params : mapping
        Of :func:`surffin.method.stages.labels_stage` (``k``, ``filter_kind``
        and ``filter_size`` also serve the ceiling's and the reject-free labels).
    method : str
        Registration method (:func:`surffin.method.stages.registration_stage`).
    max_per_class : int or None
        Most training samples per class (:func:`surffin.method.classify.training_set`).
    truth : path-like, optional
        Its truth folder; default ``<directory>-truth``.
    progress : callable, optional
        Called with each item's name when it is done.

    Returns
    -------
    dict
        ``calibration_error``: :func:`calibration_error`; ``items``: per item, the
        median absolute relative error of R0 and n on its interior, of the
        ceiling's (``ceiling_R0``, ``ceiling_n``) and the share of interior pixels
        without features (``missing``); ``features``: the same medians pooled
        over every item; ``scenes``: per scene, the accuracy of ``label`` and
        ``label_filtered`` (unclassified = wrong), ``unclassified`` (share of the
        scored pixels), the reasons' counts, ``ceiling`` (accuracy of 1-NN on the
        ceiling's features after the filter) and ``board_rejected`` (share of the
        board's pixels unclassified); ``posterior`` and ``correct``: for every
        scored scene pixel with features, the class model's posterior of its
        k-NN class and whether that class is right (without the reject option);
        ``item_features`` (item -> features Dataset) and ``training``, to try
        other label settings on.
    """
    directory = Path(directory)
    truth_dir = Path(truth) if truth is not None else Path(f"{directory.resolve()}-truth")
    camp = read_campaign(directory)
    calibration = calibrate(camp, **calibration_params)
    instrument = open_store(truth_dir / "instrument.zarr").compute()
    features, ceiling, items, scene_truths = {}, {}, {}, {}
    pooled: dict[str, list] = {"R0": [], "n": [], "ceiling_R0": [], "ceiling_n": []}
    for name, item in camp.items.items():
        ingest = ingest_item(camp, name).compute()
        chain = process_item(
            ingest,
            calibration,
            roi=item.roi,
            method=method,
            **aoi_params,
            **feature_params,
        )
        item_truth = open_store(truth_dir / f"{name}.zarr").compute()
        if name in camp.scenes:
            scene_truths[name] = item_truth
        features[name] = chain["features"]
        ceiling[name] = _ceiling_features(item, ingest, chain, instrument, item_truth, feature_params)
        ours, best = relative_errors(features[name], item_truth), relative_errors(ceiling[name], item_truth)
        errors = {"R0": ours["R0"], "n": ours["n"], "ceiling_R0": best["R0"], "ceiling_n": best["n"]}
        for key, values in errors.items():
            pooled[key].append(values)
        items[name] = {key: _median_abs([values]) for key, values in errors.items()} | {"missing": ours["missing"]}
        if progress is not None:
            progress(name)
    cap = max_per_class
    training = training_set({n: (features[n], it.cls, it.roi) for n, it in camp.specimens.items()}, max_per_class=cap)
    best_training = training_set(
        {n: (ceiling[n], it.cls, it.roi) for n, it in camp.specimens.items()}, max_per_class=cap
    )
    classes = training.attrs["classes"]
    scenes, posterior, correct = {}, [], []
    for name, scene in camp.scenes.items():
        truth_label, truth_classes = read_truth(scene.truth, width=camp.camera.width, height=camp.camera.height)
        labels = labels_stage(features[name], training, **label_params)
        best = labels_stage(
            ceiling[name],
            best_training,
            filter_kind=label_params["filter_kind"],
            filter_size=label_params["filter_size"],
        )
        grid = truth_label[labels.y.values[:, None], labels.x.values[None, :]]
        scored = grid >= 0
        free = labels_stage(features[name], training, k=label_params["k"])
        truth_index = np.array([classes.index(c) if c in classes else -2 for c in truth_classes])[grid.clip(0)]
        has = np.isfinite(free["posterior"].values) & scored
        posterior.append(free["posterior"].values[has])
        correct.append(free["label"].values[has] == truth_index[has])
        scenes[name] = {
            **{
                var: score(labels[var], truth_label, truth_classes, classes)["accuracy"]
                for var in ("label", "label_filtered")
            },
            "unclassified": float(((labels["label"].values < 0) & scored).sum() / max(int(scored.sum()), 1)),
            "reasons": labels["label"].attrs["unclassified"],
            "ceiling": score(best["label_filtered"], truth_label, truth_classes, classes)["accuracy"],
            "board_rejected": _board_rejection(labels["label"], scene_truths[name], features[name]),
        }
    return {
        "calibration_error": calibration_error(calibration, instrument, camp.crop),
        "items": items,
        "features": {key: _median_abs(values) for key, values in pooled.items()},
        "scenes": scenes,
        "posterior": np.concatenate(posterior),
        "correct": np.concatenate(correct),
        "item_features": features,
        "training": training,
    }


def risk_coverage(posterior: np.ndarray, correct: np.ndarray, coverages: Sequence[float]) -> list[float]:
    """Error rate among the most confident pixels, for each share of pixels classified.

    Parameters
    ----------
    posterior : (N,) ndarray
        Confidence of each pixel's class (higher is surer).
    correct : (N,) ndarray of bool
        Whether each pixel's class is right.
    coverages : sequence of float in (0, 1]
        Shares of the pixels classified, the most confident first.

    Returns
    -------
    list of float
        The error rate among the classified pixels at each coverage.
    """
    order = np.argsort(-posterior, kind="stable")
    errors = np.cumsum(~np.asarray(correct, dtype=bool)[order])
    counts = [max(1, int(round(coverage * order.size))) for coverage in coverages]
    return [float(errors[count - 1] / count) if order.size else float("nan") for count in counts]
