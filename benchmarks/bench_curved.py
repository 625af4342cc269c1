"""The method on curved surfaces: cylindrical specimens against flat ones, against the simulator's truth.

Run by hand: ``python benchmarks/bench_curved.py [--radii 0.3 -0.3 1.0 -1.0] [--seeds 0] [--size 128]
[--no-scene]``.

Renders, in memory, a small campaign of the ``paper`` preset (two plaster classes, S1 and S3, five views each from
0 to 40 deg at 0.35 m; a scene of both at 0.55 m) flat and with every specimen's top bent into a cylindrical panel of
each radius (``Specimen.radius``: + convex, - concave), and runs the method's chain on a centred ``--size`` pixel
square crop (:func:`surffin.method.stages.process_item`, registration by poses; the true instrument function stands
in for the calibration, which the wall makes and curvature does not touch). Printed per radius (median over the
seeds):

- ``AOI deg``: median absolute error of every view's AOI against the truth, on the specimens' interiors
  (top-face pixels at least the label margin from an edge);
- ``reg px``: median distance between the registration's map and where each view truly sees each reference pixel's
  surface point, interiors;
- ``R0 %``, ``n %``: median absolute relative error of the smoothed features on the specimens' interiors
  (:func:`surffin.analysis.evaluation.relative_errors`);
- ``label %``, ``filtered %``: the scene's accuracy (1-NN on the specimens' features) before and after the label
  filter;

and beside each its ratio to the flat row; with several seeds, then each seed's AOI, registration, R0 and n errors
and their ratios to the same seed's flat row (the spread). The default run takes about two minutes on two cores
(each seed).

The method's plane fits carry each normal from its window's centroid to the pixel along the normal's slopes
(:mod:`surffin.method.geometry`); before that, a plane of a window shifted by half its side or cut by the crop's
border had the normal of the window's centroid, up to 3.5 deg off a 0.3 m cylinder, and the curved rows' n errors
were 2.6-3.1 times the flat row's.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import xarray as xr

from surffin.analysis.evaluation import relative_errors
from surffin.grid import Roi
from surffin.io.ingest import build_cube
from surffin.io.viewfile import View
from surffin.method.classify import score, training_set
from surffin.method.stages import labels_stage, process_item
from surffin.simulate.camera import to_camera
from surffin.simulate.instrument import draw_instrument, observe
from surffin.simulate.plan import plan_campaign
from surffin.simulate.presets import PRESETS, Preset, SceneLayout
from surffin.simulate.scene import Scene, keyed_rng, render
from surffin.simulate.truth import instrument_truth, item_truth, reference_coordinates, scene_truth_label

COLUMNS = ("AOI deg", "reg px", "R0 %", "n %", "label %", "filtered %")


def design(radius: float | None, size: int) -> Preset:
    """Make the benchmark's preset: two plaster classes of ``paper``, their tops of ``radius``, a centred crop."""
    paper = PRESETS["paper"]
    specimens = tuple(replace(paper.specimens[k], radius=radius) for k in (0, 2))
    height, width = paper.camera.height, paper.camera.width
    crop = ((height - size) // 2, (height + size) // 2), ((width - size) // 2, (width + size) // 2)
    scene = SceneLayout(specimens, (0.0, 90.0), 0.55, (0.0, 10.0, 20.0, 30.0, 40.0))
    return replace(
        paper,
        name=f"curved-{radius}",
        crop=crop,
        specimens=specimens,
        scenes=(scene,),
        repeat_calibration=False,
    )


def acquire(acquisition, preset, seed, instrument, crop: Roi, textures: dict) -> tuple[xr.Dataset, xr.Dataset, list]:
    """Render and observe every view of an acquisition; its ingest cube, truth and noise-free geometries."""
    camera = preset.camera
    scene = Scene(acquisition.faces, seed, textures)
    reference_pose = acquisition.poses[acquisition.reference]
    views, geometries, per_view = [], [], []
    for stem, pose in zip(acquisition.stems, acquisition.poses):
        geometry = render(scene, camera, pose)
        xyz, intensity = observe(geometry, instrument, preset, keyed_rng(seed, "view", acquisition.name, stem))
        valid = np.isfinite(xyz).all(axis=-1)
        views.append(View(Path(f"{stem}.npz"), xyz, intensity.astype(np.float32), valid, pose))
        geometries.append(geometry)
        per_view.append((geometry.aoi, *reference_coordinates(scene, camera, reference_pose, geometry)))
    aoi, u_ref, v_ref = (np.stack(arrays) for arrays in zip(*per_view))
    truth = item_truth(acquisition, preset, geometries[acquisition.reference], aoi, u_ref, v_ref)
    return build_cube(views, crop), truth, geometries


def interior_mask(geometry, crop: Roi, margin: float) -> np.ndarray:
    """Specimen top pixels of one view at least ``margin`` from an edge, on the crop."""
    rows, columns = crop.slices
    return ((geometry.label >= 0) & (geometry.edge_distance >= margin))[rows, columns]


def aoi_errors(chain: dict, geometries: list, crop: Roi, margin: float) -> np.ndarray:
    """Absolute AOI errors (degrees) of every view's interior pixels."""
    rows, columns = crop.slices
    errors = []
    for index, geometry in enumerate(geometries):
        mask = interior_mask(geometry, crop, margin)
        fitted = chain["aoi"]["aoi"].isel(view=index).values
        errors.append(np.degrees(np.abs(fitted - geometry.aoi[rows, columns]))[mask])
    errors = np.concatenate(errors)
    return errors[np.isfinite(errors)]


def registration_errors(chain: dict, geometries: list, reference: int, camera, crop: Roi, margin: float):
    """Distances (pixels) between the registration maps and the true projections of the reference pixels' points."""
    rows, columns = crop.slices
    points = geometries[reference].world_points()[rows, columns].reshape(-1, 3)
    mask = interior_mask(geometries[reference], crop, margin).reshape(-1)
    maps = chain["registered"]
    errors = []
    for index, geometry in enumerate(geometries):
        if index == reference:
            continue
        u, v = camera.project(to_camera(points, geometry.pose))
        map_x = maps["map_x"].isel(view=index).values.reshape(-1)
        map_y = maps["map_y"].isel(view=index).values.reshape(-1)
        errors.append(np.hypot(map_x - u, map_y - v)[mask])
    errors = np.concatenate(errors)
    return errors[np.isfinite(errors)]


def measure(radius: float | None, seed: int, size: int, with_scene: bool) -> dict:
    """Render and process the benchmark's campaign with tops of ``radius`` at ``seed``; the table's values."""
    preset = design(radius, size)
    crop = Roi.from_mapping({"y": list(preset.crop[0]), "x": list(preset.crop[1])})
    camera = preset.camera
    instrument = draw_instrument(
        camera, preset.coef_mean, preset.coef_variability, preset.gain, keyed_rng(seed, "instrument")
    )
    calibration = instrument_truth(instrument, preset)
    plan = [a for a in plan_campaign(preset, seed) if a.kind == "specimen" or (with_scene and a.kind == "scene")]
    textures, features, aoi, registration, R0, n = {}, {}, [], [], [], []
    result = dict.fromkeys(COLUMNS, float("nan"))
    for acquisition in plan:
        ingest, truth, geometries = acquire(acquisition, preset, seed, instrument, crop, textures)
        chain = process_item(ingest, calibration, method="poses")
        features[acquisition.name] = chain["features"]
        if acquisition.kind == "scene":
            training = training_set({s.name: (features[s.name], s.cls, None) for s in preset.specimens})
            labels = labels_stage(chain["features"], training)
            label = scene_truth_label(geometries[acquisition.reference], preset.label_margin)
            for var, column in (("label", "label %"), ("label_filtered", "filtered %")):
                result[column] = 100 * score(labels[var], label, preset.classes, training.attrs["classes"])["accuracy"]
            continue
        aoi.append(aoi_errors(chain, geometries, crop, preset.label_margin))
        registration.append(
            registration_errors(chain, geometries, acquisition.reference, camera, crop, preset.label_margin)
        )
        errors = relative_errors(chain["features"], truth)
        R0.append(errors["R0"])
        n.append(errors["n"])
    result["AOI deg"] = float(np.median(np.concatenate(aoi)))
    result["reg px"] = float(np.median(np.concatenate(registration)))
    result["R0 %"] = 100 * float(np.median(np.abs(np.concatenate(R0))))
    result["n %"] = 100 * float(np.median(np.abs(np.concatenate(n))))
    return result


def main() -> None:
    """Measure flat and every radius at every seed and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--radii", nargs="+", type=float, default=[0.3, -0.3, 1.0, -1.0], help="metres")
    parser.add_argument("--seeds", nargs="+", type=int, default=[0])
    parser.add_argument("--size", type=int, default=128, help="side of the centred crop, pixels")
    parser.add_argument("--no-scene", action="store_true", help="specimens only (no classification)")
    args = parser.parse_args()
    rows, runs = {}, {}
    for radius in [None, *args.radii]:
        start = time.perf_counter()
        runs[radius] = [measure(radius, seed, args.size, not args.no_scene) for seed in args.seeds]
        rows[radius] = {key: float(np.median([run[key] for run in runs[radius]])) for key in COLUMNS}
        print(f"  radius {radius}: {time.perf_counter() - start:.0f} s", flush=True)
    flat = rows[None]
    print(f"\n{'radius m':>9s}" + "".join(f"{key:>11s}{'/flat':>6s}" for key in COLUMNS))
    for radius, values in rows.items():
        label = "flat" if radius is None else f"{radius:+.2f}"
        cells = "".join(f"{values[key]:11.3f}{values[key] / flat[key]:6.2f}" for key in COLUMNS)
        print(f"{label:>9s}{cells}")
    if len(args.seeds) > 1:
        # the spread: each seed's value and its ratio to the flat row of the same seed
        keys = COLUMNS[:4]
        print(f"\nper seed {' '.join(map(str, args.seeds))}: value (ratio to the same seed's flat row)")
        print(f"{'radius m':>9s}" + "".join(f"{key:>{14 * len(args.seeds)}s}" for key in keys))
        for radius, seeds in runs.items():
            label = "flat" if radius is None else f"{radius:+.2f}"
            cells = "".join(
                f"{run[key]:8.3f}({run[key] / base[key]:4.2f})" for key in keys for run, base in zip(seeds, runs[None])
            )
            print(f"{label:>9s}{cells}")


if __name__ == "__main__":
    main()
