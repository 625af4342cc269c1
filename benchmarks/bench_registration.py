"""Accuracy and speed of co-registration (surffin.method.registration) on a synthetic paper campaign.

Run by hand: ``python benchmarks/bench_registration.py [--campaign DIR] [--truth DIR] [--tables 1 .. 6]``. Without
``--campaign`` it renders the ``paper`` preset (seed 0) into a temporary folder. A map's error is measured against
the simulator's truth (``<campaign>-truth/<item>.zarr``) with :func:`surffin.method.registration.registration_error`:
per reference pixel, the distance in the reference image between it and the true position of the point its map
sends it to.

Table 1, per item and method: median error (pixels) per non-reference view over all mapped pixels, and over the
specimen top faces (truth ``label`` >= 0: the surface that is classified), the mapped share of the reference grid,
and the time of :func:`registration_maps`. Methods: ``poses`` (default: the reference range averaged over 9 x 9
pixels of one surface), ``poses raw`` (``smooth=1``: the error the 0.9 mm depth noise of the reference point
induces), ``homography`` (SIFT, the whole image) and, for specimens, ``homography roi`` (keypoints on the roi).
Table 2, the keypoint detectors of the homography method on every item: keypoints, matches and inliers per view,
inlier rms, median error and time per item (OpenCV 5 moved AKAZE to opencv-contrib: listed as missing unless
opencv-contrib-python-headless comes first on PYTHONPATH).
Table 3, runtime per item: the maps by each method (poses with and without the pose refinement, and its cost per
non-reference view) and :func:`register` of two images. Table 4, the poses method's ``smooth`` window (the default
is chosen on it): median and 99th percentile of the error; a wider window averages more depth noise away (the median
falls) but bends the range near depth steps (the tail grows).
Tables 5 and 6, the pose refinement against a robot's pose errors (0.2-0.5 deg and 1-2 mm per non-reference view,
``--seed``): the map errors on the specimen tops and the corrections (Table 5), and the features against the truth
from the whole item chain (Table 6), with the true, the perturbed and the refined poses.
Table 7, registration without poses (``method="clouds"``: the poses estimated from the clouds), with the campaign's
intrinsics (``yaml``) and without any (``none``; without distortion in campaign.yaml the model is fitted to the clouds
either way): per item the median error against the truth per non-reference view, the distance from the maps of the
true poses (median and 95th percentile over the pixels both map), the candidates refined per view, the camera model
used (``given`` or ``estimated``) with its residual (pixels), and the time.
Table 8, :func:`surffin.method.stages.registration_stage` per item (the item's intensity and z standing in for its
reflectance and AOI), single-threaded: median CPU seconds of ``--repeat`` runs (at least 5) of the stage and of its
parts, the maps and :func:`register`. ``--baseline DIR`` (a folder holding another revision's registration.py and
optionally camera_model.py, e.g. from ``git show``) runs that code alternately in the same process: the speed-ups,
the largest relative differences of the stage's maps and values (and whether their NaN patterns agree) and whether
the two outputs are identical (values, NaNs, dtypes and attrs: ``xarray.Dataset.identical``).
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import tempfile
import time
from pathlib import Path
from unittest import mock

import cv2
import numpy as np
import xarray as xr
from bench_chunks import CONFIG, chain_parameters, quiet_logs  # benchmarks/ is on sys.path when run as a script
from bench_item import interior
from scipy.spatial.transform import Rotation
from threadpoolctl import threadpool_limits

from surffin.errors import RegistrationError
from surffin.io.campaign import read_campaign
from surffin.io.ingest import ingest_item
from surffin.io.store import open_store
from surffin.method import registration, stages
from surffin.method.registration import DETECTORS, register, registration_error, registration_maps
from surffin.method.stages import process_item
from surffin.pipeline import parameters
from surffin.pipeline.run import run_calibration
from surffin.simulate import simulate_campaign

ALL_DETECTORS = ("sift", "orb", "akaze")


def load(campaign: Path, truth: Path):
    """(item, ingest cube, truth Dataset, roi or None) for every specimen and scene."""
    camp = read_campaign(campaign, require_calibration=False)
    for name, item in camp.items.items():
        ingest = ingest_item(camp, name).load()
        reference = xr.open_zarr(truth / f"{name}.zarr")[["u_ref", "v_ref", "label"]].load()
        roi = {"y": list(item.roi.y), "x": list(item.roi.x)} if item.roi is not None else None
        yield name, ingest, reference, roi


def robot_poses(ingest: xr.Dataset, rng: np.random.Generator) -> tuple[xr.Dataset, list[np.ndarray]]:
    """Return a copy of the cube whose non-reference views carry poses with a robot's errors, and the errors.

    Each error is a camera-frame transform (the recorded pose is the true one times it): 0.2-0.5 deg about a random
    axis, 1-2 mm along a random direction; the reference view's is the identity.
    """
    robot = ingest.copy(deep=True)
    errors = []
    for index, view in enumerate(robot["view"].values):
        error = np.eye(4)
        if view != ingest.attrs["reference_view"]:
            axis, direction = (vector / np.linalg.norm(vector) for vector in rng.normal(size=(2, 3)))
            error[:3, :3] = Rotation.from_rotvec(np.deg2rad(rng.uniform(0.2, 0.5)) * axis).as_matrix()
            error[:3, 3] = rng.uniform(0.001, 0.002) * direction
        robot["pose"].values[index] = robot["pose"].values[index] @ error
        errors.append(error)
    return robot, errors


def size(transform: np.ndarray) -> str:
    """Format a rigid transform's translation (mm) and rotation angle (deg)."""
    angle = np.rad2deg(Rotation.from_matrix(transform[:3, :3]).magnitude())
    return f"{1e3 * np.linalg.norm(transform[:3, 3]):.2f} mm {angle:.3f} deg"


def timed_maps(ingest, **kwargs):
    """Return (maps, seconds) of :func:`registration_maps`, or (the RegistrationError, seconds) when it fails."""
    start = time.perf_counter()
    try:
        maps = registration_maps(ingest, **kwargs)
    except RegistrationError as error:
        return error, time.perf_counter() - start
    return maps, time.perf_counter() - start


def errors(maps, truth):
    """Return the registration error of a map's non-reference views against the truth.

    Returns
    -------
    whole, top : (view,) ndarray
        Median error per non-reference view over all mapped pixels and over specimen tops.
    error : DataArray (view, y, x)
        The error of those views.
    on_top : DataArray (y, x)
        The specimen-top mask.
    """
    error = registration_error(maps, truth["u_ref"], truth["v_ref"]).isel(view=slice(1, None))
    top = truth["label"].sel(y=maps["y"], x=maps["x"]) >= 0
    return error.median(("y", "x")).values, error.where(top).median(("y", "x")).values, error, top


def fmt(values) -> str:
    """Join the values with ``/``, two decimals each."""
    return "/".join(f"{value:.2f}" for value in values)


def accuracy_table(items) -> None:
    """Print Table 1: each item's error, mapped share and time per method, then the pooled medians."""
    print("Table 1: median registration error per non-reference view (pixels), paper preset")
    print(f"{'item':5} {'method':15} {'all mapped pixels':>26} {'specimen tops':>26} {'mapped':>7} {'time s':>7}")
    pooled = {}
    for name, ingest, truth, roi in items:
        runs = {
            "poses": {"method": "poses"},
            "poses raw": {"method": "poses", "smooth": 1},
            "homography": {"method": "homography"},
        }
        if roi is not None:
            runs["homography roi"] = {"method": "homography", "roi": roi}
        for label, kwargs in runs.items():
            maps, seconds = timed_maps(ingest, **kwargs)
            if isinstance(maps, RegistrationError):
                print(f"{name:5} {label:15} failed: {str(maps)[:90]}")
                continue
            whole, top, error, on_top = errors(maps, truth)
            mapped = float(np.isfinite(maps["map_x"].isel(view=slice(1, None))).mean())
            pooled.setdefault(label, []).append((error.values, np.broadcast_to(on_top.values, error.shape)))
            print(f"{name:5} {label:15} {fmt(whole):>26} {fmt(top):>26} {mapped:7.3f} {seconds:7.2f}")
    print("pooled median over the items and views it registered (all mapped pixels / specimen tops):")
    for label, chunks in pooled.items():
        error = np.concatenate([values.ravel() for values, _ in chunks])
        top = np.concatenate([mask.ravel() for _, mask in chunks])
        print(f"  {label:15} {np.nanmedian(error):.3f} / {np.nanmedian(error[top]):.3f} px")


DETECTOR_COLUMNS = {  # statistic: (header, format)
    "keypoints": ("keypoints", "9.0f"),
    "matches": ("matches", "8.0f"),
    "inliers": ("inliers", "8.0f"),
    "rms": ("rms px", "7.2f"),
    "all": ("median err all", "15.2f"),
    "tops": ("tops", "7.2f"),
    "seconds": ("time s", "7.2f"),
}


def detector_row(detector: str, name: str, stats: dict) -> str:
    """Format one row of Table 2: a detector's statistics (:data:`DETECTOR_COLUMNS`) on one item."""
    cells = (f"{stats[key]:{spec}}" for key, (_, spec) in DETECTOR_COLUMNS.items())
    return f"{detector:8} {name:5} " + " ".join(cells)


def detector_table(items) -> None:
    """Print Table 2: each keypoint detector of the homography method on every item, and its means."""
    print("\nTable 2: detectors of the homography method (means over the non-reference views)")
    header = (f"{title:>{spec.split('.')[0]}}" for title, spec in DETECTOR_COLUMNS.values())
    print(f"{'detector':8} {'item':5} " + " ".join(header))
    for detector in ALL_DETECTORS:
        if detector not in DETECTORS:
            print(f"{detector:8} not in this OpenCV ({', '.join(DETECTORS)} are)")
            continue
        rows = []
        for name, ingest, truth, _ in items:
            maps, seconds = timed_maps(ingest, method="homography", detector=detector)
            if isinstance(maps, RegistrationError):
                print(f"{detector:8} {name:5} failed: {str(maps)[:100]}")
                continue
            views = list(maps.attrs["diagnostics"].values())[1:]
            stats = {key: np.mean([view[key] for view in views]) for key in ("keypoints", "matches", "inliers", "rms")}
            whole, top, _, _ = errors(maps, truth)
            rows.append({**stats, "all": np.median(whole), "tops": np.median(top), "seconds": seconds})
            print(detector_row(detector, name, rows[-1]))
        if rows:
            print(detector_row(detector, "mean", {key: np.mean([row[key] for row in rows]) for key in rows[0]}))


def runtime_table(items, repeat: int) -> None:
    """Print Table 3: per item, the best of ``repeat`` times of the maps by each method and of :func:`register`."""
    print(f"\nTable 3: runtime per item (best of {repeat}), seconds; refinement: its cost per non-reference view")
    print(
        f"{'item':5} {'views':>5} {'grid':>9} {'maps poses':>10} {'unrefined':>9} {'refinement':>10} "
        f"{'maps homography':>15} {'register':>9}"
    )
    runs = {"poses": {"method": "poses"}, "unrefined": {"method": "poses", "refine": False}}
    runs["homography"] = {"method": "homography"}
    for name, ingest, _, _ in items:
        best = {}
        for _ in range(repeat):
            for label, kwargs in runs.items():
                maps, seconds = timed_maps(ingest, **kwargs)
                best[label] = min(best.get(label, np.inf), seconds)
            ds = xr.Dataset({"reflectance": ingest["intensity"], "aoi": ingest["xyz"].sel(axis="z")})
            start = time.perf_counter()
            register(ds, maps)
            best["register"] = min(best.get("register", np.inf), time.perf_counter() - start)
        grid = f"{ingest.sizes['y']}x{ingest.sizes['x']}"
        per_view = (best["poses"] - best["unrefined"]) / (ingest.sizes["view"] - 1)
        print(
            f"{name:5} {ingest.sizes['view']:5} {grid:>9} {best['poses']:10.2f} {best['unrefined']:9.2f} "
            f"{per_view:10.3f} {best['homography']:15.2f} {best['register']:9.3f}"
        )


def smoothing_table(items, windows=(1, 3, 5, 7, 9, 11, 15)) -> None:
    """Print Table 4: the poses method's error and time per ``smooth`` window, over all items."""
    print("\nTable 4: poses method, reference range averaged over a window (all items, non-reference views)")
    print(f"{'smooth':>6} {'median px':>9} {'p99 px':>7} {'time s':>7}")
    for window in windows:
        chunks, seconds = [], 0.0
        for _, ingest, truth, _ in items:
            maps, elapsed = timed_maps(ingest, method="poses", smooth=window)
            _, _, error, _ = errors(maps, truth)
            chunks.append(error.values[np.isfinite(error.values)])
            seconds += elapsed
        error = np.concatenate(chunks)
        print(f"{window:6d} {np.median(error):9.3f} {np.percentile(error, 99):7.2f} {seconds / len(items):7.2f}")


def refinement_table(items, seed: int) -> dict:
    """Print Table 5: map errors with true, robot-recorded and refined poses; return the perturbed cubes by item.

    Per item and non-reference view: the median error on the specimen tops with the true poses, the recorded
    (perturbed, :func:`robot_poses`) ones, those refined and (in parentheses) the true poses refined; the recorded
    pose's error, the correction the refinement found, and the pose error it leaves (both in the view's frame).
    """
    print("\nTable 5: pose refinement against a robot's pose errors; median error on the specimen tops (pixels)")
    print(
        f"{'item':5} {'view':5} {'true':>6} {'recorded':>9} {'refined':>8} {'(true refined)':>14} "
        f"{'error of the recorded pose':>27} {'correction':>22} {'error left':>22}"
    )
    rng = np.random.default_rng(seed)
    robots, pooled = {}, {}
    for name, ingest, truth, _ in items:
        robot, pose_errors = robot_poses(ingest, rng)
        robots[name] = robot
        runs = {
            "true": (ingest, False),
            "recorded": (robot, False),
            "refined": (robot, True),
            "true refined": (ingest, True),
        }
        maps = {label: registration_maps(cube, method="poses", refine=refine) for label, (cube, refine) in runs.items()}
        tops = {label: errors(one, truth)[1] for label, one in maps.items()}
        views = list(maps["refined"]["view"].values)[1:]
        for index, view in enumerate(views, start=1):
            correction = np.array(maps["refined"].attrs["diagnostics"][view]["correction"])
            cells = " ".join(
                f"{tops[label][index - 1]:{width}.3f}"
                for label, width in (("true", 6), ("recorded", 9), ("refined", 8), ("true refined", 14))
            )
            print(
                f"{name:5} {view:5} {cells} {size(pose_errors[index]):>27} {size(correction):>22} "
                f"{size(pose_errors[index] @ correction):>22}"
            )
            for label in tops:
                pooled.setdefault(label, []).append(tops[label][index - 1])
    print("mean of the medians: " + ", ".join(f"{label} {np.mean(values):.3f}" for label, values in pooled.items()))
    return robots


def features_table(campaign: Path, truth: Path, items, robots: dict) -> None:
    """Print Table 6: the features against the truth from the item chain with true, perturbed and refined poses.

    As ``bench_item.py``: the median relative error of R0 and n on the specimen interiors (the scene's labelled
    pixels), :func:`~surffin.method.stages.process_item` with the configuration's parameters and the calibration
    fitted once, for the true and the perturbed poses (``robots``), each unrefined and refined.
    """
    quiet_logs()
    camp = read_campaign(campaign)
    with tempfile.TemporaryDirectory() as scratch:
        store = run_calibration(
            camp.path, Path(scratch, "calibration.zarr"), params=parameters.calibration_parameters(CONFIG)
        )
        calibration = open_store(store).compute()
        print("\nTable 6: features vs truth, median relative error (%) of R0 / n on the specimen interiors")
        runs = {"true": (False, False), "true refined": (False, True), "perturbed": (True, False)}
        runs["perturbed refined"] = (True, True)
        print(f"{'item':5} " + " ".join(f"{label:>18}" for label in runs))
        for name, ingest, _, _ in items:
            params = chain_parameters(CONFIG, camp.items[name])
            cells = []
            for perturbed, refine in runs.values():
                cube = robots[name] if perturbed else ingest
                features = process_item(cube, calibration, **{**params, "refine": refine})["features"]
                reference = xr.open_zarr(truth / f"{name}.zarr").sel(y=features.y, x=features.x).compute()
                mask = interior(reference, camp.items[name])
                rel = {
                    key: float(np.abs((features[key] - reference[key]) / reference[key]).where(mask).median())
                    for key in ("R0", "n")
                }
                cells.append(f"{100 * rel['R0']:8.2f} / {100 * rel['n']:6.2f}")
            print(f"{name:5} " + " ".join(f"{cell:>18}" for cell in cells))


def clouds_table(items) -> None:
    """Print Table 7: maps from poses estimated from the clouds against the truth and the true poses' maps."""
    print("Table 7: registration without poses (method clouds) against the truth and the true poses' maps (pixels)")
    print(
        f"{'item':5} {'camera':9} {'median error vs truth':>26} {'median vs poses':>22} {'p95 vs poses':>22} "
        f"{'candidates':>11} {'model':>9} {'model px':>9} {'time s':>7}"
    )
    for name, ingest, truth, _ in items:
        by_poses = registration_maps(ingest, method="poses")
        bare = ingest.drop_vars("pose")
        cameras = {"yaml": bare, "none": bare.assign_attrs(camera={})}
        for label, cube in cameras.items():
            maps, seconds = timed_maps(cube, method="clouds")
            if isinstance(maps, RegistrationError):
                print(f"{name:5} {label:9} failed: {str(maps)[:150]}")
                continue
            whole, _, _, _ = errors(maps, truth)
            apart = np.hypot(maps["map_x"] - by_poses["map_x"], maps["map_y"] - by_poses["map_y"]).isel(
                view=slice(1, None)
            )
            diagnostics = [maps.attrs["diagnostics"][str(view)] for view in maps["view"].values[1:]]
            model = maps.attrs["camera_model"]
            print(
                f"{name:5} {label:9} {fmt(whole):>26} {fmt(apart.median(('y', 'x')).values):>22} "
                f"{fmt(apart.quantile(0.95, ('y', 'x')).values):>22} "
                f"{'/'.join(str(info['candidates']) for info in diagnostics):>11} "
                f"{model['source']:>9} {model['residual_px']:9.4f} {seconds:7.2f}"
            )


def load_baseline(folder: Path):
    """Import another revision's registration.py (with its camera_model.py, if the folder has one) as a module."""

    def imported(name: str, path: Path):
        spec = importlib.util.spec_from_file_location(name, path)
        module = sys.modules[name] = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module

    current = sys.modules["surffin.method.camera_model"]
    if (folder / "camera_model.py").exists():
        sys.modules["surffin.method.camera_model"] = imported("baseline_camera_model", folder / "camera_model.py")
    try:
        return imported("baseline_registration", folder / "registration.py")
    finally:
        sys.modules["surffin.method.camera_model"] = current


def cpu_seconds(function, *args, **kwargs):
    """Return (the result of the call, the CPU seconds it took)."""
    start = time.process_time()
    result = function(*args, **kwargs)
    return result, time.process_time() - start


def stage_runs(module, ingest: xr.Dataset, inputs: tuple) -> tuple[xr.Dataset, dict]:
    """Run the registration stage with the maps and register of ``module``: its output and CPU seconds per part."""
    with mock.patch.multiple(stages, registration_maps=module.registration_maps, register=module.register):
        registered, seconds = cpu_seconds(stages.registration_stage, ingest, *inputs)
    maps, maps_seconds = cpu_seconds(module.registration_maps, ingest)
    _, register_seconds = cpu_seconds(module.register, xr.Dataset({**inputs[0], **inputs[1]}), maps)
    return registered, {"stage": seconds, "maps": maps_seconds, "register": register_seconds}


def largest_difference(new: xr.Dataset, old: xr.Dataset, names) -> tuple[float, bool]:
    """Return the largest relative difference of variables between two outputs and whether their NaN patterns agree."""
    largest, same = 0.0, True
    for name in names:
        a, b = (np.asarray(ds[name].values, dtype=np.float64) for ds in (new, old))
        same &= bool(np.array_equal(np.isnan(a), np.isnan(b)))
        both = np.isfinite(a) & np.isfinite(b) & (b != 0)
        if both.any():
            largest = max(largest, float(np.max(np.abs(a[both] - b[both]) / np.abs(b[both]))))
    return largest, same


def stage_table(items, repeat: int, baseline: Path | None) -> None:
    """Print Table 8: the registration stage per item, single-threaded, against a baseline revision if given."""
    repeat = max(repeat, 5)
    modules = {"current": registration}
    if baseline is not None:
        modules["baseline"] = load_baseline(baseline)
    print(f"\nTable 8: registration_stage per item, 1 thread, CPU seconds (median of {repeat})")
    header = f"{'item':5} {'method':10} {'stage':>6} {'maps':>6} {'register':>8}"
    if baseline is not None:
        header += f" {'base stage':>10} {'x stage':>7} {'x maps':>6} {'x reg.':>6} {'max rel maps':>12}"
        header += f" {'max rel values':>14} {'NaN same':>8} {'identical':>9}"
    print(header)
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with threadpool_limits(1):
            for name, ingest, _, _ in items:
                inputs = (
                    xr.Dataset({"aoi": ingest["xyz"].sel(axis="z", drop=True).astype(np.float32)}),
                    xr.Dataset({"reflectance": ingest["intensity"].astype(np.float32)}),
                )
                seconds, outputs = {label: [] for label in modules}, {}
                for _ in range(repeat):
                    for label, module in modules.items():
                        outputs[label], spent = stage_runs(module, ingest, inputs)
                        seconds[label].append(spent)
                median = {
                    label: {part: float(np.median([run[part] for run in runs])) for part in runs[0]}
                    for label, runs in seconds.items()
                }
                now = median["current"]
                line = f"{name:5} {outputs['current'].attrs['method']:10} {now['stage']:6.3f} {now['maps']:6.3f}"
                line += f" {now['register']:8.3f}"
                if baseline is not None:
                    old = median["baseline"]
                    maps = largest_difference(outputs["current"], outputs["baseline"], ("map_x", "map_y"))
                    values = largest_difference(outputs["current"], outputs["baseline"], ("reflectance", "aoi"))
                    line += f" {old['stage']:10.3f} {old['stage'] / now['stage']:7.2f} {old['maps'] / now['maps']:6.2f}"
                    line += f" {old['register'] / now['register']:6.2f} {maps[0]:12.1e} {values[0]:14.1e}"
                    line += f" {'yes' if maps[1] and values[1] else 'NO':>8}"
                    line += f" {'yes' if outputs['current'].identical(outputs['baseline']) else 'NO':>9}"
                print(line)
    finally:
        cv2.setNumThreads(threads)


def main() -> None:
    """Parse the command line, render a campaign unless one is given, and print the tables asked for."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--campaign", type=Path, help="a rendered paper campaign (default: render one)")
    parser.add_argument("--truth", type=Path, help="its truth folder (default: <campaign>-truth)")
    parser.add_argument("--repeat", type=int, default=3, help="timing repeats of table 3")
    parser.add_argument("--seed", type=int, default=0, help="of the robot's pose errors (tables 5 and 6)")
    parser.add_argument(
        "--baseline", type=Path, help="table 8: a folder with another revision's registration.py (and camera_model.py)"
    )
    parser.add_argument("--tables", type=int, nargs="+", default=[1, 2, 3, 4, 5, 6, 7, 8], help="the tables to print")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as scratch:
        campaign = args.campaign
        if campaign is None:
            campaign = Path(scratch) / "paper"
            simulate_campaign(campaign, preset="paper", seed=0)
        truth = args.truth or campaign.resolve().with_name(campaign.resolve().name + "-truth")
        items = list(load(campaign, truth))
        tables = {
            1: lambda: accuracy_table(items),
            2: lambda: detector_table(items),
            3: lambda: runtime_table(items, args.repeat),
            4: lambda: smoothing_table(items),
            7: lambda: clouds_table(items),
            8: lambda: stage_table(items, args.repeat, args.baseline),
        }
        for number in sorted(set(args.tables) & set(tables)):
            tables[number]()
        if {5, 6} & set(args.tables):
            robots = refinement_table(items, args.seed)
            if 6 in args.tables:
                features_table(campaign, truth, items, robots)


if __name__ == "__main__":
    main()
