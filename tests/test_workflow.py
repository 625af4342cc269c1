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

REPO = Path(__file__).resolve().parents[1]
ITEM_CHAIN = {"ingest", "aoi", "reflectance", "registration", "features", "item_figures"}
ROUGHNESS = {"roughness_relation": 1, "roughness_map": 1, "roughness_figures": 1}
DOWNSTREAM = {
    "training": 1, "labels": 1, "summary": 1, "classification_figures": 1, "scene_figures": 1, "all": 1,
    "calibration_diagnostics": 1, "paper_comparison": 1, **ROUGHNESS,
}


def snakemake(workdir, *args, config=(), overrides=None, snakefile=REPO / "Snakefile"):
    """Run snakemake on ``workdir/raw``; ``overrides`` is a nested config mapping given as a file."""
    configfiles = [str(REPO / "tests" / "data" / "tiny-config.yaml")]
    if overrides is not None:
        extra = workdir / "overrides.yaml"
        extra.write_text(yaml.safe_dump(overrides))
        configfiles.append(str(extra))
    cmd = [sys.executable, "-m", "snakemake", "--snakefile", str(snakefile), "--directory", str(workdir)]
    cmd += ["--cores", "2", *args, "--configfiles", *configfiles, "--config"]
    cmd += [f"campaign={workdir / 'raw'}", f"processed={workdir / 'processed'}", f"logs={workdir / 'logs'}", *config]
    return subprocess.run(cmd, capture_output=True, text=True, cwd=workdir, timeout=600)


def planned_jobs(workdir, *targets, **kwargs):
    """Rule name -> job count of a dry run (of the default target, or of ``targets``)."""
    run = snakemake(workdir, "--dry-run", *targets, **kwargs)
    out = run.stdout + run.stderr
    assert run.returncode == 0, out
    if "Nothing to be done" in out:
        return {}
    table = out.split("Job stats:", 1)[1]
    return {rule: int(count) for rule, count in re.findall(r"^(\w+)\s+(\d+)$", table, re.M) if rule != "total"}


def complete_run(workdir):
    surffin.simulate_campaign(workdir / "raw", preset="tiny", seed=0)
    run = snakemake(workdir)
    assert run.returncode == 0, run.stderr[-4000:]
    return workdir


@pytest.fixture(scope="module")
def done(tmp_path_factory):
    """A complete run on the tiny preset, shared by the read-only tests."""
    return complete_run(tmp_path_factory.mktemp("wf"))


@pytest.fixture
def fresh(tmp_path):
    """A complete run of one's own, for tests that change the campaign or config."""
    return complete_run(tmp_path)


@pytest.mark.slow  # a full snakemake run of the tiny campaign
def test_every_store_follows_the_contract(done):
    camp = surffin.read_campaign(done / "raw")
    processed = done / "processed"
    cal = xr.open_zarr(processed / "calibration.zarr")
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
        for stage, variables in expected.items():
            ds = xr.open_zarr(processed / stage / f"{name}.zarr")
            assert variables <= set(ds.data_vars), (stage, name)
            assert ds.attrs["surffin_version"] == surffin.__version__
            assert ds["y"].values[0] == camp.crop.y[0] and ds["x"].values[-1] == camp.crop.x[1] - 1
            for var in variables:
                assert "long_name" in ds[var].attrs, (stage, var)
        assert list(xr.open_zarr(processed / "aoi" / f"{name}.zarr")["view"].values) == list(item.view_stems)
        assert xr.open_zarr(processed / "aoi" / f"{name}.zarr")["aoi"].attrs["units"] == "rad"
        assert (done / "logs" / "features" / f"{name}.log").is_file()
        features = xr.open_zarr(processed / "features" / f"{name}.zarr")
        for var in ("R0_uncertainty", "n_uncertainty"):
            assert features[var].attrs["units"] == "1"
            uncertainty = features[var].values
            assert (uncertainty[np.isfinite(uncertainty)] >= 0).all()
            assert np.isfinite(uncertainty).mean() > 0.5
        assert "uncertainty_propagation" in features.attrs
        assert features.attrs["variability_noise_corrected"] == 1
    training = xr.open_zarr(processed / "training.zarr")
    assert list(training["feature"].values) == ["R0", "n", "variability"]
    assert set(training["class"].values) == {"S1", "S2", "S3", "S4"}
    assert training.attrs["variability_noise_corrected"] == 1
    labels = xr.open_zarr(processed / "labels" / "T1.zarr")
    for var in ("label", "label_filtered"):
        assert labels[var].dtype == np.int16
        assert labels[var].attrs["flag_values"] == [0, 1, 2, 3]
        assert labels[var].attrs["flag_meanings"] == "S1 S2 S3 S4"
        # every unclassified pixel is counted under one reason, before and after the filter
        assert sum(labels[var].attrs["unclassified"].values()) == int((labels[var] == -1).sum())
    assert labels.attrs["surffin_parameters"]["min_posterior"] == 0.5
    assert labels["posterior"].dtype == np.float32 and labels["unclassified_reason"].dtype == np.int8
    assert "noise_variance" in cal and np.isfinite(cal["noise_variance"]).sum() > 5
    summary = json.loads((processed / "summary.json").read_text())
    assert set(summary["items"]) == set(camp.items)
    assert summary["items"]["S1"]["region"] == "roi" and summary["items"]["T1"]["region"] == "image"
    assert summary["items"]["S1"]["n"]["n_pixels"] <= camp.specimens["S1"].roi.shape[0] * camp.specimens["S1"].roi.shape[1]
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
    rough = xr.open_zarr(processed / "roughness" / "T1.zarr")
    assert rough["roughness"].attrs["units"] == "mm" and "indicative" in rough.attrs["comment"]
    assert rough.attrs["surffin_stage"] == "roughness"


@pytest.mark.slow  # a full snakemake run of the tiny campaign
def test_nothing_left_after_a_complete_run(done):
    assert planned_jobs(done) == {}


@pytest.mark.slow  # a full snakemake run of the tiny campaign
def test_smoothing_change_reruns_features_and_below_only(done):
    jobs = planned_jobs(done, overrides={"features": {"smoothing": 5}})
    figures = {"item_figures": 5, "classification_figures": 1, "scene_figures": 1}
    assert jobs == {"features": 5, "training": 1, "labels": 1, "summary": 1, "all": 1, **figures, **ROUGHNESS,
                    "calibration_diagnostics": 1, "paper_comparison": 1}


@pytest.mark.slow  # a full snakemake run of the tiny campaign
def test_aoi_window_change_reruns_from_aoi_down(done):
    jobs = planned_jobs(done, overrides={"aoi": {"window": 11, "jump": 0.16}})
    downstream = {"aoi", "reflectance", "registration", "features", "training", "labels", "summary", "all"}
    assert set(jobs) == downstream | {"item_figures", "classification_figures", "scene_figures", *ROUGHNESS,
                                      "calibration_diagnostics", "paper_comparison"}
    assert jobs["aoi"] == 5


@pytest.mark.slow  # a full snakemake run of the tiny campaign
def test_code_version_bump_reruns_that_stage(done, tmp_path):
    copy = tmp_path / "repo"
    copy.mkdir()
    for part in ("Snakefile", "workflow", "config"):
        (shutil.copytree if (REPO / part).is_dir() else shutil.copy)(REPO / part, copy / part)
    common = copy / "workflow" / "rules" / "common.smk"
    # one more than whatever the labels stage's version is now
    common.write_text(re.sub(r'"labels": (\d+),', lambda m: f'"labels": {int(m[1]) + 1},', common.read_text(), count=1))
    jobs = planned_jobs(done, snakefile=copy / "Snakefile")
    assert jobs == {"labels": 1, "summary": 1, "classification_figures": 1, "scene_figures": 1, "paper_comparison": 1, "all": 1}


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
def test_replacing_one_view_reruns_its_chain_only(fresh):
    with view_replaced(fresh / "raw", "S2"):
        jobs = planned_jobs(fresh)
    assert jobs == {**{stage: 1 for stage in ITEM_CHAIN}, **DOWNSTREAM}


@pytest.mark.slow  # a full snakemake run of the tiny campaign
def test_adding_a_specimen_runs_its_chain(fresh):
    with specimen_added(fresh / "raw"):
        jobs = planned_jobs(fresh)
    # the calibration diagnostics reprocess one specimen per class, and S1 stays class S1's
    expected = {**{stage: 1 for stage in ITEM_CHAIN}, **DOWNSTREAM}
    del expected["calibration_diagnostics"]
    assert jobs == expected


def test_unknown_config_key_fails_before_any_job(tmp_path):
    surffin.simulate_campaign(tmp_path / "raw", preset="tiny", seed=0)
    run = snakemake(tmp_path, config=["smoothing_sizes=3"])
    assert run.returncode != 0
    assert "smoothing_sizes" in run.stderr + run.stdout
    assert not (tmp_path / "processed").exists()


@pytest.mark.parametrize(
    ("setting", "message"),
    [("jobs=items", "'items' is not one of ['stage', 'item']"), ("item_batches=-1", "-1 is less than the minimum of 0")],
)
def test_bad_jobs_values_fail_before_any_job_naming_the_key(tmp_path, setting, message):
    surffin.simulate_campaign(tmp_path / "raw", preset="tiny", seed=0)
    run = snakemake(tmp_path, config=[setting])
    assert run.returncode != 0
    assert message in run.stderr + run.stdout and setting.split("=")[0] in run.stderr + run.stdout
    assert not (tmp_path / "processed").exists()


def test_bad_campaign_fails_before_any_job_naming_the_file(tmp_path):
    surffin.simulate_campaign(tmp_path / "raw", preset="tiny", seed=0)
    yaml_path = tmp_path / "raw" / "campaign.yaml"
    yaml_path.write_text(yaml_path.read_text().replace("specimens:", "specimen:"))
    run = snakemake(tmp_path)
    out = run.stderr + run.stdout
    assert run.returncode != 0
    assert str(yaml_path) in out and "specimen" in out
    assert not (tmp_path / "processed").exists()


def test_workflow_files_are_formatted():
    snakefmt = Path(sys.executable).parent / "snakefmt"
    run = subprocess.run([snakefmt, "--check", "Snakefile", "workflow/rules"], capture_output=True, text=True, cwd=REPO)
    assert run.returncode == 0, run.stdout + run.stderr


@pytest.mark.parametrize("config", [(), ("jobs=item", "item_batches=2")], ids=["stage jobs", "batch jobs"])
@pytest.mark.slow  # a full snakemake run of the tiny campaign
def test_lint_is_clean(done, config):
    run = snakemake(done, "--lint", config=config)
    assert run.returncode == 0, run.stdout + run.stderr


# --- config jobs: item ---------------------------------------------------------------------


def normalised(ds, *processed):
    """``ds`` with any of the ``processed`` folders written as ``PROCESSED`` in its recorded input stores."""
    folders = "|".join(re.escape(str(folder)) for folder in processed)
    inputs = {
        name: re.sub(f"^({folders})/", "PROCESSED/", value) if isinstance(value, str) else value
        for name, value in ds.attrs["surffin_inputs"].items()
    }
    return ds.assign_attrs(surffin_inputs=inputs)


def chain_jobs(done, folder, config):
    """Run ``done``'s campaign to its features stores in ``folder`` with item jobs (``config``) and
    ``done``'s calibration; returns the folder, the targets and the config."""
    shutil.copytree(done / "raw", folder / "raw")
    items = surffin.read_campaign(done / "raw").items
    targets = [str(folder / "processed" / "features" / f"{name}.zarr") for name in items]
    config = [*config, f"calibration_store={done / 'processed' / 'calibration.zarr'}"]
    run = snakemake(folder, *targets, config=config)
    assert run.returncode == 0, run.stderr[-4000:]
    return folder, targets, config


def assert_stores_of_the_stage_jobs(workdir, done, logs):
    """``workdir``'s chain stores are ``done``'s, and the ``logs`` name each stage of each item."""
    text = "".join(log.read_text() for log in logs)
    for name in surffin.read_campaign(done / "raw").items:
        for stage in ("ingest", "aoi", "reflectance", "registered", "features"):
            # the item jobs read the calibration of `done`, by its path there
            ours, theirs = (
                normalised(xr.open_zarr(folder / stage / f"{name}.zarr"), workdir / "processed", done / "processed")
                for folder in (workdir / "processed", done / "processed")
            )
            xr.testing.assert_identical(ours.load(), theirs.load())
        assert f"item {name} done in" in text
    assert all(f"{stage} done in" in text for stage in ("ingest", "aoi", "reflectance", "registration", "features"))


@pytest.fixture(scope="module")
def item_jobs(done, tmp_path_factory):
    return chain_jobs(done, tmp_path_factory.mktemp("items"), ["jobs=item"])


@pytest.fixture(scope="module")
def batch_jobs(done, tmp_path_factory):
    # two batches of the specimens by the CRC-32 of their names: S1, S2, S3 | S4; the scene T1 alone
    return chain_jobs(done, tmp_path_factory.mktemp("batches"), ["jobs=item", "item_batches=2"])


@pytest.mark.slow  # a full snakemake run of the tiny campaign
def test_item_jobs_write_the_stores_of_the_stage_jobs(done, item_jobs):
    workdir, _, _ = item_jobs
    assert_stores_of_the_stage_jobs(workdir, done, sorted((workdir / "logs" / "item").glob("*.log")))
    assert len(list((workdir / "logs" / "item").glob("*.log"))) == 5


@pytest.mark.slow  # a full snakemake run of the tiny campaign
def test_batch_jobs_write_the_stores_of_the_stage_jobs(done, batch_jobs):
    workdir, _, _ = batch_jobs
    batches = sorted((workdir / "logs" / "item_batch").glob("*.log"))
    assert [log.name for log in batches] == ["0.log", "1.log"]
    assert "batch of 3 items done in" in batches[0].read_text()
    assert [log.name for log in (workdir / "logs" / "item").glob("*.log")] == ["T1.log"]
    assert_stores_of_the_stage_jobs(workdir, done, [*batches, workdir / "logs" / "item" / "T1.log"])


@pytest.mark.slow  # a full snakemake run of the tiny campaign
def test_item_jobs_rerun_whole_chains(item_jobs):
    workdir, targets, config = item_jobs
    assert planned_jobs(workdir, *targets, config=config) == {}
    assert planned_jobs(workdir, *targets, config=config, overrides={"features": {"smoothing": 5}}) == {"item": 5}
    # a view replaced: that item's chain only
    with view_replaced(workdir / "raw", "S2"):
        assert planned_jobs(workdir, *targets, config=config) == {"item": 1}


@pytest.mark.slow  # a full snakemake run of the tiny campaign
def test_batch_jobs_rerun_the_batch_of_a_changed_specimen(batch_jobs):
    workdir, targets, config = batch_jobs
    assert planned_jobs(workdir, *targets, config=config) == {}
    for item, batch in (("S2", {"item_batch_0": 1}), ("S4", {"item_batch_1": 1}), ("T1", {"item": 1})):
        with view_replaced(workdir / "raw", item):
            assert planned_jobs(workdir, *targets, config=config) == batch
    # a specimen added, S5: its batch runs (its other specimen with it), no other job
    with specimen_added(workdir / "raw"):
        features = str(workdir / "processed" / "features" / "S5.zarr")
        assert planned_jobs(workdir, *targets, features, config=config) == {"item_batch_1": 1}
    # three batches, S1, S4 | none | S2, S3: both hold other specimens than before, so both run
    regrouped = planned_jobs(workdir, *targets, config=[*config, "item_batches=3"])
    assert regrouped == {"item_batch_0": 1, "item_batch_2": 1}


@pytest.mark.slow  # a full snakemake run of the tiny campaign
def test_switching_to_item_jobs_reruns_every_chain_once(done):
    jobs = planned_jobs(done, config=["jobs=item"])
    assert jobs["item"] == 5 and "features" not in jobs and "calibration" not in jobs


@pytest.mark.slow  # a full snakemake run of the tiny campaign
def test_item_figures_of_scenes_only_or_none(item_jobs):
    workdir, _, config = item_jobs
    assert planned_jobs(workdir, config=[*config, "item_figures=scenes"])["item_figures"] == 1
    assert "item_figures" not in planned_jobs(workdir, config=[*config, "item_figures=none"])
