"""Surface finish classes from the feature images (method step 6).

The training set pools the per-pixel feature vectors (R0, n, variability) of
the reference specimens, inside their rois, with all three features finite.
Features have different scales (variability is ~0.01, n ~1), so a plain
Euclidean nearest neighbour would be decided by the feature with the largest
spread; every feature is therefore standardised to zero mean and unit
standard deviation over the training samples (``ddof=0``, a constant feature
keeps scale 1). The standardisation is stored in the training set
(``feature_mean``, ``feature_std``) and the classifier is rebuilt from the
stored samples whenever it is needed: nothing is pickled.

:func:`classify` predicts every pixel with a k-nearest-neighbour classifier
(the paper: k = 1), or leaves it unclassified (-1) instead of guessing: when a
feature is missing, when the standard uncertainty of its smoothed R0 or n
(:func:`surffin.features.features`) exceeds a bound, or when its features lie
farther from every training sample than a fraction of
:func:`class_separation`, the distance between the two closest classes (a
surface unlike every specimen, such as the board the specimens lie on); the
label image counts these pixels by reason. :func:`filter_labels` then removes
isolated errors among the classified pixels: unclassified pixels neither vote
nor receive a class, so the filter never fills in a pixel the classifier
declined (the unclassified pixels are the same before and after it). The
paper's median filter on class indices depends on the (arbitrary, here
alphabetical) order of the classes: a window with 10 votes for class 0, 5 for
class 1 and 10 for class 2 becomes class 1, the least frequent, because its
index lies in the middle. ``kind="majority"`` (the most frequent label in the
window) has no such dependence. Both count the votes of each class with one box filter per class,
so their cost does not depend on the window size.
"""

from __future__ import annotations

import numbers
from collections import Counter
from collections.abc import Mapping, Sequence

import cv2
import numpy as np
import xarray as xr

from surffin.campaign import Roi
from surffin.errors import SurffinError
from surffin.features import UNCERTAINTY, _check_grid, _check_size, _image_filter, select_roi

__all__ = [
    "FEATURES",
    "UNCLASSIFIED",
    "UNCLASSIFIED_REASONS",
    "training_set",
    "combine_training",
    "fit_classifier",
    "class_separation",
    "classify",
    "filter_labels",
    "score",
    "class_fractions",
]

#: Feature variables of a features Dataset, in the order of the training set's ``feature`` axis.
FEATURES = ("R0", "n", "variability")
#: Label of a pixel with no class (a feature is missing, too uncertain, or unlike every class).
UNCLASSIFIED = -1
#: Why :func:`classify` leaves a pixel unclassified, in the order the checks apply.
UNCLASSIFIED_REASONS = ("missing_feature", "uncertainty_unknown", "uncertainty_above_bound", "far_from_training")
_UNCLASSIFIED_NAME = "(unclassified)"
_FILTERS = ("median", "majority")


def _feature_matrix(ds: xr.Dataset) -> tuple[np.ndarray, np.ndarray]:
    """Features (pixel, feature) float64 of a (y, x) Dataset, row-major, and where all are finite."""
    missing = [name for name in FEATURES if name not in ds]
    if missing:
        raise ValueError(f"features Dataset lacks {missing}; it needs {list(FEATURES)} on (y, x)")
    for name in FEATURES:
        _check_grid(ds[name], name)
    stacked = ds[list(FEATURES)].to_dataarray("feature").transpose("y", "x", "feature")
    values = np.asarray(stacked.values, dtype=np.float64).reshape(-1, len(FEATURES))
    return values, np.isfinite(values).all(axis=1)


def _names(values) -> list[str]:
    """Python strings of a sequence of names (numpy unicode, object or bytes)."""
    return [str(v, "utf-8") if isinstance(v, bytes) else str(v) for v in np.asarray(values).tolist()]


def _standardised(samples: xr.Dataset) -> xr.Dataset:
    """``samples`` with the standardisation, class list and item list of its samples."""
    values = samples["features"].values
    std = values.std(axis=0)
    std[std == 0] = 1.0
    out = samples.assign(
        feature_mean=("feature", values.mean(axis=0)),
        feature_std=("feature", std),
    )
    out["feature_mean"].attrs = {"units": "1", "long_name": "mean of each feature over the training samples"}
    out["feature_std"].attrs = {
        "units": "1",
        "long_name": "standard deviation (ddof=0) of each feature over the training samples, 1 where constant",
    }
    out.attrs = {
        "classes": sorted(set(_names(samples["class"].values))),
        "items": list(dict.fromkeys(_names(samples["item"].values))),
        "standardisation": "z = (features - feature_mean) / feature_std",
    }
    return out


def _evenly(index: np.ndarray, count: int | None) -> np.ndarray:
    """At most ``count`` entries of ``index`` spread evenly over it, in order (all if None)."""
    if count is None or index.size <= count:
        return index
    return index[(np.arange(count) * index.size) // count]


def _check_cap(max_per_class) -> int | None:
    if max_per_class is not None and (
        isinstance(max_per_class, bool) or not isinstance(max_per_class, numbers.Integral) or max_per_class < 1
    ):
        raise ValueError(f"max_per_class must be a positive integer or None, got {max_per_class!r}")
    return max_per_class


def _pooled(parts: Sequence[xr.Dataset], max_per_class: int | None = None) -> xr.Dataset:
    """Samples of several sets in one, at most ``max_per_class`` of each class, standardised."""
    samples = xr.concat(parts, "sample", data_vars="all", coords="minimal", compat="override", join="exact")
    if max_per_class is not None:
        classes = np.asarray(_names(samples["class"].values))
        keep = np.sort(np.concatenate([_evenly(np.flatnonzero(classes == c), max_per_class) for c in np.unique(classes)]))
        samples = samples.isel(sample=keep)
    return _standardised(samples)


def _samples(values: np.ndarray, name: str, class_name: str, y: np.ndarray, x: np.ndarray) -> xr.Dataset:
    count = values.shape[0]
    return xr.Dataset(
        {
            "features": (("sample", "feature"), values, {"units": "1", "long_name": "feature vector"}),
            "class": ("sample", np.full(count, class_name), {"long_name": "class name"}),
        },
        coords={
            "feature": list(FEATURES),
            "item": ("sample", np.full(count, name), {"long_name": "source item"}),
            "y": ("sample", y, {"long_name": "sensor row"}),
            "x": ("sample", x, {"long_name": "sensor column"}),
        },
    )


def training_set(
    items: Mapping[str, tuple[xr.Dataset, str, Roi | None]], *, max_per_class: int | None = None
) -> xr.Dataset:
    """Pool the feature vectors of reference specimens into a training set.

    Items are read one at a time (pass lazy, dask-backed Datasets to keep only
    one item's features in memory), and with ``max_per_class`` each class keeps
    at most that many samples, so the memory of the training set and of the
    classifier built from it does not grow with the number of specimens.

    Parameters
    ----------
    items : mapping of item name to (features, class name, roi)
        ``features``: Dataset (y, x) with :data:`FEATURES` (output of
        :func:`surffin.features.features`); ``roi``: the specimen's pixels in
        sensor coordinates, or None for all pixels.
    max_per_class : int, optional
        Cap on the samples of a class. A class of ``m`` items takes at most
        ``ceil(max_per_class / m)`` samples from each, spread evenly over the
        item's pixels in row-major order (a deterministic subsample that
        keeps every item and every part of it), then at most
        ``max_per_class`` of the pooled ones the same way. None keeps all.

    Returns
    -------
    Dataset
        ``features (sample, feature)`` float64 with ``feature`` = :data:`FEATURES`;
        ``class (sample)`` class names; coordinates ``item``, ``y``, ``x``
        (sample): source item and sensor pixel; ``feature_mean``,
        ``feature_std (feature)``: the standardisation. Samples follow the
        order of ``items``, each item's pixels row-major; only pixels inside the
        roi with all three features finite. Attrs ``classes`` (sorted class
        names: the label order), ``items``, ``standardisation``.

    Raises
    ------
    SurffinError
        An item has no pixel with all features finite inside its roi.
    """
    if not items:
        raise ValueError("training_set needs at least one item")
    cap = _check_cap(max_per_class)
    items_of_class = Counter(class_name for _, class_name, _ in items.values())
    parts = []
    for name, (ds, class_name, roi) in items.items():
        part = ds if roi is None else select_roi(ds, roi)
        values, finite = _feature_matrix(part)
        if not finite.any():
            where = "" if roi is None else f" inside {roi}"
            raise SurffinError(
                f"training item {name!r} (class {class_name!r}): no pixel{where} has all of {list(FEATURES)} "
                "finite; check its roi and its feature store"
            )
        keep = _evenly(np.flatnonzero(finite), None if cap is None else -(-cap // items_of_class[class_name]))
        y, x = (coord.ravel()[keep] for coord in np.meshgrid(part["y"].values, part["x"].values, indexing="ij"))
        parts.append(_samples(values[keep], str(name), str(class_name), y, x))
    return _pooled(parts, cap)


def combine_training(*training: xr.Dataset, max_per_class: int | None = None) -> xr.Dataset:
    """Concatenate training sets (e.g. from several campaigns) and recompute the standardisation.

    Parameters
    ----------
    *training : Dataset
        Outputs of :func:`training_set` (or of this function, or read back from zarr).
    max_per_class : int, optional
        Cap on the samples of a class, spread evenly over its samples in the order given.

    Returns
    -------
    Dataset
        As :func:`training_set`, samples in the order given.
    """
    if not training:
        raise ValueError("combine_training needs at least one training set")
    parts = [t.drop_vars(["feature_mean", "feature_std"], errors="ignore").load() for t in training]
    return _pooled(parts, _check_cap(max_per_class))


def _check_k(k, n_samples: int) -> int:
    if isinstance(k, bool) or not isinstance(k, numbers.Integral) or not 1 <= k <= n_samples:
        raise ValueError(f"k must be an integer from 1 to the number of training samples ({n_samples}), got {k!r}")
    return int(k)


def _standardise(values: np.ndarray, mean: np.ndarray, std: np.ndarray) -> np.ndarray:
    return (values - mean) / std


def fit_classifier(training: xr.Dataset, k: int = 1, *, n_jobs: int | None = None):
    """A k-nearest-neighbour classifier of raw feature vectors, fitted on a training set.

    Parameters
    ----------
    training : Dataset
        Output of :func:`training_set` (or :func:`combine_training`).
    k : int, default 1
        Number of neighbours (the paper: 1).
    n_jobs : int, optional
        Parallel jobs of the neighbour search (scikit-learn's meaning).

    Returns
    -------
    sklearn.pipeline.Pipeline
        Standardisation with the stored ``feature_mean``/``feature_std``, then
        ``KNeighborsClassifier``; ``predict`` takes (pixel, feature) arrays in
        the order of :data:`FEATURES` and returns class indices into
        ``training.attrs["classes"]``.
    """
    from sklearn.neighbors import KNeighborsClassifier
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import FunctionTransformer

    features = np.asarray(training["features"].transpose("sample", "feature").values, dtype=np.float64)
    stored = _names(training["feature"].values)
    if stored != list(FEATURES):
        raise ValueError(f"training set features are {stored}; expected {list(FEATURES)}")
    index = {name: i for i, name in enumerate(training.attrs["classes"])}
    target = np.array([index[name] for name in _names(training["class"].values)], dtype=np.int16)
    standardise = FunctionTransformer(
        _standardise,
        kw_args={"mean": training["feature_mean"].values, "std": training["feature_std"].values},
    )
    model = make_pipeline(standardise, KNeighborsClassifier(n_neighbors=_check_k(k, target.size), n_jobs=n_jobs))
    return model.fit(features, target)


def _label_attrs(classes: Sequence[str]) -> dict:
    return {
        "long_name": "surface finish class",
        "flag_values": list(range(len(classes))),
        "flag_meanings": " ".join(classes),
        "comment": (
            f"{UNCLASSIFIED} = unclassified: a feature is missing, too uncertain, or far from every "
            "training sample (counts by reason in attr unclassified)"
        ),
    }


def class_separation(training: xr.Dataset) -> float:
    """Smallest distance between the medians of two classes in the standardised feature space.

    Parameters
    ----------
    training : Dataset
        Output of :func:`training_set` or :func:`combine_training`.

    Returns
    -------
    float
        ``min |m_a - m_b|`` over pairs of classes, with ``m`` the per-feature
        median of a class's standardised samples ``(features - feature_mean) /
        feature_std``: the distance the k-NN classifier must resolve between
        its two closest classes.

    Raises
    ------
    ValueError
        The training set has fewer than two classes.
    """
    classes = list(training.attrs["classes"])
    if len(classes) < 2:
        raise ValueError(f"class separation needs at least two classes, the training set has {classes}")
    values = np.asarray(training["features"].transpose("sample", "feature").values, dtype=np.float64)
    standard = _standardise(values, training["feature_mean"].values, training["feature_std"].values)
    names = np.array(_names(training["class"].values))
    medians = np.stack([np.median(standard[names == name], axis=0) for name in classes])
    distances = np.linalg.norm(medians[:, None] - medians[None], axis=-1)
    return float(distances[np.triu_indices(len(classes), 1)].min())


def _check_fraction(name: str, value) -> float | None:
    if value is not None and (isinstance(value, bool) or not isinstance(value, numbers.Real) or not value > 0):
        raise ValueError(f"{name} must be a positive fraction of the class separation or None, got {value!r}")
    return None if value is None else float(value)


def _uncertainty_bounds(max_uncertainty: float | None, training: xr.Dataset, separation: float) -> dict[str, float | None]:
    """The bound of each feature with an uncertainty, in its units (None: no bound).

    ``max_uncertainty * separation`` in standardised units, i.e. times the
    feature's standard deviation over the training samples.
    """
    if max_uncertainty is None:
        return dict.fromkeys(UNCERTAINTY)
    std = dict(zip(_names(training["feature"].values), training["feature_std"].values.tolist()))
    return {name: max_uncertainty * separation * std[name] for name in UNCERTAINTY}


def _uncertainty_flags(features: xr.Dataset, bounds: Mapping[str, float | None]) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (row-major) whose bounded uncertainty is unknown (NaN), and those above its bound."""
    pixels = features.sizes["y"] * features.sizes["x"]
    unknown, above = np.zeros(pixels, dtype=bool), np.zeros(pixels, dtype=bool)
    for name, bound in bounds.items():
        if bound is None:
            continue
        variable = f"{name}_uncertainty"
        if variable not in features:
            raise ValueError(
                f"features lack {variable}, needed by the bound max_uncertainty; "
                "recompute the features store with this surffin, or drop the bound"
            )
        _check_grid(features[variable], variable)
        values = np.asarray(features[variable].transpose("y", "x").values, dtype=np.float64).ravel()
        unknown |= np.isnan(values)
        above |= values > bound
    return unknown, above


def classify(
    features: xr.Dataset,
    training: xr.Dataset,
    *,
    k: int = 1,
    n_jobs: int | None = None,
    max_uncertainty: float | None = None,
    max_distance: float | None = None,
) -> xr.DataArray:
    """Class of every pixel of a feature image by k-nearest neighbours, or unclassified.

    Parameters
    ----------
    features : Dataset (y, x)
        With :data:`FEATURES` (output of :func:`surffin.features.features`),
        and ``R0_uncertainty``, ``n_uncertainty`` when ``max_uncertainty`` is given.
    training : Dataset
        Output of :func:`training_set` or :func:`combine_training`.
    k : int, default 1
        Number of neighbours.
    n_jobs : int, optional
        Parallel jobs of the neighbour search.
    max_uncertainty : float, optional
        Largest standard uncertainty of the smoothed R0 and n, as a fraction
        of :func:`class_separation` in standardised units (so, for each
        feature, that fraction of the separation times the feature's standard
        deviation over the training samples): the bound follows the classes
        to be told apart, whatever the camera and the specimens. A pixel whose
        uncertainty exceeds its bound, or is unknown (NaN), is unclassified
        rather than guessed. None: no bound.
    max_distance : float, optional
        Largest distance from a pixel's standardised features to the nearest
        training sample, as a fraction of :func:`class_separation`; farther
        pixels (surfaces unlike every class, such as the board the specimens
        lie on) are unclassified. None: every pixel gets the nearest class.

    Returns
    -------
    (y, x) DataArray of int16
        Class index into ``training.attrs["classes"]`` (sorted class names),
        -1 where unclassified; CF attrs ``flag_values`` (0..K-1) and
        ``flag_meanings`` (the class names, space-separated); ``k``,
        ``max_uncertainty``, ``uncertainty_bounds`` (per feature, its units),
        ``max_distance``, ``distance_bound`` (the bound in standardised units,
        when ``max_distance`` is given), ``class_separation`` and
        ``unclassified``: the number of pixels left unclassified for each of
        :data:`UNCLASSIFIED_REASONS`, each pixel counted for the first reason
        that applies. Computed eagerly: all pixels are predicted at once.
    """
    model = fit_classifier(training, k, n_jobs=n_jobs)
    max_uncertainty = _check_fraction("max_uncertainty", max_uncertainty)
    max_distance = _check_fraction("max_distance", max_distance)
    separation = class_separation(training) if (max_uncertainty, max_distance) != (None, None) else None
    bounds = _uncertainty_bounds(max_uncertainty, training, separation)
    values, keep = _feature_matrix(features)
    unclassified = dict.fromkeys(UNCLASSIFIED_REASONS, 0)
    unclassified["missing_feature"] = int((~keep).sum())
    unknown, above = _uncertainty_flags(features, bounds)
    for reason, flagged in (("uncertainty_unknown", unknown), ("uncertainty_above_bound", above)):
        unclassified[reason] = int((keep & flagged).sum())
        keep &= ~flagged
    extra = {} if separation is None else {"class_separation": separation}
    if max_distance is not None:
        extra["distance_bound"] = max_distance * separation
        if keep.any():
            standard, neighbours = model[0].transform(values[keep]), model[-1]
            far = neighbours.kneighbors(standard, 1)[0][:, 0] > extra["distance_bound"]
            unclassified["far_from_training"] = int(far.sum())
            keep[np.flatnonzero(keep)[far]] = False
    labels = np.full(values.shape[0], UNCLASSIFIED, dtype=np.int16)
    if keep.any():
        labels[keep] = model.predict(values[keep])
    shape = (features.sizes["y"], features.sizes["x"])
    out = xr.DataArray(labels.reshape(shape), dims=("y", "x"), coords={"y": features["y"], "x": features["x"]})
    out.attrs = {
        **_label_attrs(list(training.attrs["classes"])),
        "k": int(k),
        "max_uncertainty": max_uncertainty,
        "uncertainty_bounds": bounds,
        "max_distance": max_distance,
        **extra,
        "unclassified": unclassified,
    }
    return out


def _filter_image(label: np.ndarray, size: int, kind: str) -> np.ndarray:
    """Median or majority filter (H, W) int16 of a label image; -1 neither votes nor changes."""
    label = label.astype(np.int32)
    valid = label >= 0
    if not valid.any():
        return np.full(label.shape, UNCLASSIFIED, dtype=np.int16)
    counts = np.empty((int(label.max()) + 1, *label.shape), dtype=np.int32)
    for c in range(counts.shape[0]):
        votes = (label == c).astype(np.uint8)
        counts[c] = cv2.boxFilter(votes, cv2.CV_32S, (size, size), normalize=False, borderType=cv2.BORDER_CONSTANT)
    if kind == "median":
        # lower median: the smallest class with at least half of the votes at or below it
        filtered = np.argmax(2 * np.cumsum(counts, axis=0) >= counts.sum(axis=0), axis=0)
    else:
        best = counts.max(axis=0)
        centre = np.take_along_axis(counts, np.maximum(label, 0)[None], axis=0)[0]
        filtered = np.where(centre == best, label, np.argmax(counts, axis=0))
    return np.where(valid, filtered, UNCLASSIFIED).astype(np.int16)


def filter_labels(label: xr.DataArray, *, kind: str = "median", size: int = 5) -> xr.DataArray:
    """Remove isolated errors from a label image with a median or majority filter.

    Parameters
    ----------
    label : (..., y, x) DataArray of int
        Class indices 0..K-1, -1 = unclassified.
    kind : {"median", "majority"}
        ``"median"``: the paper's median of the class indices in the window
        (the lower median when the number of votes is even); it depends on the
        order of the classes (module docstring). ``"majority"``: the most
        frequent class in the window; on a tie the centre pixel keeps its
        class if it is among the most frequent, else the smallest tied index.
    size : int, default 5
        Odd side of the square window, pixels.

    Returns
    -------
    (..., y, x) DataArray of int16
        Filtered labels, attrs of ``label``. Unclassified pixels (-1) and
        pixels outside the image do not vote, and unclassified pixels stay
        unclassified: the filter never invents a class where :func:`classify`
        declined one (a missing feature, too uncertain, far from the training
        set), so the counts of its ``unclassified`` attr hold for the filtered
        image too. Lazy on dask input.
    """
    if kind not in _FILTERS:
        raise ValueError(f"kind must be one of {_FILTERS}, got {kind!r}")
    size = _check_size(size)
    if not np.issubdtype(label.dtype, np.integer):
        raise ValueError(f"label must hold integer class indices, got dtype {label.dtype}")
    if not {"y", "x"} <= set(label.dims):
        raise ValueError(f"label must have dims (..., y, x), got {label.dims}")
    out = _image_filter(label, _filter_image, size // 2, UNCLASSIFIED, np.int16, size=size, kind=kind)
    out.attrs = {**label.attrs, "filter": kind, "filter_size": size}
    return out


def _on_label_grid(truth, label: xr.DataArray) -> np.ndarray:
    """The truth labels (y, x) at the sensor pixels of ``label``."""
    if isinstance(truth, xr.DataArray):
        try:
            return truth.sel(y=label["y"].values, x=label["x"].values).transpose("y", "x").values
        except KeyError as exc:
            raise ValueError(f"truth does not cover the pixels of the label image ({exc})") from exc
    truth = np.asarray(truth)
    rows, cols = label["y"].values, label["x"].values
    if truth.ndim != 2 or rows.max() >= truth.shape[0] or cols.max() >= truth.shape[1]:
        raise ValueError(
            f"truth of shape {truth.shape} does not cover sensor rows {rows.min()}..{rows.max()}, "
            f"columns {cols.min()}..{cols.max()} of the label image"
        )
    return truth[np.ix_(rows, cols)]


def _check_indices(values: np.ndarray, n_classes: int, what: str) -> None:
    if values.size and (values.min() < -1 or values.max() >= n_classes):
        raise ValueError(f"{what} spans {values.min()}..{values.max()} but names {n_classes} classes")


def score(label: xr.DataArray, truth_label, truth_classes: Sequence[str], classes: Sequence[str]) -> dict:
    """Accuracy of a label image against ground truth, matching classes by name.

    Parameters
    ----------
    label : (y, x) DataArray of int
        Class indices into ``classes``, -1 = unclassified, with sensor coordinates.
    truth_label : (height, width) ndarray or (y, x) DataArray of int
        Truth class indices into ``truth_classes``, -1 = not scored: a whole
        sensor image (as :func:`surffin.campaign.read_truth` returns) indexed
        by the sensor coordinates of ``label``, or a DataArray selected by them.
    truth_classes : sequence of str
        Names of the truth indices 0..; their order need not match ``classes``.
    classes : sequence of str
        Names of the label indices 0..K-1.

    Returns
    -------
    dict (JSON-serialisable)
        ``accuracy``: correct / scored pixels (pixels whose truth is >= 0;
        unclassified counts as wrong), None if none is scored; ``n_scored``,
        ``n_correct``; ``recall`` and ``support`` per truth class name (recall
        None without support); ``confusion``: counts [truth row][predicted
        column], rows ``confusion_rows`` (``classes``, then truth classes not
        among them), columns ``confusion_columns`` (``classes``, then
        ``"(unclassified)"``).
    """
    classes, truth_classes = list(classes), list(truth_classes)
    _check_grid(label, "label")
    predicted = np.asarray(label.transpose("y", "x").values)
    truth = np.asarray(_on_label_grid(truth_label, label))
    _check_indices(predicted, len(classes), "label")
    _check_indices(truth, len(truth_classes), "truth label")
    rows = classes + [name for name in truth_classes if name not in classes]
    row_of_truth = np.array([rows.index(name) for name in truth_classes], dtype=np.int64)
    scored = truth >= 0
    truth_rows = row_of_truth[truth[scored]]
    columns = np.where(predicted[scored] >= 0, predicted[scored], len(classes))
    n_columns = len(classes) + 1
    cells = np.bincount(truth_rows * n_columns + columns, minlength=len(rows) * n_columns)
    confusion = cells.reshape(len(rows), n_columns)
    diagonal = np.array([confusion[i, i] if i < len(classes) else 0 for i in range(len(rows))])
    support = confusion.sum(axis=1)
    n_scored, n_correct = int(support.sum()), int(diagonal.sum())
    return {
        "accuracy": n_correct / n_scored if n_scored else None,
        "n_scored": n_scored,
        "n_correct": n_correct,
        "recall": {name: (int(d) / int(s) if s else None) for name, d, s in zip(rows, diagonal, support)},
        "support": {name: int(s) for name, s in zip(rows, support)},
        "confusion": confusion.tolist(),
        "confusion_rows": rows,
        "confusion_columns": classes + [_UNCLASSIFIED_NAME],
    }


def class_fractions(label: xr.DataArray, classes: Sequence[str]) -> dict:
    """Share of the pixels of a label image in each class.

    Parameters
    ----------
    label : (y, x) DataArray of int
        Class indices into ``classes``, -1 = unclassified.
    classes : sequence of str
        Names of the label indices 0..K-1.

    Returns
    -------
    dict (JSON-serialisable)
        ``n_pixels``; ``fractions``: class name -> share of all pixels;
        ``unclassified``: share of the -1 pixels (the shares sum to 1).
    """
    values = np.asarray(label.values).ravel()
    _check_indices(values, len(classes), "label")
    counts = np.bincount(values + 1, minlength=len(classes) + 1)
    total = values.size
    shares = counts / total if total else np.zeros(counts.shape)
    return {
        "n_pixels": int(total),
        "fractions": {name: float(share) for name, share in zip(classes, shares[1:])},
        "unclassified": float(shares[0]),
    }
