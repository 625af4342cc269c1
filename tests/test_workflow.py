"""Snakemake on a tiny synthetic campaign, in a temporary working directory."""

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

import surffin

REPO = Path(__file__).resolve().parents[1]
SNAKEMAKE = [sys.executable, "-m", "snakemake", "--snakefile", str(REPO / "Snakefile")]


def snakemake(workdir, *args, config=()):
    cmd = [*SNAKEMAKE, "--directory", str(workdir), "--cores", "2", *args]
    settings = [f"campaign={workdir / 'raw'}", f"processed={workdir / 'processed'}", f"logs={workdir / 'logs'}", *config]
    cmd += ["--config", *settings]
    return subprocess.run(cmd, capture_output=True, text=True, cwd=workdir, timeout=300)


def planned_jobs(workdir, *args, config=()):
    """Rule name -> job count of a dry run."""
    run = snakemake(workdir, "--dry-run", *args, config=config)
    assert run.returncode == 0, run.stderr + run.stdout
    out = run.stdout + run.stderr
    if "Nothing to be done" in out:
        return {}
    table = out.split("Job stats:", 1)[1]
    return {rule: int(count) for rule, count in re.findall(r"^(\w+)\s+(\d+)$", table, re.M) if rule != "total"}


@pytest.fixture(scope="module")
def done(tmp_path_factory):
    """A complete run on the tiny preset."""
    workdir = tmp_path_factory.mktemp("wf")
    surffin.simulate_campaign(workdir / "raw", preset="tiny", seed=0)
    run = snakemake(workdir)
    assert run.returncode == 0, run.stderr[-3000:]
    return workdir


def test_complete_run_writes_ingest_stores(done):
    camp = surffin.read_campaign(done / "raw")
    for name, item in camp.items.items():
        ds = xr.open_zarr(done / "processed" / "ingest" / f"{name}.zarr")
        assert list(ds["view"].values) == list(item.view_stems)
        assert ds["y"].values[0] == camp.crop.y[0] and ds["x"].values[-1] == camp.crop.x[1] - 1
        assert ds.attrs["surffin_version"] == surffin.__version__
        assert ds["xyz"].attrs["units"] == "m"
        assert (done / "logs" / "ingest" / f"{name}.log").is_file()
    assert planned_jobs(done) == {}


def test_replacing_one_view_reruns_only_its_item(tmp_path):
    surffin.simulate_campaign(tmp_path / "raw", preset="tiny", seed=0)
    assert snakemake(tmp_path).returncode == 0
    view = surffin.read_campaign(tmp_path / "raw").specimens["S2"].views[1]
    data = dict(np.load(view))
    data["intensity"] = data["intensity"] * 1.01
    np.savez(view, **data)
    assert planned_jobs(tmp_path) == {"ingest": 1, "all": 1}


def test_unknown_config_key_fails_before_any_job(tmp_path):
    surffin.simulate_campaign(tmp_path / "raw", preset="tiny", seed=0)
    run = snakemake(tmp_path, config=["smoothing_sizes=3"])
    assert run.returncode != 0
    assert "smoothing_sizes" in run.stderr + run.stdout
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


def test_lint_is_clean(done):
    run = snakemake(done, "--lint")
    assert run.returncode == 0, run.stdout + run.stderr
