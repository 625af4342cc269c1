"""Training sets, k-NN classification, label filters and scores (surffin.method.classify)."""

import json

import numpy as np
import pytest
import scipy.ndimage
import xarray as xr
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from scipy.stats import multivariate_normal
from sklearn.neighbors import KNeighborsClassifier

from surffin.errors import SurffinError
from surffin.grid import Roi
from surffin.io.store import open_store, write_store
from surffin.method.classify import (
    FEATURES,
    NOISE_CORRECTED,
    UNCLASSIFIED_REASONS,
    class_fractions,
    class_model,
    classify,
    combine_training,
    filter_labels,
    score,
    training_set,
)
from surffin.method.stages import labels_stage

Y0, X0 = 100, 60
"""Sensor position of the feature grids' top-left pixel."""

CENTRES = {"S1": (0.9, 1.2, 0.010), "S2": (0.6, 2.0, 0.030), "S3": (0.3, 0.8, 0.020)}
"""Well-separated class centres (R0, n, variability)."""


def feature_image(centre, shape=(12, 16), spread=0.02, seed=0, y0=Y0, x0=X0):
    """A features Dataset (y, x): per-feature Gaussian scatter of relative size ``spread`` about ``centre``."""
    rng = np.random.default_rng(seed)
    coords = {"y": np.arange(y0, y0 + shape[0]), "x": np.arange(x0, x0 + shape[1])}
    return xr.Dataset(
        {
            name: (("y", "x"), value * (1 + spread * rng.standard_normal(shape)))
            for name, value in zip(FEATURES, centre)
        },
        coords=coords,
    )


def specimens(seed=0):
    """Training items in reverse class order (the label order must not depend on it)."""
    return {
        f"spec{k}": (feature_image(CENTRES[name], seed=seed + k), name, None)
        for k, name in enumerate(sorted(CENTRES, reverse=True))
    }


def test_variability_with_and_without_the_noise_taken_out_never_mix():
    items = specimens()
    for ds, _, _ in items.values():
        ds.attrs[NOISE_CORRECTED] = 1
    corrected = training_set(items)
    assert corrected.attrs[NOISE_CORRECTED] == 1
    older = training_set(specimens(seed=5))  # stores made before the noise model: no attr
    assert older.attrs[NOISE_CORRECTED] == 0
    scene = feature_image(CENTRES["S1"], seed=9)
    with pytest.raises(SurffinError, match=NOISE_CORRECTED):
        classify(scene, corrected)
    assert (classify(scene.assign_attrs({NOISE_CORRECTED: 1}), corrected)["label"] == 0).all()
    with pytest.raises(SurffinError, match="training sets mix"):
        combine_training(corrected, older)
    mixed = specimens()
    mixed["spec0"][0].attrs[NOISE_CORRECTED] = 1
    with pytest.raises(SurffinError, match="spec0"):
        training_set(mixed)


def test_training_set_honours_sensor_rois_and_drops_nan():
    ds = feature_image(CENTRES["S1"])
    ds["n"][3, 5] = np.nan  # sensor (103, 65): inside the roi
    ds["R0"][0, 0] = np.nan  # outside it
    roi = Roi((Y0 + 2, Y0 + 6), (X0 + 4, X0 + 9))
    training = training_set({"a": (ds, "S1", roi), "b": (feature_image(CENTRES["S2"], seed=1), "S2", None)})
    a = training.where(training["item"] == "a", drop=True)
    assert a.sizes["sample"] == 4 * 5 - 1
    assert ((a["y"] >= Y0 + 2) & (a["y"] < Y0 + 6) & (a["x"] >= X0 + 4) & (a["x"] < X0 + 9)).all()
    assert (103, 65) not in set(zip(a["y"].values.tolist(), a["x"].values.tolist()))
    # each sample carries the features of its sensor pixel
    first = a.isel(sample=0)
    np.testing.assert_array_equal(
        first["features"].values, [ds[name].sel(y=first["y"], x=first["x"]).item() for name in FEATURES]
    )
    assert training.sizes["sample"] == 19 + 12 * 16
    assert training["feature"].values.tolist() == list(FEATURES)
    assert training["features"].dtype == np.float64
    assert set(training["class"].values.tolist()) == {"S1", "S2"}
    assert training.attrs["classes"] == ["S1", "S2"] and training.attrs["items"] == ["a", "b"]
    np.testing.assert_allclose(training["feature_mean"], training["features"].mean("sample"), rtol=1e-14)
    np.testing.assert_allclose(training["feature_std"], training["features"].std("sample"), rtol=1e-14)


def test_training_item_without_finite_pixel_is_an_error():
    ds = feature_image(CENTRES["S1"])
    ds["variability"][:4] = np.nan
    with pytest.raises(SurffinError, match="'a'.*no pixel inside"):
        training_set({"a": (ds, "S1", Roi((Y0, Y0 + 4), (X0, X0 + 16)))})


def test_classify_separated_clusters_exactly():
    training = training_set(specimens())
    assert training.attrs["classes"] == ["S1", "S2", "S3"]
    for k, name in enumerate(["S1", "S2", "S3"]):
        scene = feature_image(CENTRES[name], seed=10 + k)
        scene["R0"][2, 3] = np.nan  # two features left: still classified
        scene["R0"][4, 5] = scene["n"][4, 5] = np.nan  # one left: unclassified
        label = classify(scene, training, k=3, n_jobs=1)["label"]
        assert label.dtype == np.int16 and label.dims == ("y", "x")
        assert label["y"][0] == Y0
        expected = np.full(label.shape, k)
        expected[4, 5] = -1
        np.testing.assert_array_equal(label.values, expected)
        assert label.attrs["unclassified"] == dict.fromkeys(UNCLASSIFIED_REASONS, 0) | {"missing_feature": 1}
        assert label.attrs["flag_values"] == [0, 1, 2]
        assert label.attrs["flag_meanings"] == "S1 S2 S3"


def test_standardisation_keeps_a_huge_feature_from_dominating():
    # R0 separates the classes; n is the same noise for both, on a scale 1e4 times larger
    rng = np.random.default_rng(4)

    def item(r0, seed):
        ds = feature_image((r0, 1.0, 0.02), shape=(30, 30), spread=0.01, seed=seed)
        ds["n"][:] = rng.normal(0, 1e4, (30, 30))
        return ds

    training = training_set({"lo": (item(0.5, 1), "A", None), "hi": (item(0.6, 2), "B", None)})
    scene_a, scene_b = item(0.5, 3), item(0.6, 4)
    assert (classify(scene_a, training)["label"].values == 0).mean() > 0.99
    assert (classify(scene_b, training)["label"].values == 1).mean() > 0.99
    # the same neighbour search on raw features is no better than a coin
    raw = KNeighborsClassifier(1).fit(training["features"].values, training["class"].values)
    stacked = np.stack([scene_a[name].values.ravel() for name in FEATURES], axis=1)
    assert (raw.predict(stacked) == "A").mean() < 0.7


def test_class_model_is_the_mean_and_covariance_of_standardised_samples():
    training = training_set(specimens())
    mean, covariance = class_model(training)
    z = (training["features"].values - training["features"].values.mean(axis=0)) / training["features"].values.std(
        axis=0
    )
    names = np.asarray(training["class"].values).astype(str)
    for index, name in enumerate(training.attrs["classes"]):
        np.testing.assert_allclose(mean[index], z[names == name].mean(axis=0), atol=1e-12)
        np.testing.assert_allclose(covariance[index], np.cov(z[names == name].T) + 1e-6 * np.eye(3), rtol=1e-10)


def test_classify_takes_the_features_a_pixel_has():
    training = training_set(specimens())
    scene = feature_image(CENTRES["S2"], seed=21)
    scene["variability"][:] = np.nan
    scene["R0"][:6] = 0.5 * (CENTRES["S1"][0] + CENTRES["S3"][0])  # R0 and n disagree; n decides with S2
    label = classify(scene, training)["label"]
    z = (training["features"].values - training["feature_mean"].values) / training["feature_std"].values
    reference = KNeighborsClassifier(1).fit(z[:, :2], np.asarray(training["class"].values).astype(str))
    pixels = np.stack([scene[name].values.ravel() for name in ("R0", "n")], axis=1)
    expected = reference.predict((pixels - training["feature_mean"].values[:2]) / training["feature_std"].values[:2])
    np.testing.assert_array_equal(np.array(training.attrs["classes"])[label.values.ravel()], expected)


def test_every_pattern_of_missing_features_is_classified_on_the_features_it_leaves():
    training = training_set(specimens())
    scene = feature_image(CENTRES["S2"], spread=0.3, seed=24)  # wide: the classes' clusters overlap
    missing = np.random.default_rng(5).random((len(FEATURES), *scene["R0"].shape)) < 0.4
    for name, where in zip(FEATURES, missing):
        scene[name] = scene[name].where(~where)
    labels = classify(scene, training, k=3)
    z = (training["features"].values - training["feature_mean"].values) / training["feature_std"].values
    pixels = np.stack([scene[name].values.ravel() for name in FEATURES], axis=1)
    pixels = (pixels - training["feature_mean"].values) / training["feature_std"].values
    names = np.asarray(training["class"].values).astype(str)
    label, reason = labels["label"].values.ravel(), labels["unclassified_reason"].values.ravel()
    patterns = set()
    for i, pixel in enumerate(pixels):
        columns = np.flatnonzero(np.isfinite(pixel))
        patterns.add(tuple(columns))
        if columns.size < 2:
            assert label[i] == -1 and reason[i] == 1
            continue
        reference = KNeighborsClassifier(3, algorithm="brute").fit(z[:, columns], names)
        assert training.attrs["classes"][label[i]] == reference.predict(pixel[None, columns])[0]
    assert len(patterns) == 2 ** len(FEATURES)


def test_posterior_is_the_gaussian_class_model_with_the_pixels_uncertainty():
    training = training_set(specimens())
    mean, covariance = class_model(training)
    scene = with_uncertainty(feature_image(CENTRES["S1"], seed=22), r0=0.05, n=0.1)
    labels = classify(scene, training)
    std = training["feature_std"].values
    for y, x in ((0, 0), (5, 7), (11, 15)):
        pixel = np.array([scene[name].values[y, x] for name in FEATURES])
        z = (pixel - training["feature_mean"].values) / std
        extra = np.diag([(0.05 / std[0]) ** 2, (0.1 / std[1]) ** 2, 0.0])
        density = [multivariate_normal(mean[c], covariance[c] + extra).pdf(z) for c in range(3)]
        chosen = labels["label"].values[y, x]
        assert labels["posterior"].values[y, x] == pytest.approx(density[chosen] / sum(density), rel=1e-5)


def test_combine_training_through_zarr(tmp_path):
    first = training_set(dict(list(specimens().items())[:2]))  # S3 and S2
    second = training_set({"other": (feature_image(CENTRES["S1"], seed=7), "S1", None)})
    write_store(first, tmp_path / "first.zarr")
    combined = combine_training(open_store(tmp_path / "first.zarr"), second)
    assert combined.sizes["sample"] == first.sizes["sample"] + second.sizes["sample"]
    assert combined.attrs["classes"] == ["S1", "S2", "S3"]
    assert combined.attrs["items"] == ["spec0", "spec1", "other"]
    pooled = np.concatenate([first["features"].values, second["features"].values])
    np.testing.assert_allclose(combined["feature_mean"], pooled.mean(axis=0), rtol=1e-14)
    np.testing.assert_allclose(combined["feature_std"], pooled.std(axis=0), rtol=1e-14)
    # the pooled set classifies like one built in a single step
    scene = feature_image(CENTRES["S2"], seed=20)
    np.testing.assert_array_equal(
        classify(scene, combined)["label"].values, classify(scene, training_set(specimens()))["label"].values
    )


def test_training_cap_keeps_evenly_spread_samples_of_every_item():
    # two S1 items of 192 pixels (one with a NaN) and one S2 item: cap 50 per class
    first, second = feature_image(CENTRES["S1"], seed=1), feature_image(CENTRES["S1"], seed=2)
    first["R0"][0, 3] = np.nan
    items = {
        "a": (first, "S1", None),
        "b": (second, "S1", None),
        "c": (feature_image(CENTRES["S2"], seed=3), "S2", None),
    }
    capped = training_set(items, max_per_class=50)
    full = training_set(items)
    classes = np.asarray(capped["class"].values).astype(str)
    assert (classes == "S1").sum() == 50 and (classes == "S2").sum() == 50
    sources = np.asarray(capped["item"].values).astype(str)
    assert (sources == "a").sum() == 25 and (sources == "b").sum() == 25
    # a subset of the full set, spread over the whole image of each item
    full_rows = {tuple(row) for row in full["features"].values}
    assert all(tuple(row) in full_rows for row in capped["features"].values)
    for name in "abc":
        rows = capped["y"].values[sources == name]
        assert rows.min() <= Y0 + 1 and rows.max() >= Y0 + 10
    # the standardisation is that of the kept samples; a cap above the counts keeps all
    np.testing.assert_allclose(capped["feature_mean"], capped["features"].values.mean(axis=0), rtol=1e-14)
    assert training_set(items, max_per_class=1000).sizes["sample"] == full.sizes["sample"]
    combined = combine_training(full, full, max_per_class=70)
    assert sorted(np.unique(np.asarray(combined["class"].values).astype(str), return_counts=True)[1]) == [70, 70]


@pytest.mark.parametrize("dtype", ["U", "S", "O", "T"])
def test_sample_names_in_any_order_and_dtype(dtype):
    # samples shuffled (no run of one item or class) and names as numpy unicode, bytes, objects or StringDType
    training = training_set(specimens())
    shuffled = training.isel(sample=np.random.default_rng(3).permutation(training.sizes["sample"]))
    names = {key: np.asarray(shuffled[key].values).astype(str).tolist() for key in ("class", "item")}
    as_dtype = {
        "U": np.array,
        "S": lambda values: np.array([value.encode() for value in values]),
        "O": lambda values: np.array(values, dtype=object),
        "T": lambda values: np.array(values, dtype=np.dtypes.StringDType()),
    }[dtype]
    shuffled = shuffled.assign(**{"class": ("sample", as_dtype(names["class"]))})
    shuffled = shuffled.assign_coords(item=("sample", as_dtype(names["item"])))
    pooled = combine_training(shuffled)
    assert pooled.attrs["classes"] == sorted(set(names["class"]))
    assert pooled.attrs["items"] == list(dict.fromkeys(names["item"]))
    assert pooled.attrs["items"] != training.attrs["items"]  # the order of first appearance, not the items'
    z = (pooled["features"].values - pooled["feature_mean"].values) / pooled["feature_std"].values
    mean, _ = class_model(pooled)
    for index, name in enumerate(pooled.attrs["classes"]):
        np.testing.assert_array_equal(mean[index], z[np.array(names["class"]) == name].mean(axis=0))
    scene = feature_image(CENTRES["S2"], seed=23)
    scene["R0"][:6] = 0.5 * (CENTRES["S1"][0] + CENTRES["S3"][0])
    label = classify(scene, pooled, k=3)["label"].values.ravel()
    pixels = np.stack([scene[name].values.ravel() for name in FEATURES], axis=1)
    reference = KNeighborsClassifier(3, algorithm="brute").fit(z, names["class"])
    expected = reference.predict((pixels - pooled["feature_mean"].values) / pooled["feature_std"].values)
    np.testing.assert_array_equal(np.array(pooled.attrs["classes"])[label], expected)
    capped = combine_training(shuffled, max_per_class=100)
    kept = [value.decode() if isinstance(value, bytes) else str(value) for value in capped["class"].values.tolist()]
    assert {name: kept.count(name) for name in CENTRES} == dict.fromkeys(CENTRES, 100)


@pytest.mark.parametrize("cap", [0, -3, 2.5, True])
def test_training_cap_must_be_a_positive_integer(cap):
    with pytest.raises(ValueError, match="max_per_class"):
        training_set(specimens(), max_per_class=cap)


def with_uncertainty(ds, r0=0.002, n=0.005):
    """``ds`` with constant ``R0_uncertainty`` and ``n_uncertainty``."""
    return ds.assign(R0_uncertainty=xr.full_like(ds["R0"], r0), n_uncertainty=xr.full_like(ds["n"], n))


def test_pixels_between_classes_are_left_unclassified():
    training = training_set(specimens())
    scene = with_uncertainty(feature_image(CENTRES["S2"], seed=11))
    # row 2 walks from the centre of S1 to that of S2
    for name, a, b in zip(FEATURES, CENTRES["S1"], CENTRES["S2"]):
        scene[name][2] = a + (b - a) * np.linspace(0.0, 1.0, 16)
    free = classify(scene, training)
    assert (free["label"].values >= 0).all()
    between = free["posterior"].values < 0.9
    assert 0 < between.sum() < 16 and between[2].sum() == between.sum()
    bounded = classify(scene, training, min_posterior=0.9)
    expected = np.where(between, -1, free["label"].values)
    np.testing.assert_array_equal(bounded["label"].values, expected)
    reasons = {"missing_feature": 0, "far_from_training": 0, "ambiguous": int(between.sum())}
    assert bounded["label"].attrs["unclassified"] == reasons


@pytest.mark.parametrize("bound", [0, 1, -0.5, "0.1", True])
def test_reject_bounds_are_checked(bound):
    training = training_set(specimens())
    scene = feature_image(CENTRES["S1"])
    for name in ("min_posterior", "outlier_probability"):
        with pytest.raises(ValueError, match=name):
            classify(scene, training, **{name: bound})


def test_pixels_far_from_every_class_are_left_unclassified():
    training = training_set(specimens())
    scene = feature_image(CENTRES["S3"], seed=12)
    scene["n"][:3] = 5.0  # a board unlike every class
    nearest = classify(scene, training)["label"]
    assert (nearest.values >= 0).all()
    label = classify(scene, training, outlier_probability=1e-4)["label"]
    expected = np.full(label.shape, 2)
    expected[:3] = -1
    np.testing.assert_array_equal(label.values, expected)
    assert label.attrs["unclassified"]["far_from_training"] == 3 * 16
    assert label.attrs["outlier_probability"] == 1e-4


def test_labels_stage_fills_isolated_abstentions_and_counts_what_is_left():
    training = training_set(specimens())
    scene = with_uncertainty(feature_image(CENTRES["S1"], seed=13))
    scene["n"][4:7, 8:11] = 5.0  # 9 pixels unlike every class, inside S1
    scene["n"][:, :4] = 5.0  # and a strip of them along the left edge
    ds = labels_stage(scene, training, min_posterior=0.5, outlier_probability=1e-4)
    reason, label, filtered = ds["unclassified_reason"].values, ds["label"].values, ds["label_filtered"].values
    np.testing.assert_array_equal(reason > 0, label == -1)
    assert (reason[4:7, 8:11] == 1 + UNCLASSIFIED_REASONS.index("far_from_training")).all()
    assert ds["label"].attrs["unclassified"]["far_from_training"] == 9 + 4 * scene.sizes["y"]
    # 5 x 5 filter: the 3 x 3 patch is a minority of every window around it and is filled; the
    # strip's pixels see at most 2 of 5 columns classified and stay unclassified
    assert (filtered[4:7, 8:11] == 0).all()
    assert (filtered[:, :4] == -1).all()
    left = ds["label_filtered"].attrs["unclassified"]
    assert sum(left.values()) == int((filtered == -1).sum()) and left["far_from_training"] == 4 * scene.sizes["y"]
    assert ds["posterior"].dtype == np.float32 and reason.dtype == np.int8


def brute_filter(label, size, kind):
    """Label filter pixel by pixel: -1 and outside pixels do not vote; -1 changes where over half the window votes."""
    r = size // 2
    padded = np.pad(label, r, constant_values=-1)
    out = label.copy()
    for i, j in np.ndindex(label.shape):
        votes = padded[i : i + size, j : j + size]
        votes = np.sort(votes[votes >= 0])
        if label[i, j] < 0 and 2 * votes.size <= size * size:
            continue
        if kind == "median":
            out[i, j] = votes[(votes.size - 1) // 2]
        else:
            counts = np.bincount(votes)
            best = np.flatnonzero(counts == counts.max())
            out[i, j] = label[i, j] if label[i, j] in best else best[0]
    return out


def labels(values, y0=Y0, x0=X0):
    values = np.asarray(values, dtype=np.int16)
    coords = {"y": np.arange(y0, y0 + values.shape[0]), "x": np.arange(x0, x0 + values.shape[1])}
    return xr.DataArray(values, dims=("y", "x"), coords=coords, attrs={"flag_meanings": "S1 S2 S3"})


@pytest.mark.parametrize("kind", ["median", "majority"])
def test_filters_remove_salt_noise(kind):
    clean = np.zeros((30, 40), dtype=np.int16)
    clean[:, 13:26] = 2
    clean[:, 26:] = 1
    noisy = clean.copy()
    rng = np.random.default_rng(0)
    # isolated errors on a 5-pixel lattice: never two in one 5 x 5 window
    rows, cols = np.meshgrid(np.arange(2, 30, 5), np.arange(1, 40, 5), indexing="ij")
    pick = rng.random(rows.shape) < 0.7
    noisy[rows[pick], cols[pick]] = (clean[rows[pick], cols[pick]] + rng.integers(1, 3, pick.sum())) % 3
    assert (noisy != clean).sum() > 20
    out = filter_labels(labels(noisy), kind=kind, size=5)
    assert out.dtype == np.int16 and out.attrs["flag_meanings"] == "S1 S2 S3"
    np.testing.assert_array_equal(out.values, clean)


def test_median_matches_scipy_inside_the_image():
    rng = np.random.default_rng(1)
    label = rng.integers(0, 4, (20, 25))
    out = filter_labels(labels(label), kind="median", size=5).values
    np.testing.assert_array_equal(out[2:-2, 2:-2], scipy.ndimage.median_filter(label, size=5)[2:-2, 2:-2])


def test_median_depends_on_class_order_and_majority_does_not():
    # 10 votes of class 0, 5 of class 1 (the centre column) and 10 of class 2
    window = np.array([[0, 0, 1, 2, 2]] * 5)
    assert filter_labels(labels(window), kind="median").values[2, 2] == 1
    assert filter_labels(labels(window), kind="majority").values[2, 2] in (0, 2)
    swapped = np.where(window == 1, 2, np.where(window == 2, 1, window))
    assert filter_labels(labels(swapped), kind="median").values[2, 2] == 1


def test_unclassified_pixels_do_not_vote_and_change_only_among_classified_ones():
    label = np.full((5, 5), -1)
    label[2, 2] = 0
    label[0, :3] = 1
    # the centre sees one 0 and three 1s: -1 (sixteen of them) would win if it voted
    for kind in ("median", "majority"):
        out = filter_labels(labels(label), kind=kind).values
        assert out[2, 2] == 1
        np.testing.assert_array_equal(out == -1, label == -1)
    assert (filter_labels(labels(np.full((4, 4), -1))).values == -1).all()
    # an abstention among classified pixels is filled; a region of them (the board) stays
    region = np.full((9, 9), 2)
    region[4, 4] = -1
    region[:, 7:] = -1
    for kind in ("median", "majority"):
        out = filter_labels(labels(region), kind=kind).values
        assert out[4, 4] == 2
        assert (out[:, 8] == -1).all()


@settings(max_examples=40, deadline=None)
@given(
    label=hnp.arrays(np.int16, st.tuples(st.integers(1, 14), st.integers(1, 14)), elements=st.integers(-1, 4)),
    size=st.sampled_from([1, 3, 5]),
    kind=st.sampled_from(["median", "majority"]),
    chunk=st.integers(1, 6),
)
def test_filters_match_brute_force_on_any_chunks(label, size, kind, chunk):
    expected = brute_filter(label, size, kind)
    np.testing.assert_array_equal(filter_labels(labels(label), kind=kind, size=size).values, expected)
    lazy = filter_labels(labels(label).chunk({"y": chunk, "x": chunk + 1}), kind=kind, size=size)
    np.testing.assert_array_equal(lazy.values, expected)


def test_score_by_hand():
    classes = ["S1", "S2", "S3"]
    truth_classes = ["S3", "S1", "S9"]  # another order, and a class the classifier lacks
    # label on the crop rows 100-101, columns 60-63 of a 110 x 70 sensor
    label = labels([[0, 0, 2, -1], [1, 2, 2, 0]])
    truth = np.full((110, 70), -1)
    truth[100:102, 60:64] = [[1, 1, 0, 0], [1, -1, 2, 0]]  # S1 S1 S3 S3 / S1 . S9 S3
    result = score(label, truth, truth_classes, classes)
    # scored 7: S1 -> S1, S1, S2 (2 of 3); S3 -> S3, unclassified, S1 (1 of 3); S9 -> S3 (0 of 1)
    assert result["n_scored"] == 7 and result["n_correct"] == 3
    assert result["accuracy"] == pytest.approx(3 / 7)
    assert result["recall"] == {"S1": pytest.approx(2 / 3), "S2": None, "S3": pytest.approx(1 / 3), "S9": 0.0}
    assert result["support"] == {"S1": 3, "S2": 0, "S3": 3, "S9": 1}
    assert result["confusion_rows"] == ["S1", "S2", "S3", "S9"]
    assert result["confusion_columns"] == ["S1", "S2", "S3", "(unclassified)"]
    assert result["confusion"] == [[2, 1, 0, 0], [0, 0, 0, 0], [1, 0, 1, 1], [0, 0, 1, 0]]
    json.dumps(result)
    # the same truth as a DataArray on sensor coordinates
    on_grid = xr.DataArray(truth, dims=("y", "x"), coords={"y": np.arange(110), "x": np.arange(70)})
    assert score(label, on_grid, truth_classes, classes) == result


def test_score_maps_classes_by_name():
    label = labels([[0, 1, 2]])
    truth = np.zeros((Y0 + 1, X0 + 3), dtype=int)
    truth[Y0, X0 : X0 + 3] = [2, 1, 0]
    assert score(label, truth, ["S3", "S2", "S1"], ["S1", "S2", "S3"])["accuracy"] == 1.0
    assert score(label, truth, ["S1", "S2", "S3"], ["S1", "S2", "S3"])["accuracy"] == pytest.approx(1 / 3)
    with pytest.raises(ValueError, match="does not cover"):
        score(labels([[0]], y0=200), truth, ["S1"], ["S1"])


def test_class_fractions():
    result = class_fractions(labels([[0, 0, 2, -1], [2, 2, 2, 0]]), ["S1", "S2", "S3"])
    assert result == {"n_pixels": 8, "fractions": {"S1": 0.375, "S2": 0.0, "S3": 0.5}, "unclassified": 0.125}
    json.dumps(result)
