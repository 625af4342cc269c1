"""Snakemake on a tiny synthetic campaign, in temporary working directories."""

import contextlib
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
import yaml

import surffin
from surffin.io.store import open_store
from surffin.paper import DOI
from surffin.pipeline.table import STAGES

REPO = Path(__file__).resolve().parents[1]
ITEM_CHAIN = {"ingest", "aoi", "reflectance", "registration", "features", "item_figures"}
ROUGHNESS = {"roughness_relation": 1, "roughness_map": 1, "roughness_figures": 1}
DOWNSTREAM = {
    "training": 1,
    "labels": 1,
    "summary": 1,
    "classification_figures": 1,
    "scene_figures": 1,
    "all": 1,
    "calibration_diagnostics": 1,
    "paper_comparison": 1,
    "export": 1,
    **ROUGHNESS,
}


@pytest.fixture
def done(tiny_run):
    """The session's complete run of the tiny campaign, shared by the read-only tests."""
    return tiny_run


@pytest.fixture
def fresh(fresh_run):
    return fresh_run


@pytest.mark.slow  # a full snakemake run of the tiny campaign
def test_every_store_follows_the_contract(done, tmp_path):
    camp = surffin.read_campaign(done / "raw")
    processed = done / "processed"
    stores = [path for path in processed.rglob("*.zarr") if (path / "zarr.json").is_file()]
    assert len(stores) == 5 * len(camp.items) + 4 + len(camp.scenes) * 2  # + calibrations, training, sensitivity
    for index, path in enumerate(stores):  # each records the code version the stage table gives its stage
        attrs = open_store(path).attrs
        assert attrs["surffin_code_version"] == STAGES[attrs["surffin_stage"]].version, path
        assert attrs["Conventions"].startswith("CF-") and DOI in attrs["references"], path
        # plain xarray opens it, and netCDF takes it as it is (nested attrs are JSON text)
        plain = xr.open_zarr(path)
        plain.to_netcdf(tmp_path / f"{index}.nc", engine="scipy")
        xr.testing.assert_equal(xr.open_dataset(tmp_path / f"{index}.nc", engine="scipy").load(), plain.load())
    cal = open_store(processed / "calibration.zarr")
    assert list(cal["term"].values) == ["A", "B", "C", "D", "E"]
    assert cal["coef"].dims == ("term", "y", "x") and cal.sizes["y"] == camp.camera.height
    assert cal.attrs["scale_k"] > 0 and cal.attrs["reference_reflectance"] == pytest.approx(0.6)
    for name, item in camp.items.items():
        expected = {
            "ingest": {"xyz", "intensity", "valid"},
            "aoi": {"aoi", "distance"},
            "reflectance": {"reflectance", "reflectance_noise"},
            "registered": {"reflectance", "aoi"},
            "features": {"R0", "n", "variability", "R0_uncertainty", "n_uncertainty"},
        }
        # a specimen is registered and fitted on its roi and the margin the 7 x 7 smoothing reads
        window = camp.crop if item.roi is None else item.roi.grown(3).clip(camp.crop)
        for stage, variables in expected.items():
            ds = open_store(processed / stage / f"{name}.zarr")
            assert variables <= set(ds.data_vars), (stage, name)
            assert ds.attrs["surffin_version"] == surffin.__version__
            grid = window if stage in ("registered", "features") else camp.crop
            assert (ds["y"].values[[0, -1]].tolist(), ds["x"].values[[0, -1]].tolist()) == (
                [grid.y[0], grid.y[1] - 1],
                [grid.x[0], grid.x[1] - 1],
            ), (stage, name)
            for var in variables:
                assert "long_name" in ds[var].attrs, (stage, var)
        assert list(open_store(processed / "aoi" / f"{name}.zarr")["view"].values) == list(item.view_stems)
        assert open_store(processed / "aoi" / f"{name}.zarr")["aoi"].attrs["units"] == "rad"
        assert (done / "logs" / "features" / f"{name}.log").is_file()
        features = open_store(processed / "features" / f"{name}.zarr")
        for var in ("R0_uncertainty", "n_uncertainty"):
            assert features[var].attrs["units"] == "1"
            uncertainty = features[var].values
            assert (uncertainty[np.isfinite(uncertainty)] >= 0).all()
            assert np.isfinite(uncertainty).mean() > 0.5
        assert "uncertainty_propagation" in features.attrs
        assert features.attrs["variability_noise_corrected"] == 1
        # computed from the camera's float32 data, stored as float32
        assert {features[var].dtype for var in ("R0", "n", "variability", "R0_uncertainty")} == {np.dtype("f4")}
    training = open_store(processed / "training.zarr")
    assert list(training["feature"].values) == ["R0", "n", "variability"]
    assert set(training["class"].values) == {"S1", "S2", "S3", "S4"}
    assert training.attrs["variability_noise_corrected"] == 1
    labels = open_store(processed / "labels" / "T1.zarr")
    for var in ("label", "label_filtered"):
        assert labels[var].dtype == np.int16
        assert labels[var].attrs["flag_values"] == [0, 1, 2, 3]
        assert labels[var].attrs["flag_meanings"] == "S1 S2 S3 S4"
        assert (labels[var].attrs["valid_min"], labels[var].attrs["valid_max"]) == (-1, 3)  # -1: unclassified
        # every unclassified pixel is counted under one reason, before and after the filter
        assert sum(labels[var].attrs["unclassified"].values()) == int((labels[var] == -1).sum())
    assert labels.attrs["surffin_parameters"]["min_posterior"] == 0.5
    assert labels["posterior"].dtype == np.float32 and labels["unclassified_reason"].dtype == np.int8
    assert "noise_variance" in cal and np.isfinite(cal["noise_variance"]).sum() > 5
    summary = json.loads((processed / "summary.json").read_text())
    assert set(summary["items"]) == set(camp.items)
    assert summary["items"]["S1"]["region"] == "roi" and summary["items"]["T1"]["region"] == "image"
    assert (
        summary["items"]["S1"]["n"]["n_pixels"] <= camp.specimens["S1"].roi.shape[0] * camp.specimens["S1"].roi.shape[1]
    )
    accuracy = summary["scenes"]["T1"]["accuracy"]
    # measured 0.809 / 0.854 (tiny preset, seed 0: specimens 16 px wide in the scene, a sixth of it
    # unclassified as unlike the specimens); tests/test_accuracy.py holds the end-to-end bounds
    assert accuracy["label"]["accuracy"] > 0.75 and accuracy["label_filtered"]["accuracy"] > 0.8
    relation = json.loads((processed / "roughness" / "relation.json").read_text())
    assert set(relation["specimens"]) == {"S1", "S2", "S3", "S4"}
    assert relation["slope"] < 0  # the tiny preset's plaster: n falls with roughness
    comparison = (processed / "paper-comparison.md").read_text()
    assert "| classification | T1: accuracy of label " in comparison and "| calibration | mean R²" in comparison
    diagnostics = json.loads((processed / "diagnostics" / "calibration.json").read_text())
    assert diagnostics["repeatability"]["available"]  # the tiny preset renders a repeat calibration set
    assert 0 < diagnostics["calibrations"]["first"]["fit"]["mean_r2"] <= 1
    rough = open_store(processed / "roughness" / "T1.zarr")
    assert rough["roughness"].attrs["units"] == "mm" and "indicative" in rough.attrs["comment"]
    assert rough.attrs["surffin_stage"] == "roughness"


@pytest.mark.slow  # a full snakemake run of the tiny campaign
def test_local_run_turns_off_the_job_rate_limiter(done):
    # its timers multiply scheduling rounds with every finished job (Snakefile, onstart)
    logs = (done / ".snakemake" / "log").glob("*.snakemake.log")
    assert any("job rate limiter is off" in log.read_text() for log in logs)


@pytest.mark.slow  # a full snakemake run of the tiny campaign
def test_nothing_left_after_a_complete_run(done, planned_jobs):
    assert planned_jobs(done) == {}


@pytest.mark.slow  # a full snakemake run of the tiny campaign
def test_smoothing_change_reruns_the_specimens_registration_features_and_below_only(done, planned_jobs):
    # a specimen's registration covers its roi and the margin the smoothing reads; the scene's the whole crop
    jobs = planned_jobs(done, overrides={"features": {"smoothing": 5}})
    figures = {"item_figures": 5, "classification_figures": 1, "scene_figures": 1}
    assert jobs == {
        "registration": 4,
        "features": 5,
        "training": 1,
        "labels": 1,
        "summary": 1,
        "all": 1,
        **figures,
        **ROUGHNESS,
        "calibration_diagnostics": 1,
        "paper_comparison": 1,
        "export": 1,
    }


@pytest.mark.slow  # a full snakemake run of the tiny campaign
def test_aoi_window_change_reruns_from_aoi_down(done, planned_jobs):
    jobs = planned_jobs(done, overrides={"aoi": {"window": 11, "jump": 0.16}})
    downstream = {"aoi", "reflectance", "registration", "features", "training", "labels", "summary", "all"}
    assert set(jobs) == downstream | {
        "item_figures",
        "classification_figures",
        "scene_figures",
        *ROUGHNESS,
        "calibration_diagnostics",
        "paper_comparison",
        "export",
    }
    assert jobs["aoi"] == 5


BUMP_LABELS = (
    "import dataclasses\n"
    "from surffin.pipeline.table import STAGES\n"
    "STAGES['labels'] = dataclasses.replace(STAGES['labels'], version=STAGES['labels'].version + 1)"
)


@pytest.mark.slow  # a full snakemake run of the tiny campaign
def test_code_version_bump_reruns_that_stage(done, planned_jobs):
    jobs = planned_jobs(done, prelude=BUMP_LABELS)
    assert jobs == {
        "labels": 1,
        "summary": 1,
        "classification_figures": 1,
        "scene_figures": 1,
        "paper_comparison": 1,
        "export": 1,
        "all": 1,
    }


@contextlib.contextmanager
def view_replaced(raw, item):
    """A view of ``item`` in campaign ``raw`` replaced by one 1 % brighter, put back as it was after."""
    view = surffin.read_campaign(raw).items[item].views[1]
    original, stat = view.read_bytes(), view.stat()
    data = dict(np.load(view))
    np.savez(view, **{**data, "intensity": data["intensity"] * 1.01})
    try:
        yield
    finally:
        view.write_bytes(original)
        os.utime(view, ns=(stat.st_atime_ns, stat.st_mtime_ns))


@contextlib.contextmanager
def specimen_added(raw):
    """Specimen S5 (S1's views and settings) added to campaign ``raw``, and removed after."""
    spec = (raw / "campaign.yaml").read_text()
    shutil.copytree(raw / "specimens" / "S1", raw / "specimens" / "S5")
    added = yaml.safe_load(spec)
    added["specimens"]["S5"] = {**added["specimens"]["S1"], "views": "specimens/S5"}
    (raw / "campaign.yaml").write_text(yaml.safe_dump(added))
    try:
        yield
    finally:
        (raw / "campaign.yaml").write_text(spec)
        shutil.rmtree(raw / "specimens" / "S5")


@pytest.mark.slow  # a full snakemake run of the tiny campaign
def test_replacing_one_view_reruns_its_chain_only(fresh, planned_jobs):
    with view_replaced(fresh / "raw", "S2"):
        jobs = planned_jobs(fresh)
    assert jobs == {**{stage: 1 for stage in ITEM_CHAIN}, **DOWNSTREAM}


@pytest.mark.slow  # a full snakemake run of the tiny campaign
def test_adding_a_specimen_runs_its_chain(fresh, planned_jobs):
    with specimen_added(fresh / "raw"):
        jobs = planned_jobs(fresh)
    # the calibration diagnostics reprocess one specimen per class, and S1 stays class S1's
    expected = {**{stage: 1 for stage in ITEM_CHAIN}, **DOWNSTREAM}
    del expected["calibration_diagnostics"]
    assert jobs == expected


def test_unknown_config_key_fails_before_any_job(tiny_campaign, tmp_path, snakemake):
    shutil.copytree(tiny_campaign, tmp_path / "raw")
    run = snakemake(tmp_path, config=["smoothing_sizes=3"])
    assert run.returncode != 0
    assert "smoothing_sizes" in run.stderr + run.stdout
    assert not (tmp_path / "processed").exists()


@pytest.mark.parametrize(
    ("setting", "message"),
    [("item_figures=few", "'few' is not one of ['all', 'scenes', 'none']"), ("scheduler=7", "7 is not of type")],
)
def test_bad_config_values_fail_before_any_job_naming_the_key(tiny_campaign, tmp_path, snakemake, setting, message):
    shutil.copytree(tiny_campaign, tmp_path / "raw")
    run = snakemake(tmp_path, config=[setting])
    assert run.returncode != 0
    assert message in run.stderr + run.stdout and setting.split("=")[0] in run.stderr + run.stdout
    assert not (tmp_path / "processed").exists()


def test_bad_campaign_fails_before_any_job_naming_the_file(tiny_campaign, tmp_path, snakemake):
    shutil.copytree(tiny_campaign, tmp_path / "raw")
    yaml_path = tmp_path / "raw" / "campaign.yaml"
    yaml_path.write_text(yaml_path.read_text().replace("specimens:", "specimen:"))
    run = snakemake(tmp_path)
    out = run.stderr + run.stdout
    assert run.returncode != 0
    assert str(yaml_path) in out and "specimen" in out
    assert not (tmp_path / "processed").exists()


def test_a_view_with_broken_pixels_fails_before_any_job_naming_the_file(tiny_campaign, tmp_path, snakemake):
    shutil.copytree(tiny_campaign, tmp_path / "raw")
    view = surffin.read_campaign(tmp_path / "raw").items["T1"].views[2]
    arrays = dict(np.load(view))
    arrays["intensity"][np.isfinite(arrays["xyz"]).all(axis=-1)] = np.nan
    np.savez(view, **arrays)
    run = snakemake(tmp_path)
    assert run.returncode != 0
    assert f"{view}: intensity is NaN, infinite or negative on " in run.stderr + run.stdout
    assert not (tmp_path / "processed").exists()


@pytest.mark.slow  # a full snakemake run of the tiny campaign
def test_lint_is_clean(done, snakemake):
    run = snakemake(done, "--lint")
    assert run.returncode == 0, run.stdout + run.stderr


# --- a fresh clone: nothing happens when the workflow is read ------------------------------------


@pytest.fixture
def clone(tmp_path):
    """The workflow's files as a fresh clone has them (no campaign in data/raw), the default campaign tiny."""
    for part in ("Snakefile", "workflow", "config", "profiles", "data/raw/README.md"):
        target = tmp_path / part
        target.parent.mkdir(parents=True, exist_ok=True)
        (shutil.copytree if (REPO / part).is_dir() else shutil.copy)(REPO / part, target)
    (tmp_path / "tiny.yaml").write_text(yaml.safe_dump({"default_campaign": {"preset": "tiny", "seed": 0}}))
    return tmp_path


def in_clone(clone, *args):
    cmd = [sys.executable, "-m", "snakemake", "--cores", "2", *args, "--configfiles", str(clone / "tiny.yaml")]
    return subprocess.run(cmd, capture_output=True, text=True, cwd=clone, timeout=600)


def written(folder):
    return sorted(str(path.relative_to(folder)) for path in folder.rglob("*") if ".snakemake" not in path.parts)


@pytest.mark.parametrize("args", [("--dry-run",), ("--lint",)], ids=["dry run", "lint"])
def test_reading_the_workflow_writes_nothing(clone, args):
    before = written(clone)
    run = in_clone(clone, *args)
    assert run.returncode == 0, run.stdout + run.stderr
    assert written(clone) == before
    if args == ("--dry-run",):
        assert re.search(r"^default_campaign\s+1$", run.stdout, re.M), run.stdout


@pytest.mark.slow  # a full snakemake run of the tiny campaign
def test_a_fresh_clone_renders_the_default_campaign_and_runs_it(clone):
    run = in_clone(clone)
    assert run.returncode == 0, run.stderr[-4000:]
    camp = surffin.read_campaign(clone / "data" / "raw")
    summary = json.loads((clone / "data" / "processed" / "summary.json").read_text())
    assert set(summary["items"]) == set(camp.items) and set(summary["scenes"]) == set(camp.scenes)
    assert (clone / "data" / "processed" / "paper-comparison.md").is_file()
    assert in_clone(clone, "--dry-run").stdout.count("Nothing to be done") == 1
