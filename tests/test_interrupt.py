"""A killed workflow leaves no store that looks finished, and the same command completes it.

CAMPAIGN.md: "Every store is complete or absent ... After a crash or kill, running the same
command again (after `snakemake --unlock` if snakemake's own lock remains) completes the run
with results identical to an uninterrupted one." Both runs use `--cores 2` on the tiny preset;
the uninterrupted reference runs alongside the killed one to keep the test short.
"""

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import xarray as xr

from surffin.pipeline.workflow import CHECKED_VIEWS

REPO = Path(__file__).resolve().parents[1]
TIMEOUT = 300
#: The only names a killed write may leave beside a store: ``.<store>.partial-<token>``.
PARTIAL = re.compile(r"\.[^/]+\.zarr\.partial-[0-9a-f]+")


def command(workdir: Path, campaign: Path, *args: str) -> list[str]:
    """The snakemake command line of a run in ``workdir`` (the same for the first run and the rerun)."""
    config = [f"campaign={campaign}", f"processed={workdir / 'processed'}", f"logs={workdir / 'logs'}"]
    return [
        *(sys.executable, "-m", "snakemake", "--snakefile", str(REPO / "Snakefile"), "--directory", str(workdir)),
        *("--cores", "2", *args, "--configfiles", str(REPO / "tests" / "data" / "tiny-config.yaml")),
        *("--config", *config),
    ]


def start(workdir: Path, campaign: Path) -> subprocess.Popen:
    """Start a run in its own process group, output to ``workdir/snakemake.out``."""
    workdir.mkdir()
    with open(workdir / "snakemake.out", "w") as out:
        return subprocess.Popen(
            command(workdir, campaign), stdout=out, stderr=subprocess.STDOUT, cwd=workdir, start_new_session=True
        )


def entries(processed: Path) -> list[Path]:
    """What the run wrote into ``processed`` and its per-item folders (not inside stores)."""
    found = []
    for entry in processed.iterdir():
        per_item = entry.is_dir() and not entry.name.endswith(".zarr") and not entry.name.startswith(".")
        found += sorted(entry.iterdir()) if per_item else [entry]
    return sorted(found)


def finished_stores(processed: Path) -> list[Path]:
    """Stores at their final paths (hidden temporary folders excluded)."""
    if not processed.is_dir():
        return []
    return [p for p in entries(processed) if p.suffix == ".zarr" and not p.name.startswith(".")]


def kill_after_first_store(run: subprocess.Popen, processed: Path) -> None:
    """SIGKILL the run's process group as soon as one store is finished."""
    deadline = time.monotonic() + TIMEOUT
    while not finished_stores(processed):
        assert run.poll() is None, "the run ended before any store was finished"
        assert time.monotonic() < deadline, "no store finished in time"
        time.sleep(0.02)
    os.killpg(run.pid, signal.SIGKILL)
    run.wait()


def assert_only_stores_and_partials(processed: Path) -> None:
    """Besides finished stores (and summary.json, the checked views' record), only ``.<store>.partial-<token>``."""
    for entry in entries(processed):
        finished = entry.suffix == ".zarr" and not entry.name.startswith(".")
        finished = finished or entry.name in ("summary.json", CHECKED_VIEWS)
        assert finished or PARTIAL.fullmatch(entry.name), entry


def assert_identical_stores(stores: list[Path], processed: Path, reference: Path) -> None:
    """Each store holds the reference store's variables with identical data."""
    for store in stores:
        expected, actual = xr.open_zarr(reference / store), xr.open_zarr(processed / store)
        assert set(actual.data_vars) == set(expected.data_vars), store
        for name in expected.data_vars:
            xr.testing.assert_identical(actual[name].load(), expected[name].load())


@pytest.mark.slow  # full snakemake runs, one killed
def test_killed_run_leaves_complete_stores_and_completes_identically(tiny_campaign, tmp_path):
    campaign = tiny_campaign
    reference = start(tmp_path / "reference", campaign)
    killed = tmp_path / "killed"
    kill_after_first_store(start(killed, campaign), killed / "processed")

    assert_only_stores_and_partials(killed / "processed")
    at_kill = shutil.copytree(killed / "processed", tmp_path / "at-kill")
    unlock = subprocess.run(command(killed, campaign, "--unlock"), capture_output=True, text=True, cwd=killed)
    assert unlock.returncode == 0, unlock.stderr[-3000:]
    rerun = subprocess.run(command(killed, campaign), capture_output=True, text=True, cwd=killed, timeout=TIMEOUT)
    assert rerun.returncode == 0, rerun.stderr[-3000:]
    assert not [p for p in entries(killed / "processed") if PARTIAL.fullmatch(p.name)], "leftovers not cleaned up"

    assert reference.wait(timeout=TIMEOUT) == 0, (tmp_path / "reference" / "snakemake.out").read_text()[-3000:]
    expected = tmp_path / "reference" / "processed"
    # What looked finished at the kill was complete: the reference's variables, identical data.
    assert_identical_stores([store.relative_to(at_kill) for store in finished_stores(at_kill)], at_kill, expected)
    stores = [store.relative_to(expected) for store in finished_stores(expected)]
    assert [store.relative_to(killed / "processed") for store in finished_stores(killed / "processed")] == stores
    assert_identical_stores(stores, killed / "processed", expected)
    summary = json.loads((killed / "processed" / "summary.json").read_text())
    assert summary == json.loads((expected / "summary.json").read_text())
