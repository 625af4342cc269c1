"""run_item: an item's chain in one call writes what the stage-by-stage calls write; dask schedulers."""

import math
import subprocess
import sys

import pytest
import xarray as xr

import surffin
from surffin.pipeline.jobs import dask_scheduler
from surffin.pipeline.run import run_calibration, run_ingest, run_item, run_items, run_stage

CHUNKS = {"y": 32, "x": 32}
STORES = ("ingest", "aoi", "reflectance", "registered", "features")
AOI = {"window": 9}
FEATURES = {"size": 5, "variability_size": 7, "min_views": 2, "min_spread": math.radians(10)}


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    root = tmp_path_factory.mktemp("pipeline")
    surffin.simulate_campaign(root / "raw", preset="tiny", seed=0)
    camp = surffin.read_campaign(root / "raw")
    return camp, run_calibration(camp.path, root / "calibration.zarr")


def stage_by_stage(camp, calibration, item, folder):
    """The chain as the per-stage rules run it, one call per stage."""
    store = {name: folder / name / f"{item}.zarr" for name in STORES}
    run_ingest(camp.path, item, store["ingest"], chunks=CHUNKS)
    run_stage("aoi", store["aoi"], stores={"ingest": store["ingest"]}, params=AOI, chunks=CHUNKS)
    inputs = {"ingest": store["ingest"], "aoi": store["aoi"]}
    run_stage("reflectance", store["reflectance"], stores={**inputs, "calibration": calibration}, chunks=CHUNKS)
    inputs["reflectance"] = store["reflectance"]
    run_stage("registration", store["registered"], stores=inputs, chunks=CHUNKS)
    del inputs["ingest"]
    run_stage("features", store["features"], stores={"registered": store["registered"], **inputs}, params=FEATURES,
              chunks=CHUNKS)
    return store


def test_run_item_writes_the_stores_of_the_stages(campaign, tmp_path):
    camp, calibration = campaign
    expected = stage_by_stage(camp, calibration, "T1", tmp_path / "stages")
    outputs = {name: tmp_path / "item" / name / "T1.zarr" for name in STORES}
    log = tmp_path / "item.log"
    written = run_item(
        camp.path, "T1", outputs, calibration=calibration, params={"aoi": AOI, "features": FEATURES},
        chunks=CHUNKS, log_path=log,
    )
    assert written == outputs
    for name in STORES:
        ours, theirs = xr.open_zarr(outputs[name]).load(), xr.open_zarr(expected[name]).load()
        assert {k: str(v).replace("/item/", "/") for k, v in ours.attrs.pop("surffin_inputs").items()} == {
            k: str(v).replace("/stages/", "/") for k, v in theirs.attrs.pop("surffin_inputs").items()
        }
        xr.testing.assert_identical(ours, theirs)
    assert xr.open_zarr(outputs["features"])["R0"].notnull().mean() > 0.5
    text = log.read_text()
    for stage in ("ingest", "aoi", "reflectance", "registration", "features", "item T1"):
        assert f"{stage} done in" in text


def test_run_items_runs_each_chain_with_its_own_parameters(campaign, tmp_path):
    camp, calibration = campaign
    expected = stage_by_stage(camp, calibration, "S1", tmp_path / "stages")
    items = {name: {store: tmp_path / "batch" / store / f"{name}.zarr" for store in STORES} for name in ("S1", "T1")}
    params = {"S1": {"aoi": AOI, "features": FEATURES}, "T1": {"features": {**FEATURES, "size": 3}}}
    log = tmp_path / "batch.log"
    assert run_items(camp.path, items, calibration=calibration, params=params, chunks=CHUNKS, log_path=log) == items
    for name in STORES:
        ours, theirs = xr.open_zarr(items["S1"][name]).load(), xr.open_zarr(expected[name]).load()
        del ours.attrs["surffin_inputs"], theirs.attrs["surffin_inputs"]
        xr.testing.assert_identical(ours, theirs)
    t1 = {store: xr.open_zarr(items["T1"][store]).attrs["surffin_parameters"] for store in ("aoi", "features")}
    assert t1["aoi"] == {} and t1["features"]["size"] == 3
    text = log.read_text()
    assert all(f"{line} done in" in text for line in ("item S1", "item T1", "batch of 2 items"))


def test_run_items_refuses_parameters_of_items_it_does_not_run(campaign, tmp_path):
    camp, calibration = campaign
    items = {"T1": {store: tmp_path / store / "T1.zarr" for store in STORES}}
    with pytest.raises(ValueError, match=r"items not in the batch: \['S9'\]"):
        run_items(camp.path, items, calibration=calibration, params={"S9": {}})
    assert not any(path.exists() for path in items["T1"].values())


def test_run_item_names_wrong_outputs_and_stages(campaign, tmp_path):
    camp, calibration = campaign
    outputs = {name: tmp_path / name for name in STORES if name != "registered"}
    with pytest.raises(ValueError, match="registered"):
        run_item(camp.path, "T1", outputs, calibration=calibration)
    outputs["registered"] = tmp_path / "registered"
    with pytest.raises(ValueError, match="smoothing"):
        run_item(camp.path, "T1", outputs, calibration=calibration, params={"smoothing": {}})
    assert not any(path.exists() for path in outputs.values())


def test_an_unknown_scheduler_name_is_an_error_naming_it():
    with pytest.raises(ValueError, match="unknown dask scheduler 'thread'"):
        with dask_scheduler("thread"):
            pass


def test_local_schedulers_never_import_dask_distributed():
    # Looking for a dask.distributed client (a scheduler given by name, a rechunk left to
    # choose its method) imports it: 0.4 s in every job. A fresh process shows whether it did.
    code = (
        "import sys, dask.array as da\n"
        "from surffin.pipeline.jobs import dask_scheduler\n"
        "with dask_scheduler('threads', 2):\n"
        "    total = da.ones((64, 64), chunks=16).rechunk((32, 8)).sum().compute()\n"
        "print(int(total), 'distributed' in sys.modules)\n"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert run.stdout.split() == ["4096", "False"]
