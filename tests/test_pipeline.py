"""The entry points: the stage table's jobs write what the in-memory chain computes; jobs sharing a process."""

import dataclasses
import json
import logging
import math
import multiprocessing
import os
import shutil
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

import cv2
import dask
import dask.array
import numpy as np
import pytest
import xarray as xr
import yaml

import surffin
from surffin.io.ingest import ingest_item
from surffin.io.store import open_store
from surffin.method import stages
from surffin.method.features import select_roi, variability
from surffin.method.stages import ITEM_CHAIN, aoi_stage, features_stage, process_item
from surffin.pipeline.jobs import dask_scheduler, in_worker, job_seconds, logging_to, start_workers
from surffin.pipeline.parameters import read_config
from surffin.pipeline.run import run_calibration, run_ingest, run_stage
from surffin.pipeline.table import STAGES, input_paths
from surffin.pipeline.workflow import CHECKED_VIEWS, Plan
from surffin.simulate.presets import PRESETS

CHUNKS = {"y": 32, "x": 32}
PARAMS = {"window": 9, "size": 5, "variability_size": 7, "min_views": 2, "min_spread": math.radians(10)}


@pytest.fixture(scope="module")
def campaign(tiny_campaign, tmp_path_factory):
    camp = surffin.read_campaign(tiny_campaign)
    return camp, run_calibration(camp.path, tmp_path_factory.mktemp("pipeline") / "calibration.zarr")


def chain_jobs(camp, calibration, item, folder):
    """An item's chain as the workflow's jobs run it: one run_stage per stage of the table."""
    stores = {"ingest": run_ingest(camp.path, item, folder / "ingest.zarr", chunks=CHUNKS), "calibration": calibration}
    roi = camp.items[item].roi
    for step in ITEM_CHAIN:
        params = {key: PARAMS[key] for key in step.keywords if key in PARAMS}
        params |= {"roi": roi.as_mapping()} if "roi" in step.keywords and roi is not None else {}
        inputs = {name: stores[name] for name in step.inputs}
        stores[step.output] = run_stage(
            step.function, folder / f"{step.output}.zarr", stores=inputs, params=params, chunks=CHUNKS
        )
    return stores


@pytest.mark.parametrize("item", ["S1", "T1"])
def test_the_jobs_write_what_the_chain_in_memory_computes(campaign, tmp_path, item):
    camp, calibration = campaign
    stores = chain_jobs(camp, calibration, item, tmp_path)
    ingest = open_store(stores["ingest"]).load()
    in_memory = process_item(ingest, open_store(calibration).load(), roi=camp.items[item].roi, **PARAMS)
    for step in ITEM_CHAIN:
        written = open_store(stores[step.output]).load()
        xr.testing.assert_allclose(written.drop_attrs(), in_memory[step.output].drop_attrs())
        assert written.attrs["surffin_stage"] == step.name
        assert written.attrs["surffin_code_version"] == STAGES[step.name].version
    assert open_store(stores["features"])["R0"].notnull().mean() > 0.5
    assert open_store(stores["ingest"]).attrs["surffin_code_version"] == STAGES["ingest"].version
    # a specimen's registration and features cover its roi and the smoothing's margin, a scene's its whole crop
    roi = camp.items[item].roi
    grid = camp.crop if roi is None else roi.grown(PARAMS["size"] // 2).clip(camp.crop)
    for name in ("registered", "features"):
        written = open_store(stores[name])
        assert (written["y"].values[[0, -1]].tolist(), written["x"].values[[0, -1]].tolist()) == (
            [grid.y[0], grid.y[1] - 1],
            [grid.x[0], grid.x[1] - 1],
        )


def test_a_roi_changes_no_value_inside_it(campaign, monkeypatch):
    # the chain on the roi and its margin against the same chain on the whole crop: bit for bit inside the roi
    camp, calibration = campaign
    roi = camp.items["S1"].roi
    assert roi.grown(PARAMS["size"] // 2).clip(camp.crop).shape < camp.crop.shape
    ingest, calibration = ingest_item(camp, "S1"), open_store(calibration).load()
    restricted = process_item(ingest, calibration, roi=roi, **PARAMS)
    with pytest.raises(ValueError, match="does not hold"):
        features_stage(restricted["registered"], restricted["reflectance"], restricted["aoi"], roi=roi, size=9)
    monkeypatch.setattr(stages, "feature_window", lambda roi, size, grid: grid)
    whole = process_item(ingest, calibration, roi=roi, **PARAMS)
    assert whole["features"].sizes == dict(zip("yx", camp.crop.shape))
    for name in ("registered", "features"):
        inside, expected = select_roi(restricted[name], roi), select_roi(whole[name], roi)
        assert set(inside.data_vars) == set(expected.data_vars)
        for variable in inside.data_vars:
            np.testing.assert_array_equal(inside[variable].values, expected[variable].values, err_msg=variable)
    assert restricted["features"].attrs["uncertainty_inflation"] == whole["features"].attrs["uncertainty_inflation"]


def test_run_stage_refuses_what_is_no_stage_and_wrong_stores(campaign, tmp_path):
    camp, _ = campaign
    ingest = run_ingest(camp.path, "T1", tmp_path / "ingest.zarr", chunks=CHUNKS)
    with pytest.raises(KeyError, match="variability"):
        run_stage(variability, tmp_path / "a.zarr", stores={"ingest": ingest})
    with pytest.raises(ValueError, match=r"stage aoi reads the stores \['ingest'\], got \['aoi'\]"):
        run_stage(aoi_stage, tmp_path / "a.zarr", stores={"aoi": ingest})
    assert not (tmp_path / "a.zarr").exists()


def test_process_item_names_a_parameter_no_stage_takes(campaign):
    camp, calibration = campaign
    with pytest.raises(TypeError, match="smoothing"):
        process_item(xr.Dataset(), xr.Dataset(), smoothing=3)


def test_jobs_in_threads_keep_their_own_log(tmp_path):
    barrier = threading.Barrier(2)

    def job(name):
        with logging_to(tmp_path / f"{name}.log") as log:
            barrier.wait()
            for step in range(20):
                log.info("%s step %d", name, step)
            barrier.wait()

    threads = [threading.Thread(target=job, args=(name,)) for name in ("first", "second")]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    for name, other in (("first", "second"), ("second", "first")):
        text = (tmp_path / f"{name}.log").read_text()
        assert text.count(f"{name} step") == 20 and other not in text
    assert not logging.getLogger("surffin").handlers


def test_a_job_logs_its_wall_time_only_when_it_finishes(tmp_path):
    start = time.perf_counter()
    with logging_to(tmp_path / "done.log"):
        time.sleep(0.2)
    elapsed = time.perf_counter() - start
    with pytest.raises(RuntimeError), logging_to(tmp_path / "failed.log"):
        raise RuntimeError("broken")
    assert 0.2 <= job_seconds(tmp_path / "done.log") <= elapsed + 0.01
    assert "job failed" in (tmp_path / "failed.log").read_text()
    assert job_seconds(tmp_path / "failed.log") is None
    assert job_seconds(tmp_path / "missing.log") is None


def test_jobs_in_threads_share_the_scheduler_and_restore_it(tmp_path):
    before = dask.config.get("scheduler", None)
    inside, barrier = [], threading.Barrier(2)

    def job(rows):
        with dask_scheduler("synchronous"):
            barrier.wait()
            inside.append(dask.config.get("scheduler"))
            inside.append(int(dask.array.ones((rows, 8), chunks=4).sum().compute()))
            barrier.wait()

    threads = [threading.Thread(target=job, args=(rows,)) for rows in (8, 16)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert sorted(value for value in inside if isinstance(value, int)) == [64, 128]
    assert [value for value in inside if not isinstance(value, int)] == [dask.local.get_sync] * 2
    assert dask.config.get("scheduler", None) == before


def test_an_unknown_scheduler_name_is_an_error_naming_it():
    with pytest.raises(ValueError, match="unknown dask scheduler 'thread'"):
        with dask_scheduler("thread"):
            pass
    with dask_scheduler("synchronous"):  # the failure left nothing behind
        assert np.isfinite(dask.array.ones(4, chunks=2).sum().compute())


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


def test_the_plan_names_each_job_s_files_from_the_table(tiny_campaign, tmp_path):
    config = {**read_config(), "campaign": str(tiny_campaign), "processed": str(tmp_path / "out")}
    plan = Plan.read(tiny_campaign, config)
    camp = plan.campaign
    assert plan.output("registration", "S1") == f"{tmp_path}/out/registered/S1.zarr"
    assert input_paths("features", config["processed"], "cal.zarr") == {
        name: f"{tmp_path}/out/{name}/{{item}}.zarr" for name in ("registered", "reflectance", "aoi")
    }
    assert input_paths("reflectance", config["processed"], "cal.zarr")["calibration"] == "cal.zarr"
    results = plan.results()
    assert [path for path in results if "/features/" in path] == [plan.output("features", n) for n in camp.items]
    assert plan.output("summary") in results and plan.output("labels", "T1") in results
    assert plan.item_views("S2") == [str(path) for path in camp.items["S2"].views]
    assert plan.registration_parameters("S1")["roi"] == camp.items["S1"].roi.as_mapping()
    assert plan.registration_parameters("S1")["size"] == config["features"]["smoothing"]
    assert "size" not in plan.registration_parameters("T1")  # no roi: no margin, the smoothing does not rerun it
    assert plan.repeat is not None  # the tiny preset renders a repeat calibration set
    assert plan.specimens_by_roughness()[0] == min(
        camp.specimens, key=lambda name: camp.specimens[name].roughness_mm or float("inf")
    )
    without = Plan.read(tiny_campaign, {**config, "calibration_repeat": None})
    assert without.repeat is None


def test_a_views_sidecars_are_inputs_of_the_jobs_that_read_it(tiny_campaign, tmp_path):
    raw = tmp_path / "raw"
    shutil.copytree(tiny_campaign, raw)
    camp = surffin.read_campaign(raw)
    view = camp.items["S2"].views[1]
    meta = view.with_name(f"{view.stem}.meta.json")
    meta.write_text('{"exposure_us": 250}')
    wall = camp.calibration.wall[0]
    settings = wall.with_name(f"{wall.stem}.meta.json")
    settings.write_text('{"exposure_us": 250}')
    config = {**read_config(), "processed": str(tmp_path / "out"), "calibration_repeat": None}
    plan = Plan.read(raw, config)
    assert plan.item_views("S2") == [str(path) for path in camp.items["S2"].views[:2]] + [str(meta)] + [
        str(path) for path in camp.items["S2"].views[2:]
    ]
    assert str(settings) in plan.calibration_views()
    assert plan.item_views("S1") == [str(path) for path in camp.items["S1"].views]


def broken_intensity(view: Path, pixels: int) -> None:
    """Rewrite npz ``view`` with a negative intensity on its first ``pixels`` valid pixels."""
    arrays = dict(np.load(view))
    valid = np.flatnonzero(np.isfinite(arrays["xyz"]).all(axis=-1).ravel() & (arrays["xyz"][..., 2].ravel() > 0))
    arrays["intensity"].reshape(-1)[valid[:pixels]] = -1.0
    np.savez(view, **arrays)


def test_the_plan_reads_every_view_s_pixels_once_and_again_when_the_file_changes(tiny_campaign, tmp_path):
    raw = tmp_path / "raw"
    shutil.copytree(tiny_campaign, raw)
    config = {**read_config(), "campaign": str(raw), "processed": str(tmp_path / "out")}
    plan = Plan.read(raw, config)
    camp = plan.campaign
    every = [*(v for item in camp.items.values() for v in item.views), *camp.calibration.wall]
    every += [*camp.calibration.reference.views, *plan.repeat.wall, *plan.repeat.reference.views]
    assert set(plan.checked["views"]) == {str(view) for view in every}
    (tmp_path / "out").mkdir()
    for damaged in ("[1, 2]", '{"views": 3}', "{"):  # a damaged record: every file is read
        (tmp_path / "out" / CHECKED_VIEWS).write_text(damaged)
        assert Plan.read(raw, config).checked == plan.checked
    shutil.rmtree(tmp_path / "out")
    assert not (tmp_path / "out").exists()  # reading a plan writes nothing
    plan.keep_checked()
    record = json.loads((tmp_path / "out" / CHECKED_VIEWS).read_text())
    assert record == plan.checked and record["camera"] == camp.camera.settings
    written = (tmp_path / "out" / CHECKED_VIEWS).stat()
    Plan.read(raw, config).keep_checked()  # the record is current: it is not written again
    assert (tmp_path / "out" / CHECKED_VIEWS).stat().st_ino == written.st_ino
    scene, wall = camp.scenes["T1"].views[1], plan.repeat.wall[0]
    # a recorded file of the same size and time is not read again: broken pixels there pass ...
    stat = scene.stat()
    broken_intensity(scene, 7)
    assert scene.stat().st_size == stat.st_size
    os.utime(scene, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    Plan.read(raw, config)
    # ... but a file that changed is read, and every broken one is named with its problem
    os.utime(scene)
    broken_intensity(wall, 3)
    with pytest.raises(surffin.ViewFileError) as raised:
        Plan.read(raw, config)
    message = str(raised.value)
    assert message.startswith(f"2 of {len(every)} view files break the campaign contract:\n")
    assert f"{scene}: intensity is NaN, infinite or negative on 7 of " in message
    assert f"{wall}: intensity is NaN, infinite or negative on 3 of " in message


def test_the_plan_refuses_a_calibration_of_another_camera(tiny_campaign, tmp_path):
    other = tmp_path / "other"
    surffin.simulate_campaign(
        other,
        preset=dataclasses.replace(
            PRESETS["tiny"],
            crop=None,
            camera=dataclasses.replace(PRESETS["tiny"].camera, width=PRESETS["tiny"].camera.width + 8),
        ),
        seed=0,
    )
    calibration = run_calibration(other, tmp_path / "other.zarr")
    config = {**read_config(), "calibration_store": str(calibration)}
    with pytest.raises(surffin.StoreError, match="sensor"):
        Plan.read(tiny_campaign, config)


def test_the_plan_refuses_a_calibration_acquired_with_other_settings(tiny_campaign, tmp_path):
    root = tmp_path / "raw"
    shutil.copytree(tiny_campaign, root)

    def settings(folder, exposure):
        for view in (root / folder).rglob("*.npz"):
            view.with_name(f"{view.stem}.meta.json").write_text(json.dumps({"exposure_us": exposure, "gain": 2}))

    settings("calibration", 250)
    settings("specimens", 250)
    settings("scenes", 250)
    calibration = run_calibration(root, tmp_path / "calibration.zarr")
    doc = yaml.safe_load((root / "campaign.yaml").read_text())
    del doc["calibration"]
    doc["camera"]["match_settings"] = ["exposure_us"]
    (root / "campaign.yaml").write_text(yaml.safe_dump(doc))
    config = {**read_config(), "calibration_store": str(calibration)}
    assert Plan.read(root, config).campaign.camera.match_settings == ("exposure_us",)
    settings("specimens", 300)
    settings("scenes", 300)
    with pytest.raises(surffin.StoreError) as raised:
        Plan.read(root, config)
    message = str(raised.value)
    assert message.startswith(f"{calibration}: setting 'exposure_us' differs between the calibration's views (250 in ")
    assert "calibration/wall/" in message and "(300 in " in message and "specimens/" in message
    assert "camera.match_settings asks them equal" in message
    # the gain differs nowhere, and is not asked to match anyway
    doc["camera"]["match_settings"] = ["gain"]
    (root / "campaign.yaml").write_text(yaml.safe_dump(doc))
    Plan.read(root, config)


class Name(str):
    """A str subclass, as snakemake's file names are."""


def crash():
    os._exit(3)


def test_in_worker_runs_the_call_in_another_process_with_plain_arguments():
    pid, argument = in_worker(worker_report, Name("a"), {"b": (Name("c"),)})
    assert pid != os.getpid()
    assert argument == ("str", {"b": ["c"]})
    # the workers are kept for the next jobs: no new process per job
    assert len({pid, *(in_worker(worker_report, "x")[0] for _ in range(2 * (os.cpu_count() or 1)))}) <= (
        os.cpu_count() or 1
    )


def test_in_worker_raises_the_call_s_error_and_survives_a_crash(tmp_path):
    with pytest.raises(ValueError, match="stage aoi reads the stores"):
        in_worker(run_stage, aoi_stage, tmp_path / "a.zarr", stores={"aoi": tmp_path})
    with pytest.raises(BrokenProcessPool):
        in_worker(crash)
    assert in_worker(worker_report, "after")[1] == ("str", "after")


def worker_report(name, mapping=None):
    return os.getpid(), (type(name).__name__, name if mapping is None else mapping)


def pid_after(seconds):
    time.sleep(seconds)
    return os.getpid()


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="one worker per core: two workers need two cores")
def test_in_worker_sends_a_key_s_job_to_the_worker_that_ran_its_last_job():
    # two jobs at once take two workers; each key's next job goes back to its key's worker
    with ThreadPoolExecutor(2) as threads:
        pids = dict(zip("ab", threads.map(lambda key: in_worker(pid_after, 0.5, affinity=key), "ab")))
    assert pids["a"] != pids["b"]
    assert in_worker(os.getpid, affinity="b") == pids["b"]
    assert in_worker(os.getpid, affinity="a") == pids["a"]
    assert in_worker(os.getpid) == pids["b"]  # no key: the worker used longest ago, which keeps its key
    assert in_worker(os.getpid, affinity="b") == pids["b"]
    assert in_worker(os.getpid, affinity="c") == pids["a"]


def test_start_workers_starts_the_worker_the_next_job_runs_in():
    thread = start_workers()
    thread.join(timeout=120)
    assert not thread.is_alive()
    started = {child.pid for child in multiprocessing.active_children()}
    assert in_worker(os.getpid) in started


def opencv_threads():
    return cv2.getNumThreads()


def test_in_worker_computes_on_one_thread():
    # the pool runs one worker per core: OpenCV's own threads would only contend with the other workers
    assert in_worker(opencv_threads) == 1
