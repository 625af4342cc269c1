"""Calibration diagnostics and repeatability: statistics against independent references; the tiny campaign."""

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
import yaml
from scipy.optimize import least_squares
from scipy.stats import norm

import surffin
from surffin.analysis.diagnostics import (
    coefficient_statistics,
    compare_calibrations,
    process_specimens,
    relative_difference,
    representative_specimens,
    spread,
    variability,
    wall_features,
)
from surffin.errors import CalibrationError
from surffin.grid import Roi
from surffin.io.ingest import ingest_item
from surffin.io.store import open_store
from surffin.method.calibration import TERMS, calibration_set, correction_factor, instrument_function
from surffin.method.features import select_roi
from surffin.method.geometry import DEFAULT_JUMP, DEFAULT_MAX_WINDOW
from surffin.method.stages import process_item
from surffin.pipeline.analyses import run_calibration_diagnostics
from surffin.pipeline.parameters import read_config
from surffin.pipeline.run import run_calibration
from surffin.pipeline.workflow import Plan
from surffin.report.diagnostics import CORRELATION_FIGURE, REPEATABILITY_FIGURE
from surffin.simulate import PRESETS
from surffin.simulate.plan import REPEAT_FOLDERS

TINY = PRESETS["tiny"]
HELD_OUT = "w005"
ITEM_PARAMS = {}
AOI = {"window": 15, "jump": DEFAULT_JUMP, "max_window": DEFAULT_MAX_WINDOW}


def calibration_dataset(coef, r2=None, status=None, scale_k=2.0):
    """A calibration-like Dataset of coefficients (5, H, W) on sensor coordinates."""
    shape = coef.shape[1:]
    r2 = np.full(shape, 0.99) if r2 is None else r2
    status = np.zeros(shape, dtype=np.int8) if status is None else status
    return xr.Dataset(
        {"coef": (("term", "y", "x"), coef), "r2": (("y", "x"), r2), "status": (("y", "x"), status)},
        coords={"term": list(TERMS), "y": np.arange(shape[0]), "x": np.arange(shape[1])},
        attrs={"scale_k": scale_k},
    )


# --- statistics against analytic and numpy references -------------------------------------------


def test_variability_of_a_known_field():
    # +-s around m on alternating pixels: std = MAD = s exactly
    m, s = np.array([[10.0], [-0.25]]), np.array([[0.5], [0.01]])
    values = m + s * np.where(np.arange(1000) % 2, 1.0, -1.0)
    result = variability(values)
    np.testing.assert_allclose(result["plain"], 100 * np.abs(s[:, 0] / m[:, 0]), rtol=1e-12)
    np.testing.assert_allclose(result["robust"], 100 * 1.4826 * np.abs(s[:, 0] / m[:, 0]), rtol=1e-12)
    # normal quantiles: both are s / m; a few wild pixels move the plain one, hardly the robust one; NaN is ignored
    field = m + s * norm.ppf((np.arange(2000) + 0.5) / 2000)
    wild = np.concatenate([field, np.full((2, 5), 1e3), np.full((2, 3), np.nan)], axis=1)
    np.testing.assert_allclose(variability(field)["robust"], 100 * np.abs(s[:, 0] / m[:, 0]), rtol=0.01)
    assert variability(wild)["plain"][0] > 10 * result["plain"][0]
    np.testing.assert_allclose(variability(wild)["robust"], 100 * np.abs(s[:, 0] / m[:, 0]), rtol=0.01)


def test_spread_and_relative_difference_of_known_values():
    values = np.array([0.5, 0.5, 0.52, 0.48, np.nan])
    out = spread(values)
    assert out["n_pixels"] == 4 and out["mean"] == pytest.approx(0.5) and out["median"] == pytest.approx(0.5)
    assert out["std"] == pytest.approx(np.std([0.5, 0.5, 0.52, 0.48]))
    assert out["robust_std"] == pytest.approx(1.4826 * 0.01)  # the median absolute deviation is 0.01
    assert spread([np.nan])["std"] is None
    x = np.random.default_rng(0).uniform(0.5, 1.5, 500)
    assert relative_difference(x, x) == {
        "n": 500,
        "median_abs_percent": 0.0,
        "mean_percent": 0.0,
        "std_percent": 0.0,
        "p95_abs_percent": 0.0,
    }
    eps = 0.02  # b = a (1 + eps): (a - b) / ((a + b) / 2) = -2 eps / (2 + eps) everywhere
    out = relative_difference(x, x * (1 + eps))
    assert out["median_abs_percent"] == pytest.approx(100 * 2 * eps / (2 + eps), rel=1e-12)
    assert out["mean_percent"] == pytest.approx(-100 * 2 * eps / (2 + eps), rel=1e-12)
    assert out["std_percent"] == pytest.approx(0.0, abs=1e-12)
    assert relative_difference(x, x + 0.01, scale=0.5)["median_abs_percent"] == pytest.approx(2.0)


def test_correlation_and_fit_quality_of_a_known_coefficient_image():
    rng = np.random.default_rng(1)
    target = np.array([[1.0, 0.3, 0.2, -0.2], [0.3, 1.0, 0.1, -0.1], [0.2, 0.1, 1.0, -0.95], [-0.2, -0.1, -0.95, 1.0]])
    shape, region = (120, 150), Roi((10, 110), (20, 140))
    draws = np.linalg.cholesky(target) @ rng.standard_normal((4, shape[0] * shape[1]))
    mean, scale = np.array([60.0, 200.0, -0.25, 0.05]), np.array([4.0, 8.0, 0.01, 0.002])
    coef = np.concatenate([mean[:, None] + scale[:, None] * draws, np.ones((1, draws.shape[1]))]).reshape(5, *shape)
    status = np.zeros(shape, dtype=np.int8)
    status[40:45, 50:90] = 3  # unfitted pixels inside the region
    coef[:, status != 0] = np.nan
    coef[:, :5] = 1e6  # wild pixels outside the region
    r2 = rng.uniform(0.95, 1.0, shape)
    stats = coefficient_statistics(calibration_dataset(coef, r2, status), region)
    inside = coef[:, 10:110, 20:140][:, status[10:110, 20:140] == 0]
    matrix = np.array(stats["correlation"]["matrix"])
    assert stats["correlation"]["terms"] == ["A", "B", "C", "D"]
    np.testing.assert_allclose(matrix, np.corrcoef(inside[:4]), atol=1e-12)
    np.testing.assert_allclose(matrix, target, atol=0.03)
    assert stats["fit"]["n_fitted"] == inside.shape[1] and stats["fit"]["n_pixels"] == 100 * 120
    assert stats["fit"]["mean_r2"] == pytest.approx(r2[10:110, 20:140][status[10:110, 20:140] == 0].mean())
    for index, term in enumerate(TERMS[:4]):
        expected = 100 * inside[index].std() / abs(inside[index].mean())
        assert stats["variability_percent"]["plain"][term] == pytest.approx(expected, rel=1e-10)
        robust = stats["variability_percent"]["robust"][term]
        assert robust == pytest.approx(100 * scale[index] / abs(mean[index]), rel=0.05)
    assert stats["variability_percent"]["plain"]["E"] == 0.0


def test_calibration_compared_with_itself_and_with_a_known_perturbation():
    rng = np.random.default_rng(2)
    shape = (20, 30)
    coef = np.stack(
        [
            rng.uniform(50, 70, shape),
            rng.uniform(180, 220, shape),
            rng.uniform(-0.3, -0.2, shape),
            rng.uniform(0.04, 0.06, shape),
            np.ones(shape),
        ]
    )
    first = calibration_dataset(coef)
    grid = np.meshgrid(np.linspace(0.3, 1.0, 5), np.linspace(0.0, 0.8, 4), indexing="ij")
    same = compare_calibrations(first, first, grid)
    assert same["n_pixels"] == 600 and same["scale_k"]["difference_percent"] == 0.0
    for part in (*same["coefficients"].values(), same["instrument_function"], same["calibration"]):
        assert part["median_abs_percent"] == 0.0 and part["p95_abs_percent"] == 0.0
    # the distance factor 1 % larger, k 1 % smaller: f differs by 1 % everywhere, k f not at all
    eps = 0.01
    second = calibration_dataset(coef * np.array([1 + eps, 1 + eps, 1, 1, 1])[:, None, None], scale_k=2.0 / (1 + eps))
    out = compare_calibrations(first, second, grid, Roi((0, 10), (0, 30)))
    assert out["n_pixels"] == 300
    a = coef[0, :10].ravel()
    assert out["coefficients"]["A"]["median_abs_percent"] == pytest.approx(
        np.median(100 * eps * a / (a.mean() * (1 + eps / 2))), rel=1e-12
    )
    assert out["coefficients"]["C"]["median_abs_percent"] == 0.0
    expected = 100 * 2 * eps / (2 + eps)
    assert out["instrument_function"]["median_abs_percent"] == pytest.approx(expected, rel=1e-10)
    assert out["instrument_function"]["median_pixel_max_abs_percent"] == pytest.approx(expected, rel=1e-10)
    assert out["scale_k"]["difference_percent"] == pytest.approx(expected, rel=1e-10)
    assert out["calibration"]["median_abs_percent"] == pytest.approx(0.0, abs=1e-12)


# --- the tiny campaign, with its repeat calibration set -------------------------------------------


@pytest.fixture(scope="module")
def tiny(tiny_campaign, tmp_path_factory):
    """A tiny campaign, its calibration without one wall view, the repeat calibration and the truth."""
    root = tmp_path_factory.mktemp("diagnostics")
    (root / "raw").symlink_to(tiny_campaign)
    (root / "raw-truth").symlink_to(f"{tiny_campaign}-truth")
    processed = root / "processed"
    params = {"exclude": [HELD_OUT]}
    first = run_calibration(root / "raw", processed / "calibration.zarr", params=params)
    repeat = run_calibration(root / "raw", processed / "repeat.zarr", folders=REPEAT_FOLDERS)
    return root, first, repeat


def test_one_specimen_per_class_is_reprocessed(tiny, tmp_path):
    root = tiny[0]
    assert representative_specimens(surffin.read_campaign(root / "raw")) == ["S1", "S2", "S3", "S4"]
    # a copy with a second specimen of class S2 listed first
    copy = shutil.copytree(root / "raw", tmp_path / "campaign")
    spec = yaml.safe_load((copy / "campaign.yaml").read_text())
    spec["specimens"] = {"S2b": {**spec["specimens"]["S2"]}, **spec["specimens"]}
    (copy / "campaign.yaml").write_text(yaml.safe_dump(spec, sort_keys=False))
    assert representative_specimens(surffin.read_campaign(copy)) == ["S2b", "S1", "S3", "S4"]


def diagnose(tiny, output, **kwargs):
    root, first, repeat = tiny
    path = run_calibration_diagnostics(
        root / output, calibration=first, campaign=root / "raw", item_params=ITEM_PARAMS, **kwargs
    )
    return json.loads(path.read_text())


@pytest.fixture(scope="module")
def report(tiny):
    root, first, repeat = tiny
    return diagnose(
        tiny,
        "diagnostics.json",
        repeat=repeat,
        repeat_folders=REPEAT_FOLDERS,
        instrument_truth=root / "raw-truth" / "instrument.zarr",
        figures_dir=root / "figures",
        log_path=root / "diagnostics.log",
    )


def test_the_repeat_set_is_the_same_camera_from_slightly_different_poses(tiny):
    root = tiny[0]
    camp = surffin.read_campaign(root / "raw")
    assert "repeat" not in (root / "raw" / "campaign.yaml").read_text()
    assert all("repeat" not in str(path) for item in camp.items.values() for path in item.views)
    repeat = calibration_set(camp, REPEAT_FOLDERS["wall"], REPEAT_FOLDERS["reference"])
    assert [path.stem for path in repeat.wall] == [path.stem for path in camp.calibration.wall]
    assert repeat.reference.roi == camp.calibration.reference.roi
    moves, turns = [], []
    for first, second in zip(camp.calibration.wall, repeat.wall):
        a, b = camp.read_view(first), camp.read_view(second)
        assert not np.array_equal(a.intensity, b.intensity)
        moves.append(np.linalg.norm(a.pose[:3, 3] - b.pose[:3, 3]))
        turns.append(np.degrees(np.arccos(np.clip(a.pose[:3, 2] @ b.pose[:3, 2], -1, 1))))
    # the target and distance move by up to repeat_shift, the tilt and azimuth turn by up to repeat_turn
    reach = math.sqrt(3) * TINY.repeat_shift + 2 * max(TINY.wall_distances) * math.radians(TINY.repeat_turn)
    assert 0 < min(moves) and max(moves) < reach  # metres
    assert 0 < max(turns) < 2 * TINY.repeat_turn  # degrees between the optical axes


def test_calibration_set_names_the_bad_folder(tiny):
    camp = surffin.read_campaign(tiny[0] / "raw")
    with pytest.raises(CalibrationError, match="nowhere"):
        calibration_set(camp, "nowhere", REPEAT_FOLDERS["reference"])
    with pytest.raises(CalibrationError, match="inside the campaign"):
        calibration_set(camp, "../raw-truth", REPEAT_FOLDERS["reference"])
    with pytest.raises(CalibrationError, match="at least 2"):
        calibration_set(camp, REPEAT_FOLDERS["wall"], "scenes/T1/..")  # a folder without views


def test_report_layout_and_figures(tiny, report):
    root = tiny[0]
    assert set(report) == {
        "campaign",
        "region",
        "inputs",
        "calibrations",
        "wall_features",
        "truth",
        "repeatability",
        "paper",
    }
    assert report["region"]["y"] == list(TINY.crop[0])
    assert set(report["calibrations"]) == {"first", "repeat"}
    assert report["calibrations"]["first"]["calibration_set"] == {
        "wall": "calibration/wall",
        "reference": "calibration/reference",
    }
    assert report["calibrations"]["repeat"]["calibration_set"] == REPEAT_FOLDERS
    assert report["calibrations"]["first"]["fit"]["mean_r2"] > 0.99
    for name in (CORRELATION_FIGURE, REPEATABILITY_FIGURE):
        assert (root / "figures" / name).read_bytes()[:4] == b"\x89PNG"
    assert "repeatability" in (root / "diagnostics.log").read_text()


def test_wall_features_say_which_views_were_fitted(report):
    rows = {(row["calibration"], row["wall"]): row for row in report["wall_features"]}
    walls = ("calibration/wall", REPEAT_FOLDERS["wall"])
    assert set(rows) == {(name, wall) for name in ("first", "repeat") for wall in walls}
    n_views = len(TINY.wall_distances) * len(TINY.wall_tilts)
    assert rows["first", "calibration/wall"]["views_in_fit"] == n_views - 1  # HELD_OUT left out of the fit
    assert rows["repeat", REPEAT_FOLDERS["wall"]]["views_in_fit"] == n_views
    assert rows["first", walls[1]]["views_in_fit"] == rows["repeat", walls[0]]["views_in_fit"] == 0
    for row in rows.values():
        assert row["R0"]["mean"] == pytest.approx(TINY.wall.R0, rel=0.01)  # the wall's reflectance, 1 / k
        assert row["n"]["median"] == pytest.approx(1.0, abs=0.01)  # Lambertian
    # a calibration has absorbed the noise of the views it was fitted to
    assert rows["first", "calibration/wall"]["R0"]["std"] < rows["first", REPEAT_FOLDERS["wall"]]["R0"]["std"]
    assert rows["repeat", REPEAT_FOLDERS["wall"]]["n"]["std"] < rows["repeat", "calibration/wall"]["n"]["std"]


def test_wall_fit_per_pixel_equals_least_squares(tiny):
    root, first, _ = tiny
    camp = surffin.read_campaign(root / "raw")
    calibration = open_store(first).load()
    observed, fits = wall_features(camp, camp.calibration.wall, {"first": calibration}, aoi=AOI)
    # the reflectance of one view: I / (k f c) by hand from the cube's own AOI
    view = camp.read_view(camp.calibration.wall[3])
    rows, columns = camp.crop.slices
    coef = calibration["coef"].values[:, rows, columns]
    distance = np.where(view.valid, np.linalg.norm(np.nan_to_num(view.xyz), axis=-1), np.nan)[rows, columns]
    aoi = observed["aoi"].values[3]
    instrument = instrument_function(coef, distance, aoi) * correction_factor(calibration["correction"], distance, aoi)
    by_hand = view.intensity[rows, columns] / (calibration.attrs["scale_k"] * instrument)
    np.testing.assert_allclose(observed["reflectance"].values[0, 3], by_hand, rtol=2e-6)
    for y, x in ((0, 0), (7, 31), (25, 50), (39, 59)):
        r, theta = observed["reflectance"].values[0, :, y, x], observed["aoi"].values[:, y, x]
        ok = np.isfinite(r) & np.isfinite(theta)
        r, theta = r[ok].astype(float), theta[ok].astype(float)

        def residual(p):
            return p[0] * np.cos((2 - 1 / p[1]) * theta) ** p[1] - r

        best = least_squares(residual, [0.5, 1.0], bounds=([0, 0.5], [np.inf, np.inf]), xtol=1e-14, ftol=1e-14)
        assert fits["R0"].values[0, y, x] == pytest.approx(best.x[0], rel=1e-6)
        assert fits["n"].values[0, y, x] == pytest.approx(best.x[1], rel=1e-5)


def test_repeatability_of_two_calibrations(report):
    rep = report["repeatability"]
    assert rep["available"] and rep["reason"] is None
    assert rep["calibration"]["median_abs_percent"] < 5  # k f of 16-view calibrations of an 80x60 sensor
    assert abs(rep["scale_k"]["difference_percent"]) < 1
    assert set(rep["specimens"]["items"]) == set(TINY.classes)
    for name in ("reflectance", "R0", "n"):
        assert 0 < rep["specimens"][name]["median_abs_percent"] < 5
    assert [wall["wall"] for wall in rep["wall"]] == ["calibration/wall", REPEAT_FOLDERS["wall"]]
    for name in ("first", "repeat"):
        assert report["truth"][name]["calibration"]["median_abs_percent"] < 5
    assert report["truth"]["correlation"]["terms"] == ["A", "B", "C", "D"]


def test_specimens_with_the_repeat_calibration_are_what_the_item_chain_makes(tiny):
    # the repeat's runs reuse the first run's AOI and registration maps, and fit the roi and a margin only
    root, first, repeat = tiny
    camp = surffin.read_campaign(root / "raw")
    calibrations = {"first": open_store(first).load(), "repeat": open_store(repeat).load()}
    out = process_specimens(camp, calibrations, ITEM_PARAMS)
    for name, runs in out.items():
        roi = camp.specimens[name].roi
        assert roi is not None and runs["repeat"].sizes["y"] == roi.shape[0]
        chain = process_item(ingest_item(camp, name), calibrations["repeat"], roi=roi, **ITEM_PARAMS)
        expected = select_roi(xr.merge([chain["registered"]["reflectance"], chain["features"]], compat="override"), roi)
        for variable in ("reflectance", "R0", "n", "R0_fit", "n_fit"):
            np.testing.assert_array_equal(runs["repeat"][variable].values, expected[variable].values)


@pytest.mark.slow  # a full snakemake run of the tiny campaign
def test_the_workflow_job_reads_the_specimens_stores_without_changing_a_number(tiny_run, tmp_path):
    processed = tiny_run / "processed"
    config = {**read_config(), "campaign": str(tiny_run / "raw"), "processed": str(processed)}
    plan = Plan.read(tiny_run / "raw", config)
    assert set(plan.diagnostics_stores()) == {"S1", "S2", "S3", "S4"}
    in_memory = run_calibration_diagnostics(
        tmp_path / "diagnostics.json",
        calibration=processed / "calibration.zarr",
        repeat=processed / "diagnostics" / "calibration-repeat.zarr",
        campaign=tiny_run / "raw",
        item_params=plan.diagnostics_item_parameters(),
    )
    written = json.loads((processed / "diagnostics" / "calibration.json").read_text())
    assert json.loads(in_memory.read_text()) == written


def test_repeatability_of_a_calibration_with_itself_is_zero(tiny):
    out = diagnose(tiny, "itself.json", repeat=tiny[1])["repeatability"]
    parts = [*out["coefficients"].values(), out["instrument_function"], out["calibration"]]
    parts += [wall[name] for wall in out["wall"] for name in ("reflectance", "R0", "n")]
    parts += [out["specimens"][name] for name in ("reflectance", "R0", "n", "R0_fit", "n_fit")]
    for part in parts:
        assert part["n"] > 0 and part["median_abs_percent"] == 0.0 and part["p95_abs_percent"] == 0.0


@pytest.mark.parametrize(
    ("folders", "reason"),
    [(None, "calibration_repeat: null"), ({"wall": "nope/wall", "reference": "nope/panel"}, "nope/panel")],
)
def test_without_a_repeat_the_report_says_why(tiny, folders, reason):
    root = tiny[0]
    out = diagnose(tiny, "alone.json", repeat_folders=folders, figures_dir=root / "alone", log_path=root / "alone.log")
    assert set(out["repeatability"]) == {"available", "reason"} and not out["repeatability"]["available"]
    assert reason in out["repeatability"]["reason"] and reason in (root / "alone.log").read_text()
    assert list(out["calibrations"]) == ["first"] and len(out["wall_features"]) == 1
    assert (root / "alone" / REPEATABILITY_FIGURE).is_file()


def test_config_turns_the_repeat_set_on_by_default():
    repo = Path(__file__).resolve().parents[1]
    config = yaml.safe_load((repo / "config" / "config.yaml").read_text())
    schema = yaml.safe_load((repo / "workflow" / "schemas" / "config.schema.yaml").read_text())
    assert config["calibration_repeat"] == REPEAT_FOLDERS
    assert schema["properties"]["calibration_repeat"]["default"] == REPEAT_FOLDERS
