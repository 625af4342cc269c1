"""The feature stage on a dask.distributed cluster writes the stores the threads scheduler writes.

The stages reach a cluster through ``run_stage(..., scheduler=<address>)`` (``--config
scheduler=tcp://...`` in the workflow). Inputs are made from the tiny preset with the pipeline
functions, chunked so that chunks do not divide the image and every worker gets several.
"""

import math

import pytest
import xarray as xr
from distributed import Client, LocalCluster, get_task_stream

import surffin
from surffin.method.stages import aoi_stage, features_stage, reflectance_stage, registration_stage
from surffin.pipeline.run import run_calibration, run_ingest, run_stage

#: Chunks over the 40 x 60 crop of the tiny camera: neither divides it.
CHUNKS = {"y": 16, "x": 24}


@pytest.fixture(scope="module")
def campaign(tiny_campaign, tmp_path_factory):
    """A tiny campaign with the stores the feature stage reads, for a specimen (roi) and the scene."""
    camp = surffin.read_campaign(tiny_campaign)
    processed = tmp_path_factory.mktemp("distributed") / "processed"
    calibration = run_calibration(camp.path, processed / "calibration.zarr")
    for item in ("S1", "T1"):
        store = {stage: processed / stage / f"{item}.zarr" for stage in ("ingest", "aoi", "reflectance", "registered")}
        run_ingest(camp.path, item, store["ingest"], chunks=CHUNKS)
        inputs = {"ingest": store["ingest"]}
        run_stage(aoi_stage, store["aoi"], stores=inputs, chunks=CHUNKS)
        inputs["aoi"] = store["aoi"]
        run_stage(reflectance_stage, store["reflectance"], stores={**inputs, "calibration": calibration}, chunks=CHUNKS)
        inputs["reflectance"] = store["reflectance"]
        run_stage(
            registration_stage, store["registered"], stores=inputs, params={"roi": roi(camp, item)}, chunks=CHUNKS
        )
    return camp, processed


@pytest.fixture(scope="module")
def cluster():
    """Two single-threaded worker processes (tasks and results cross process boundaries)."""
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as local:
        yield local


def roi(camp, item):
    region = camp.items[item].roi
    return None if region is None else region.as_mapping()


@pytest.mark.parametrize("item", ["S1", "T1"])
def test_features_on_a_cluster_are_identical_to_threads(campaign, cluster, tmp_path, item):
    camp, processed = campaign
    stores = {name: processed / name / f"{item}.zarr" for name in ("registered", "reflectance", "aoi")}
    params = {"roi": roi(camp, item), "size": 7, "variability_size": 7, "min_views": 2, "min_spread": math.radians(10)}
    common = {"stores": stores, "params": params, "chunks": CHUNKS}
    threads = run_stage(features_stage, tmp_path / "threads.zarr", scheduler="threads", threads=2, **common)
    with Client(cluster) as client, get_task_stream(client) as tasks:
        on_cluster = run_stage(features_stage, tmp_path / "cluster.zarr", scheduler=cluster.scheduler_address, **common)

    assert tasks.data, "no task ran on the cluster"
    assert {task["worker"] for task in tasks.data} <= set(cluster.scheduler_info["workers"])
    expected = xr.open_zarr(threads).load()
    assert expected["R0"].notnull().sum() > 100
    xr.testing.assert_identical(xr.open_zarr(on_cluster).load(), expected)
