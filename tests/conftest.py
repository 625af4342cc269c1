"""Shared fixtures: a tiny synthetic sensor with known invalid pixels; the tiny campaign and its workflow run."""

import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

HEIGHT, WIDTH = 6, 8
"""Sensor rows and columns of the synthetic views."""

INVALID_PIXELS = ((0, 0), (1, 2), (2, 5), (5, 7))
"""(row, column) of the pixels made invalid: a NaN, all zeros, z < 0, z == 0."""


@pytest.fixture
def synthetic_view() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """xyz (HEIGHT, WIDTH, 3) metres, intensity (HEIGHT, WIDTH) and the expected valid mask.

    A tilted plane 0.5-0.8 m in front of the camera with a millimetre texture,
    intensities 10..~1000; the pixels of :data:`INVALID_PIXELS` are invalid.
    """
    rows, cols = np.mgrid[0:HEIGHT, 0:WIDTH]
    z = 0.5 + 0.01 * rows + 0.03 * cols + 0.001 * np.sin(rows * cols)
    xyz = np.stack([(cols - WIDTH / 2) * 0.01 * z, (rows - HEIGHT / 2) * 0.01 * z, z], axis=-1)
    intensity = 10.0 + 30.0 * rows * cols + 0.37 * cols
    valid = np.ones((HEIGHT, WIDTH), dtype=bool)
    for pixel, bad_xyz in zip(INVALID_PIXELS, ([np.nan, 0.1, 0.5], [0, 0, 0], [0.1, 0.1, -0.5], [0.2, 0.1, 0.0])):
        xyz[pixel] = bad_xyz
        valid[pixel] = False
    return xyz, intensity, valid


@pytest.fixture
def sensor() -> dict[str, int]:
    """``{"width", "height"}`` of the synthetic views, as keyword arguments of the readers."""
    return {"width": WIDTH, "height": HEIGHT}


# --- the tiny campaign and one complete workflow run, shared by every module -----------------------

REPO = Path(__file__).resolve().parents[1]


def run_snakemake(workdir, *args, config=(), overrides=None, snakefile=REPO / "Snakefile", prelude=None):
    """Run snakemake on ``workdir/raw``; ``overrides`` is a nested config mapping given as a file.

    ``prelude`` is Python run in snakemake's process before it starts (e.g. to change the
    stage table the workflow reads).
    """
    configfiles = [str(REPO / "tests" / "data" / "tiny-config.yaml")]
    if overrides is not None:
        extra = workdir / "overrides.yaml"
        extra.write_text(yaml.safe_dump(overrides))
        configfiles.append(str(extra))
    start = [sys.executable, "-m", "snakemake"]
    if prelude is not None:
        start = [sys.executable, "-c", f"{prelude}\nimport sys\nfrom snakemake.cli import main\nsys.exit(main())"]
    cmd = [*start, "--snakefile", str(snakefile), "--directory", str(workdir), "--cores", "2", *args]
    cmd += ["--configfiles", *configfiles, "--config"]
    cmd += [f"campaign={workdir / 'raw'}", f"processed={workdir / 'processed'}", f"logs={workdir / 'logs'}", *config]
    return subprocess.run(cmd, capture_output=True, text=True, cwd=workdir, timeout=600)


def dry_run_jobs(workdir, *targets, **kwargs):
    """Rule name -> job count of a dry run (of the default target, or of ``targets``)."""
    run = run_snakemake(workdir, "--dry-run", *targets, **kwargs)
    out = run.stdout + run.stderr
    assert run.returncode == 0, out
    if "Nothing to be done" in out:
        return {}
    table = out.split("Job stats:", 1)[1]
    return {rule: int(count) for rule, count in re.findall(r"^(\w+)\s+(\d+)$", table, re.M) if rule != "total"}


def complete_run(workdir, campaign):
    """A copy of ``campaign`` in ``workdir/raw`` processed by the workflow."""
    shutil.copytree(campaign, workdir / "raw")
    shutil.copytree(f"{campaign}-truth", workdir / "raw-truth")
    run = run_snakemake(workdir)
    assert run.returncode == 0, run.stderr[-4000:]
    return workdir


@pytest.fixture(scope="session")
def tiny_campaign(tmp_path_factory) -> Path:
    """The ``tiny`` preset (seed 0), rendered once; read it, never change it (copy it to change it)."""
    import surffin

    path = tmp_path_factory.mktemp("tiny") / "raw"
    surffin.simulate_campaign(path, preset="tiny", seed=0)
    return path


@pytest.fixture(scope="session")
def tiny_run(tiny_campaign, tmp_path_factory) -> Path:
    """A complete workflow run of the tiny campaign (``raw``, ``processed``, ``logs``); read only."""
    return complete_run(tmp_path_factory.mktemp("run"), tiny_campaign)


@pytest.fixture
def snakemake():
    """:func:`run_snakemake`: the workflow on a folder's campaign."""
    return run_snakemake


@pytest.fixture
def planned_jobs():
    """:func:`dry_run_jobs`: rule name -> job count of a dry run."""
    return dry_run_jobs


@pytest.fixture
def fresh_run(tiny_campaign, tmp_path):
    """A complete run of one's own, for tests that change the campaign or config."""
    return complete_run(tmp_path, tiny_campaign)
