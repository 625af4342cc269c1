"""Figures and tables of the report: each from small synthetic stores, the calibration's kept samples, the report."""

import gc
import io
import json
import os
import subprocess
import sys
from pathlib import Path

import matplotlib
import numpy as np
import pandas as pd
import pytest
import xarray as xr
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.image import imread
from matplotlib.patches import Rectangle
from PIL import Image

import surffin
from surffin.grid import Roi
from surffin.io.store import write_store
from surffin.method.calibration import (
    SAMPLE_QUANTITIES,
    TERMS,
    calibrate,
    correction_factor,
    instrument_function,
    reflectance,
)
from surffin.method.geometry import angle_of_incidence
from surffin.method.roughness import roughness_relation
from surffin.pipeline.analyses import run_figures
from surffin.pipeline.run import run_roughness_map
from surffin.report import figures
from surffin.report.canvas import DPI, DRAWING, collector_paused, figure, save
from surffin.report.figures import (
    FIGURE_KINDS,
    accuracy_table,
    parameter_table,
    plot_calibration_fit,
    plot_feature_space,
    plot_features,
    plot_labels,
    plot_r2_map,
    plot_wall_reflectance,
    write_table,
)

REPO = Path(__file__).resolve().parents[1]
HEIGHT, WIDTH = 24, 32
CLASSES = ["S1", "S2", "S3"]
ROI = Roi((6, 18), (8, 24))


def sensor_coords(y0=0, x0=0, height=HEIGHT, width=WIDTH):
    return {"y": np.arange(y0, y0 + height), "x": np.arange(x0, x0 + width)}


@pytest.fixture(scope="module")
def calibration():
    """A calibration store's content: coefficients with some spread, kept wall observations, scale k."""
    rng = np.random.default_rng(0)
    shape = (HEIGHT, WIDTH)
    coef = np.stack(
        [
            rng.uniform(50, 70, shape),
            rng.uniform(180, 220, shape),
            rng.uniform(-0.3, -0.2, shape),
            rng.uniform(0.04, 0.06, shape),
            np.ones(shape),
        ]
    )
    coef[3] = -0.2 * coef[2] + 0.0002 * rng.standard_normal(shape)  # C, D anti-correlated as in Table 2
    status = np.zeros(shape, dtype=np.int8)
    status[0, :4] = 1
    coef[:, status != 0] = np.nan
    scale_k, n_views = 2.0, 12

    def observe(rows, columns, count):
        distance = rng.uniform(0.3, 1.0, count)
        aoi = rng.uniform(0.0, 0.7, count)
        f = instrument_function(coef[:, rows, columns], distance, aoi)
        intensity = f * np.cos(aoi) * (1 + 0.02 * rng.standard_normal(count))
        return np.stack([intensity, distance, aoi, intensity / (scale_k * f)], axis=-1)

    sample_y, sample_x = np.array([6, 6, 18, 18]), np.array([8, 24, 8, 24])
    sample_obs = np.stack([observe(y, x, n_views) for y, x in zip(sample_y, sample_x)])
    wall_y, wall_x = rng.integers(1, HEIGHT, 300), rng.integers(4, WIDTH, 300)
    wall_obs = observe(wall_y, wall_x, 300)
    image = np.moveaxis(observe(*np.indices(shape), shape), -1, 0)
    return xr.Dataset(
        {
            "coef": (("term", "y", "x"), coef),
            "r2": (("y", "x"), np.where(status == 0, rng.uniform(0.95, 1.0, shape), np.nan)),
            "status": (("y", "x"), status),
            "sample_obs": (("sample_pixel", "view", "quantity"), sample_obs),
            "wall_obs": (("wall_sample", "quantity"), wall_obs),
            "wall_image": (("quantity", "y", "x"), image, {"view": "w003"}),
        },
        coords={
            "term": list(TERMS),
            **sensor_coords(),
            "quantity": list(SAMPLE_QUANTITIES),
            "view": [f"w{i:03d}" for i in range(n_views)],
            "sample_y": ("sample_pixel", sample_y),
            "sample_x": ("sample_pixel", sample_x),
            "wall_y": ("wall_sample", wall_y),
            "wall_x": ("wall_sample", wall_x),
            "wall_view": ("wall_sample", np.repeat([f"w{i:03d}" for i in range(n_views)], 25)),
        },
        attrs={"scale_k": scale_k, "reference_reflectance": 0.6},
    )


def training_set():
    rng = np.random.default_rng(1)
    centres = {"S1": (0.8, 1.3, 0.015), "S2": (0.86, 1.24, 0.018), "S3": (0.92, 1.17, 0.02)}
    values = np.concatenate([rng.normal(centre, (0.01, 0.02, 0.002), (200, 3)) for centre in centres.values()])
    return xr.Dataset(
        {
            "features": (("sample", "feature"), values),
            "class": ("sample", np.repeat(list(centres), 200)),
        },
        coords={"feature": ["R0", "n", "variability"]},
        attrs={"classes": CLASSES, "items": CLASSES},
    )


def item_stores(kind="specimen"):
    """features (y, x) and registered (view, y, x) of an item on a cropped grid."""
    rng = np.random.default_rng(2)
    coords = sensor_coords(4, 4, HEIGHT - 8, WIDTH - 8)
    shape = (HEIGHT - 8, WIDTH - 8)
    features = xr.Dataset(
        {
            "R0": (("y", "x"), rng.normal(0.85, 0.02, shape)),
            "n": (("y", "x"), rng.normal(1.2, 0.03, shape)),
            "variability": (("y", "x"), rng.uniform(0.01, 0.03, shape)),
        },
        coords=coords,
        attrs={"item": "S2", "kind": kind, "class": "S2", "smoothing_size": 7},
    )
    aoi = np.stack([np.full(shape, angle) + 0.01 * rng.standard_normal(shape) for angle in (0.1, 0.35, 0.6)])
    features["R0"][0, 0] = np.nan
    registered = xr.Dataset(
        {"aoi": (("view", "y", "x"), aoi), "reflectance": (("view", "y", "x"), 0.85 * np.cos(aoi))},
        coords={"view": ["v00", "v01", "v02"], **coords},
    )
    return features, registered


def scene_stores(seed=3):
    rng = np.random.default_rng(seed)
    coords = sensor_coords(4, 4, HEIGHT - 8, WIDTH - 8)
    shape = (HEIGHT - 8, WIDTH - 8)
    label = rng.integers(-1, len(CLASSES), shape).astype(np.int16)
    attrs = {"flag_values": [0, 1, 2], "flag_meanings": " ".join(CLASSES), "filter": "median", "filter_size": 5}
    labels = xr.Dataset(
        {"label": (("y", "x"), label, attrs), "label_filtered": (("y", "x"), np.maximum(label, 0), attrs)},
        coords=coords,
        attrs={"item": "T1"},
    )
    ingest = xr.Dataset(
        {
            "intensity": (("view", "y", "x"), rng.uniform(100, 1000, (2, *shape))),
            "valid": (("view", "y", "x"), np.ones((2, *shape), dtype=bool)),
        },
        coords={"view": ["v00", "v01"], **coords},
        attrs={"reference_view": "v00"},
    )
    return labels, ingest


SUMMARY = {
    "items": {},
    "scenes": {
        "T1": {
            "class_fractions": {
                variable: {"n_pixels": 384, "fractions": {"S1": 0.5, "S2": 0.25, "S3": 0.125}, "unclassified": 0.125}
                for variable in ("label", "label_filtered")
            },
            "accuracy": {
                "label": {"accuracy": 0.91234, "n_scored": 300},
                "label_filtered": {"accuracy": 0.98765, "n_scored": 300},
            },
        },
        "T2": {
            "class_fractions": {
                variable: {"n_pixels": 100, "fractions": {"S1": 1.0}, "unclassified": 0.0}
                for variable in ("label", "label_filtered")
            }
        },
    },
}


def png(path):
    """The image (rows, columns, channels) of a PNG file, checked to be one."""
    assert Path(path).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    return imread(path)


def assert_drawn(path, min_size=(300, 500)):
    image = png(path)
    assert image.shape[0] >= min_size[0] and image.shape[1] >= min_size[1]
    assert image[..., :3].std() > 0.05  # not a blank canvas


# --- each figure ------------------------------------------------------------------------------


def test_calibration_figures_are_drawn(calibration, tmp_path):
    assert_drawn(plot_calibration_fit(calibration, tmp_path / "fit.png"))
    assert_drawn(plot_r2_map(calibration, tmp_path / "r2.png"))
    assert_drawn(plot_wall_reflectance(calibration, tmp_path / "wall.png"))


def test_calibration_figures_depend_on_the_data(calibration, tmp_path):
    other = calibration.copy(deep=True)
    other["sample_obs"].loc[{"quantity": "intensity"}] *= 1.5
    first = png(plot_calibration_fit(calibration, tmp_path / "a.png"))
    second = png(plot_calibration_fit(other, tmp_path / "b.png"))
    assert first.shape != second.shape or not np.array_equal(first, second)


def test_a_calibration_without_samples_gives_a_notice_not_an_error(calibration, tmp_path):
    old = calibration[["coef", "r2", "status"]]
    for plot in (plot_calibration_fit, plot_wall_reflectance):
        image = png(plot(old, tmp_path / f"{plot.__name__}.png"))
        assert image.shape[0] > 100
    assert_drawn(plot_r2_map(old, tmp_path / "r2.png"))


def test_parameter_table_is_table_2(calibration, tmp_path):
    table = parameter_table(calibration)
    fitted = calibration["coef"].values[:, calibration["status"].values == 0]
    np.testing.assert_allclose(table.loc[list("ABCD"), list("ABCD")].values, np.corrcoef(fitted[:4]), atol=1e-12)
    assert table.loc["C", "D"] < -0.99
    assert table.loc["E"].iloc[:5].isna().all()  # E = 1 does not vary
    for index, term in enumerate(TERMS):
        expected = 100 * fitted[index].std() / abs(fitted[index].mean())
        assert table.loc["variability (%)", term] == pytest.approx(expected, abs=1e-9)
    assert table.loc["paper variability (%)", "A"] == 8.94
    html = write_table(table, tmp_path / "t.html").read_text()
    assert f"{table.loc['C', 'D']:.2f}" in html and "Table 2" in html
    back = pd.read_csv(write_table(table, tmp_path / "t.csv"), index_col=0)
    assert back.loc["variability (%)", "B"] == pytest.approx(table.loc["variability (%)", "B"], rel=1e-5)


def test_feature_figures_are_drawn(tmp_path):
    features, registered = item_stores()
    assert_drawn(plot_features(features, registered, tmp_path / "roi.png", roi=ROI))
    scene_features, _ = item_stores("scene")
    assert_drawn(plot_features(scene_features, registered, tmp_path / "whole.png"))
    # with the uncertainty maps of a features store of this surffin (the stores above have none)
    uncertain = features.assign(R0_uncertainty=0.01 * features["R0"], n_uncertainty=0.02 * features["n"])
    uncertain.attrs["uncertainty_effective_pixels"] = 3.2
    without = png(plot_features(features, registered, tmp_path / "without.png", roi=ROI))
    shown = png(plot_features(uncertain, registered, tmp_path / "with.png", roi=ROI))
    assert_drawn(tmp_path / "with.png")
    assert not np.array_equal(without, shown)
    assert_drawn(plot_feature_space(training_set(), tmp_path / "space.png"))


def test_feature_figure_keeps_its_scales_roi_and_legend(tmp_path, monkeypatch):
    drawn = []
    monkeypatch.setattr(figures, "save", lambda fig, path, **options: drawn.append(fig) or Path(path))
    features, registered = item_stores()
    uncertain = features.assign(R0_uncertainty=0.01 * features["R0"], n_uncertainty=0.02 * features["n"])
    plot_features(uncertain, registered, tmp_path / "f.png", roi=ROI)
    (fig,) = drawn
    FigureCanvasAgg(fig).draw()
    names = ["R0", "n", "variability", "R0_uncertainty", "n_uncertainty"]
    panels = [ax for ax in fig.axes if ax.images]
    assert [ax.images[0].get_array().shape for ax in panels] == [features["R0"].shape] * len(names)
    assert all(any(isinstance(p, Rectangle) and p.get_linestyle() == "--" for p in ax.patches) for ax in panels)
    titles = [ax.get_title() for ax in panels]
    assert titles[0] == "R0: reflectance at normal incidence"  # linear: no claim of a log scale
    assert titles[3] == "uncertainty of the smoothed R0 (log scale)"
    bars = {ax.get_ylabel(): ax for ax in fig.axes if ax.get_ylabel().endswith(" (1)")}
    assert sorted(bars) == sorted(f"{name} (1)" for name in names)
    for name in names:  # each colour scale readable: at least two labelled values; the maps of spread logarithmic
        bar = bars[f"{name} (1)"]
        assert len([label for label in bar.get_yticklabels() if label.get_text()]) >= 2
        assert bar.get_yscale() == ("linear" if name in ("R0", "n") else "log")
    first, *others = panels  # sensor coordinates on the first panel only
    assert (first.get_xlabel(), first.get_ylabel()) == ("sensor column x (px)", "sensor row y (px)")
    assert len([label for label in first.get_xticklabels() if label.get_text()]) >= 2
    assert not any(axis.get_visible() for ax in others for axis in (ax.xaxis, ax.yaxis))  # no ticks drawn
    (legend,) = [ax.get_legend() for ax in fig.axes if ax.get_legend()]
    entries = [text.get_text() for text in legend.get_texts()]
    assert entries[:3] == ["view v00", "view v01", "view v02"] and entries[3].startswith("model at median R0 = ")


def test_a_feature_figure_drawn_after_others_is_the_one_drawn_alone(tmp_path):
    # Each item's figure drawn after other items in this process (as in a worker), byte for byte the one a new
    # process draws: nothing of a figure is left for the next, of the same shape and panels or not.
    features, registered = item_stores()
    uncertain = features.assign(R0_uncertainty=0.01 * features["R0"], n_uncertainty=0.02 * features["n"])
    scene = item_stores("scene")[0].assign(R0=features["R0"] * 0.9, n=features["n"] + 0.1)
    scene.attrs["item"] = "T1"
    items = {
        "specimen": (features, ROI),
        "uncertain": (uncertain, ROI),
        "narrow": (features.isel(x=slice(0, 10)), Roi((6, 18), (8, 12))),
        "scene": (scene, None),
    }
    inputs = {"registered": str(write_store(registered, tmp_path / "registered.zarr"))}
    for name, (store, roi) in items.items():
        inputs[name] = str(write_store(store, tmp_path / f"{name}.zarr"))

    def draw(name, path):
        run_figures({"features": path}, features=inputs[name], registered=inputs["registered"], roi=items[name][1])
        return Path(path).read_bytes()

    drawn = [
        (name, draw(name, tmp_path / f"{index}-{name}.png"))
        for index, name in enumerate(("scene", "uncertain", "narrow", "specimen", "scene"))
    ]
    script = (
        "import json, sys\nfrom surffin.pipeline.analyses import run_figures\n"
        "run_figures({'features': sys.argv[1]}, features=sys.argv[2], registered=sys.argv[3], "
        "roi=json.loads(sys.argv[4]))"
    )
    root = str(Path(surffin.__file__).resolve().parents[1])  # this surffin in the new process too
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, (root, os.environ.get("PYTHONPATH"))))}
    alone = {}
    for name in ("specimen", "scene"):
        roi = json.dumps(None if items[name][1] is None else items[name][1].as_mapping())
        path = tmp_path / f"alone-{name}.png"
        subprocess.run(
            [sys.executable, "-c", script, path, inputs[name], inputs["registered"], roi], check=True, env=env
        )
        alone[name] = path.read_bytes()
    assert [content == alone[name] for name, content in drawn if name in alone] == [True] * 3
    assert drawn[0][1] != drawn[3][1]


def test_the_collector_is_paused_for_a_figure_only():
    with collector_paused():
        assert not gc.isenabled()
    assert gc.isenabled()
    with pytest.raises(ValueError), collector_paused():
        raise ValueError
    assert gc.isenabled()
    gc.disable()
    try:
        with collector_paused():
            pass
        assert not gc.isenabled()  # left as it was
    finally:
        gc.enable()


@pytest.mark.parametrize("dpi", [DPI, 100])
def test_a_saved_png_has_matplotlibs_pixels_and_resolution(tmp_path, dpi):
    fig = figure(3.0, 2.0)
    ax = fig.add_subplot()
    ax.imshow(np.random.default_rng(0).random((5, 7)))
    ax.set_title("θ")
    path = save(fig, tmp_path / "ours.png", dpi=dpi)
    theirs = io.BytesIO()
    with matplotlib.rc_context(DRAWING):
        fig.savefig(theirs, format="png", dpi=dpi)
    with Image.open(path) as image, Image.open(theirs) as reference:
        np.testing.assert_array_equal(np.asarray(image), np.asarray(reference))
        assert image.info["dpi"] == pytest.approx((dpi, dpi), abs=0.05)  # as pixels per metre


def test_label_map_shows_the_labels(tmp_path):
    labels, ingest = scene_stores()
    first = png(plot_labels(labels, ingest, tmp_path / "a.png", scores=SUMMARY["scenes"]["T1"]))
    assert_drawn(tmp_path / "a.png")
    changed = labels.copy(deep=True)
    changed["label"].values[:] = np.roll(changed["label"].values, 3, axis=1)
    second = png(plot_labels(changed, ingest, tmp_path / "b.png", scores=SUMMARY["scenes"]["T1"]))
    assert first.shape == second.shape and not np.array_equal(first, second)
    same = png(plot_labels(labels, ingest, tmp_path / "c.png", scores=SUMMARY["scenes"]["T1"]))
    np.testing.assert_array_equal(first, same)
    # unclassified pixels are drawn (dark), and their count by reason noted
    declined = labels.copy(deep=True)
    declined["label"].values[:3] = -1
    declined["label"].attrs["unclassified"] = {"missing_feature": 0, "ambiguous": 3 * labels.sizes["x"]}
    assert not np.array_equal(
        first, png(plot_labels(declined, ingest, tmp_path / "d.png", scores=SUMMARY["scenes"]["T1"]))
    )


def test_accuracy_table_reports_the_summary(tmp_path):
    table = accuracy_table(SUMMARY)
    assert table.loc[("T1", "label"), "accuracy (%)"] == pytest.approx(91.234)
    assert table.loc[("T1", "label_filtered"), "accuracy (%)"] == pytest.approx(98.765)
    assert np.isnan(table.loc[("T2", "label"), "accuracy (%)"])  # no truth
    assert table.loc[("T1", "label"), "S3 (%)"] == pytest.approx(12.5)
    assert table.loc[("T2", "label"), "unclassified (%)"] == 0
    html = write_table(table, tmp_path / "accuracy.html").read_text()
    assert "91.23" in html and "98.77" in html
    back = pd.read_csv(write_table(table, tmp_path / "accuracy.csv"), index_col=[0, 1])
    assert back.loc[("T1", "label_filtered"), "accuracy (%)"] == pytest.approx(98.765)


# --- run_figures ------------------------------------------------------------------------------------


@pytest.fixture
def stores(calibration, tmp_path):
    features, registered = item_stores()
    labels, ingest = scene_stores()
    summary = tmp_path / "summary.json"
    summary.write_text(json.dumps(SUMMARY))
    relation = tmp_path / "relation.json"
    relation.write_text(
        json.dumps(roughness_relation({"S1": 1.28, "S2": 1.24, "S3": 1.17}, {"S1": 0.007, "S2": 0.026, "S3": 0.053}))
    )
    features_store = write_store(features, tmp_path / "features.zarr")
    return {
        "calibration": write_store(calibration, tmp_path / "calibration.zarr"),
        "training": write_store(training_set(), tmp_path / "training.zarr"),
        "features": features_store,
        "registered": write_store(registered, tmp_path / "registered.zarr"),
        "labels": write_store(labels, tmp_path / "labels.zarr"),
        "ingest": write_store(ingest, tmp_path / "ingest.zarr"),
        "roughness": run_roughness_map(tmp_path / "roughness.zarr", features=features_store, relation=relation),
        "summary": summary,
    }


#: The files of the campaign-wide figure rules (calibration and classification).
CAMPAIGN_FILES = {
    "calibration_fit.png",
    "calibration_r2.png",
    "calibration_parameters.html",
    "calibration_parameters.csv",
    "wall_reflectance.png",
    "feature_space.png",
    "accuracy.html",
    "accuracy.csv",
}


def test_run_figures_writes_every_requested_file(stores, tmp_path):
    out = tmp_path / "figures"
    outputs = {
        "calibration_fit": out / "calibration_fit.png",
        "calibration_r2": out / "calibration_r2.png",
        "calibration_table": [out / "calibration_parameters.html", out / "calibration_parameters.csv"],
        "wall_reflectance": out / "wall_reflectance.png",
        "feature_space": out / "feature_space.png",
        "accuracy_table": [out / "accuracy.html", out / "accuracy.csv"],
        "features": out / "features" / "S2.png",
        "labels": out / "labels" / "T1.png",
        "roughness": out / "roughness" / "T1.png",
    }
    assert set(outputs) == set(FIGURE_KINDS)
    written = run_figures(outputs, roi={"y": [6, 18], "x": [8, 24]}, log_path=tmp_path / "figures.log", **stores)
    expected = {
        *CAMPAIGN_FILES,
        "features/S2.png",
        "labels/T1.png",
        "roughness/T1.png",
    }
    assert {str(path.relative_to(out)) for path in written} == expected
    assert {str(path.relative_to(out)) for path in out.rglob("*") if path.is_file()} == expected
    for path in out.rglob("*.png"):
        assert_drawn(path)
    assert "98.77" in (out / "accuracy.html").read_text()
    assert "features/S2.png" in (tmp_path / "figures.log").read_text()


def test_run_figures_refuses_unknown_kinds_and_missing_inputs(stores, tmp_path):
    with pytest.raises(ValueError, match="unknown figure kind 'histogram'"):
        run_figures({"histogram": tmp_path / "h.png"}, **stores)
    with pytest.raises(ValueError, match="needs \\['registered'\\]"):
        run_figures({"features": tmp_path / "f.png"}, features=stores["features"])
    assert not list(tmp_path.glob("*.png"))


# --- the calibration's kept observations ------------------------------------------------------------


def test_calibrate_keeps_raw_wall_observations_with_their_reflectance(tiny_campaign):
    camp = surffin.read_campaign(tiny_campaign)
    ds = calibrate(camp)
    wall = camp.calibration.wall
    views = {path.stem: camp.read_view(path) for path in wall}
    assert list(ds["view"].values) == list(views)
    assert list(ds["quantity"].values) == list(SAMPLE_QUANTITIES)
    (top, bottom), (left, right) = camp.crop.y, camp.crop.x

    def inside_crop(rows, columns):
        return bool(((rows >= top) & (rows < bottom) & (columns >= left) & (columns < right)).all())

    # six distinct sample pixels in the crop; their stored intensities are those of the view files
    rows, columns = ds["sample_y"].values, ds["sample_x"].values
    assert ds.sizes["sample_pixel"] == 6 and len(set(zip(rows, columns))) == 6 and inside_crop(rows, columns)
    for stem, view in views.items():
        stored = ds["sample_obs"].sel(quantity="intensity", view=stem).values
        np.testing.assert_array_equal(stored, np.where(view.valid, view.intensity, np.nan)[rows, columns])
    # random pixels: a bounded number in the crop, spread over all views, their intensity that of their view
    wall_y, wall_x, wall_view = ds["wall_y"].values, ds["wall_x"].values, ds["wall_view"].values
    assert 2000 <= ds.sizes["wall_sample"] <= 3200 and inside_crop(wall_y, wall_x)
    assert set(wall_view.tolist()) == set(views)
    obs = ds["wall_obs"]
    files = [views[str(stem)].intensity[y, x] for stem, y, x in zip(wall_view, wall_y, wall_x)]
    np.testing.assert_array_equal(obs.sel(quantity="intensity").values, files)
    intensity, distance, aoi = (obs.sel(quantity=q).values for q in SAMPLE_QUANTITIES[:3])
    # the instrument: eq. 5's f times the calibration's residual correction c
    f = instrument_function(ds["coef"].values[:, wall_y, wall_x], distance, aoi)
    f = f * np.asarray(correction_factor(ds["correction"], distance, aoi))
    np.testing.assert_allclose(obs.sel(quantity="reflectance").values, intensity / (ds.attrs["scale_k"] * f))
    # the wall image: the view with the smallest median AOI over the crop, reflectance as reflectance() gives it
    geometry = {
        stem: angle_of_incidence(
            xr.DataArray(
                view.xyz[None],
                dims=("view", "y", "x", "axis"),
                coords={"view": [stem], **sensor_coords(height=view.xyz.shape[0], width=view.xyz.shape[1])},
            ),
        ).isel(view=0)
        for stem, view in views.items()
    }
    medians = {stem: float(g["aoi"][top:bottom, left:right].median()) for stem, g in geometry.items()}
    image = ds["wall_image"]
    assert image.attrs["view"] == min(medians, key=medians.get)
    layer = {q: image.sel(quantity=q, drop=True).expand_dims(view=[image.attrs["view"]]) for q in SAMPLE_QUANTITIES}
    public = reflectance(
        layer["intensity"], layer["distance"], layer["aoi"], ds["coef"], ds.attrs["scale_k"], ds["correction"]
    )
    np.testing.assert_allclose(layer["reflectance"].values, public.values, rtol=1e-6)


# --- the workflow's report ---------------------------------------------------------------------------


@pytest.mark.slow
def test_snakemake_report_holds_every_figure(tiny_run, snakemake, planned_jobs, tmp_path):
    done = tiny_run
    figures = done / "processed" / "figures"
    camp = surffin.read_campaign(done / "raw")
    expected = {
        *CAMPAIGN_FILES,
        "calibration_correlation.png",
        "calibration_repeatability.png",
        *(f"features/{name}.png" for name in camp.items),
        *(f"labels/{name}.png" for name in camp.scenes),
        *(f"roughness/{name}.png" for name in camp.scenes),
    }
    assert {str(path.relative_to(figures)) for path in figures.rglob("*") if path.is_file()} == expected
    for path in figures.rglob("*.png"):
        assert_drawn(path)
    summary = json.loads((done / "processed" / "summary.json").read_text())
    accuracy = summary["scenes"]["T1"]["accuracy"]["label_filtered"]["accuracy"]
    assert f"{100 * accuracy:.2f}" in (figures / "accuracy.html").read_text()
    run = snakemake(done, "--report", str(tmp_path / "report.html"))
    assert run.returncode == 0, run.stderr[-3000:]
    report = (tmp_path / "report.html").read_text()
    for name in (
        "calibration_fit.png",
        "wall_reflectance.png",
        "accuracy.html",
        "feature_space.png",
        "calibration_repeatability.png",
        "separation.png",
        "views.png",
    ):
        assert name in report
    assert "Undefined substitution" not in run.stderr + run.stdout  # captions are valid reStructuredText
    # a smoothing change redraws the feature figures and what follows, not the calibration's
    jobs = planned_jobs(done, overrides={"features": {"smoothing": 5}})
    items, scenes = len(camp.items), len(camp.scenes)
    assert jobs["item_figures"] == items and jobs["scene_figures"] == scenes and jobs["classification_figures"] == 1
    assert "calibration" not in jobs and "calibration_figures" not in jobs


def test_the_report_needs_nothing_beyond_surffins_own_requirements():
    # `snakemake --report` needs pygments, which snakemake installs only with its `reports`
    # extra (surffin's `workflow` extra asks for it); the test extras bring it through pytest, so the
    # suite alone would not notice.
    from importlib.metadata import requires

    from packaging.requirements import Requirement

    workflow = [req for req in map(Requirement, requires("surffin")) if req.marker]
    snakemake = [req for req in workflow if req.name == "snakemake" and req.marker.evaluate({"extra": "workflow"})]
    assert len(snakemake) == 1 and "reports" in snakemake[0].extras
