"""Speed and accuracy of the AOI kernel (surffin.method.geometry) on synthetic 480x640 frames.

Run by hand: ``python benchmarks/bench_aoi.py [--repeat N] [--subset N]``, or, to time the kernel against another
version of it, ``python benchmarks/bench_aoi.py --against OLD.py`` (e.g. after
``git show HEAD:surffin/method/geometry.py > /tmp/geometry_head.py``).

Table 1, one row per window (``15-120``: the adaptive support, windows of 15 px doubling up to 120 px while the
surface stays planar), on a scene: the kernel's median time per frame, its best (the machine is shared: the gap
shows the load) and the median rate; a scipy cKDTree PCA (k = window**2 nearest points, tree build + queries on a
subset of pixels, extrapolated per pixel) in the same process, and the ratio; the AOI error against the truth
(median and 95th percentile of |aoi - truth|, and the median of aoi - truth, over the pixels with a normal) and the
share of valid pixels without one. The scene: a wall 0.8 m away tilted by 25 deg, with a 2 cm proud rectangular
specimen (parallel to the wall, so the true normal is the same everywhere) over the central third of the image.
Then the mixed-pixel test (``mixed_pixels``) on that frame: time, ratio to the 15-120 AOI's, pixels flagged (none).

Table 2, the median AOI error |aoi - truth| of a plain wall per window, distance and tilt: what the default window
is chosen on (METHOD.md: calibration views at 0.3-1.0 m, tilts 0-30 deg; the paper's AOI noise 0.27-1.7 deg).

Table 3, the bias: the median signed error aoi - truth on the same walls, of the kernel (all pixels with a normal)
and of a PCA (total least squares) plane fit, the estimator the kernel replaced, computed here by brute force on the
centred windows of a sample of pixels: with depth noise along the ray, PCA overestimates the AOI, by ~1/window^2.
What the kernel keeps at small windows near normal incidence is not a tilt of its normals but the fold of
arccos(|v . n|) at 0: a noisy normal can only make an AOI near 0 larger. It vanishes where the AOI is far from 0
(60 deg tilt).

The camera: pinhole, fx 565, fy 579, principal point at the centre; 0.9 mm Gaussian depth noise along each ray.

With ``--against``, only one table: per frame (the scene, its central 320x480 crop, a plain wall at 30 deg, and
the views of the ingest stores given with ``--stores``, e.g. ``processed/ingest/S1-01.zarr``) and support, the
median time per frame of the other version's ``frame_angle_of_incidence`` and of this one's, run in turn in the same
process, and the ratio of the medians (wall clock, and CPU time: the machine is shared), the largest |aoi
difference| (deg), whether the two leave the same pixels without an AOI, and whether aoi and distance are equal to
the bit; then, per frame, the same for ``mixed_pixels`` (window ``mixed``; the last columns: the same pixels flagged).
"""

from __future__ import annotations

import argparse
import importlib.util
import time
import timeit
from pathlib import Path

import numpy as np
import xarray as xr
from scipy.spatial import cKDTree

from surffin.io.store import open_store
from surffin.method.geometry import frame_angle_of_incidence, mixed_pixels

HEIGHT, WIDTH = 480, 640
FX, FY = 565.0, 579.0
NOISE = 0.9e-3
# Plane-fit supports (window, max_window): fixed windows, then the adaptive ones (windows doubling up to
# max_window while the surface stays planar: the defaults of the items' and of the wall views' AOI).
WINDOWS = ((7, 7), (15, 15), (21, 21), (31, 31), (61, 61), (15, 120), (21, 120))
ERROR_WINDOWS = ((7, 7), (11, 11), (15, 15), (21, 21), (31, 31), (15, 120), (21, 120))
DISTANCES = (0.3, 0.5, 0.8, 1.0)
TILTS = (0.0, 30.0, 60.0)


def scene(distance: float = 0.8, tilt: float = 25.0, specimen: bool = True, seed: int = 0):
    """Noisy frame xyz (H, W, 3) float32, metres, and the true AOI (H, W), radians.

    A wall ``distance`` metres away along the optical axis, turned by ``tilt`` degrees
    about the y axis, with a 2 cm proud specimen over the central third if ``specimen``.
    """
    rows, cols = np.mgrid[0:HEIGHT, 0:WIDTH].astype(float)
    rays = np.stack([(cols - (WIDTH - 1) / 2) / FX, (rows - (HEIGHT - 1) / 2) / FY, np.ones_like(rows)], axis=-1)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    normal = np.array([np.sin(np.deg2rad(tilt)), 0.0, -np.cos(np.deg2rad(tilt))])
    offset = np.full((HEIGHT, WIDTH), distance * np.cos(np.deg2rad(tilt)))
    if specimen:
        offset[HEIGHT // 3 : 2 * HEIGHT // 3, WIDTH // 3 : 2 * WIDTH // 3] -= 0.02
    cosine = rays @ normal
    depth = -offset / cosine + np.random.default_rng(seed).normal(0.0, NOISE, (HEIGHT, WIDTH))
    return (rays * depth[..., None]).astype(np.float32), np.arccos(np.abs(cosine))


def error_degrees(xyz: np.ndarray, truth: np.ndarray, support: tuple[int, int]) -> tuple[np.ndarray, float]:
    """Aoi - truth (degrees) where the kernel gives an AOI, and the share of pixels without one."""
    aoi, _ = frame_angle_of_incidence(xyz, support[0], max_window=support[1])
    has = np.isfinite(aoi)
    return np.rad2deg((aoi - truth)[has]), 1.0 - has.mean()


def pca_error_degrees(xyz: np.ndarray, truth: np.ndarray, window: int, sample: int) -> np.ndarray:
    """Aoi - truth (degrees) of PCA planes through the centred windows of ``sample`` random pixels."""
    rng = np.random.default_rng(2)
    half = window // 2
    rows = rng.integers(half, HEIGHT - half, sample)
    cols = rng.integers(half, WIDTH - half, sample)
    offsets = np.arange(-half, half + 1)
    points = xyz.astype(np.float64)
    windows = points[rows[:, None, None] + offsets[:, None], cols[:, None, None] + offsets].reshape(sample, -1, 3)
    windows -= windows.mean(axis=1, keepdims=True)
    normal = np.linalg.eigh(np.einsum("nki,nkj->nij", windows, windows))[1][..., 0]
    ray = points[rows, cols] / np.linalg.norm(points[rows, cols], axis=-1, keepdims=True)
    aoi = np.arccos(np.minimum(np.abs(np.sum(normal * ray, axis=-1)), 1.0))
    return np.rad2deg(aoi - truth[rows, cols])


def kdtree_seconds_per_frame(xyz: np.ndarray, k: int, subset: int, repeat: int) -> float:
    """CKDTree PCA normals: tree build + k-NN query + batched eigh, extrapolated to a frame."""
    points = xyz.reshape(-1, 3).astype(np.float64)
    chosen = np.random.default_rng(1).choice(len(points), subset, replace=False)

    def normals():
        tree = cKDTree(points)
        built = time.perf_counter()
        _, neighbours = tree.query(points[chosen], k=k, workers=-1)
        near = points[neighbours]
        near -= near.mean(axis=1, keepdims=True)
        np.linalg.eigh(np.einsum("nki,nkj->nij", near, near))
        return built

    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        built = normals()
        end = time.perf_counter()
        times.append((built - start) + (end - built) * len(points) / subset)
    return float(np.median(times))


def label(window: int, largest: int) -> str:
    """``15`` for a fixed window, ``15-120`` for an adaptive one."""
    return f"{window:>7d}" if largest == window else f"{window:>3d}-{largest:<3d}"


def median_seconds(kernels, repeat: int) -> np.ndarray:
    """Median wall and CPU seconds (2, 2) of two callables run in turn ``repeat`` times for each timer."""
    timers = (time.perf_counter, time.process_time)
    # seconds[timer][kernel]: the runs of each kernel, alternating
    seconds = [[[], []] for _ in timers]
    for timer, runs in zip(timers, seconds):
        for _ in range(repeat):
            for kernel, kept in zip(kernels, runs):
                kept += timeit.repeat(kernel, timer, number=1, repeat=1)
    return np.median(seconds, axis=-1)


def store_frames(paths: list[Path]) -> dict[str, np.ndarray]:
    """Read the views (H, W, 3) of ingest stores' ``xyz``, axis in x, y, z order, by ``item vK``."""
    frames = {}
    for path in paths:
        xyz = open_store(path, chunks=None)["xyz"].load()
        if "axis" in xyz.coords:
            xyz = xyz.sel(axis=["x", "y", "z"])
        for view in range(xyz.sizes["view"]):
            frames[f"{path.name.removesuffix('.zarr')} v{view}"] = xyz.isel(view=view).values
    return frames


def compare(path: Path, repeat: int, stores: list[Path]) -> None:
    """Print the table of this kernel against the ``frame_angle_of_incidence`` of another geometry module file."""
    spec = importlib.util.spec_from_file_location("reference_geometry", path)
    reference = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(reference)
    kernels = (reference.frame_angle_of_incidence, frame_angle_of_incidence)
    xyz = scene()[0]
    frames = {
        "scene 480x640": xyz,
        "crop 320x480": xyz[80:400, 80:560],
        "wall 480x640": scene(0.5, 30.0, specimen=False, seed=1)[0],
        **store_frames(stores),
    }
    print(f"this kernel against {path}: median of {repeat} runs each, in turn")
    header = ("frame", "window", "ref ms", "ms", "speed-up", "cpu speed-up", "max |d aoi| deg", "same NaN", "identical")
    print(" | ".join(header))

    def row(name, support, seconds, difference, same, identical):
        (old_wall, new_wall), (old_cpu, new_cpu) = seconds
        cells = (f"{name:13s}", f"{support:>7s}", f"{old_wall * 1e3:6.1f}", f"{new_wall * 1e3:5.1f}")
        cells += (f"{old_wall / new_wall:8.2f}", f"{old_cpu / new_cpu:12.2f}", f"{difference:>15s}", f"{same!s:>8}")
        print(" | ".join((*cells, f"{identical!s:>9}")))

    for name, frame in frames.items():
        for window, largest in ((15, 120), (21, 120), (15, 15)):
            runs = [lambda kernel=kernel: kernel(frame, window, max_window=largest) for kernel in kernels]
            (old, old_distance), (new, new_distance) = (run() for run in runs)
            difference = f"{np.nanmax(np.abs(np.rad2deg(old - new)), initial=0.0):.1e}"
            same = np.array_equal(np.isnan(old), np.isnan(new))
            identical = np.array_equal(old, new, equal_nan=True)
            identical &= np.array_equal(old_distance, new_distance, equal_nan=True)
            row(name, label(window, largest), median_seconds(runs, repeat), difference, same, identical)
    for name, frame in frames.items():
        cloud = xr.DataArray(frame[None], dims=("view", "y", "x", "axis"))
        runs = [lambda kernel=kernel: kernel(cloud).values for kernel in (reference.mixed_pixels, mixed_pixels)]
        same = np.array_equal(*(run() for run in runs))
        row(name, "mixed", median_seconds(runs, repeat), "-", same, same)


def main() -> None:
    """Parse the command line and print the three tables, or the table against another version of the kernel."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=15, help="timed runs per window (median reported)")
    parser.add_argument("--subset", type=int, default=2000, help="pixels of the cKDTree and PCA references")
    parser.add_argument("--against", type=Path, help="a geometry.py to time this kernel against (only that table)")
    parser.add_argument("--stores", type=Path, nargs="*", default=[], help="ingest stores whose views --against adds")
    args = parser.parse_args()
    if args.against is not None:
        compare(args.against, args.repeat, args.stores)
        return
    xyz, truth = scene()
    pixels = HEIGHT * WIDTH
    print(f"frame {HEIGHT}x{WIDTH}, noise {NOISE * 1e3:.1f} mm along the ray, median of {args.repeat} runs")
    header = ("window", "ms/frame", "best ms", "Mpx/s", "kdtree Mpx/s", "speed-up")
    header += ("median err deg", "p95 err deg", "bias deg", "no AOI %")
    print(" | ".join(header))
    for window, largest in WINDOWS:
        runs = timeit.repeat(
            lambda: frame_angle_of_incidence(xyz, window, max_window=largest), number=1, repeat=args.repeat
        )
        seconds = float(np.median(runs))
        reference = kdtree_seconds_per_frame(xyz, window * window, args.subset, max(3, args.repeat // 5))
        signed, lost = error_degrees(xyz, truth, (window, largest))
        error = np.abs(signed)
        row = (
            label(window, largest),
            f"{seconds * 1e3:8.1f}",
            f"{min(runs) * 1e3:7.1f}",
            f"{pixels / seconds / 1e6:5.1f}",
            f"{pixels / reference / 1e6:12.3f}",
            f"{reference / seconds:8.0f}",
            f"{np.median(error):14.3f}",
            f"{np.percentile(error, 95):11.3f}",
            f"{np.median(signed):+8.3f}",
            f"{100 * lost:8.2f}",
        )
        print(" | ".join(row))
    print()
    cloud = xr.DataArray(xyz[None], dims=("view", "y", "x", "axis"))
    runs = timeit.repeat(lambda: mixed_pixels(cloud), number=1, repeat=args.repeat)
    adaptive = timeit.repeat(lambda: frame_angle_of_incidence(xyz, 15, max_window=120), number=1, repeat=args.repeat)
    print(
        f"mixed pixels: {np.median(runs) * 1e3:.1f} ms/frame (best {min(runs) * 1e3:.1f}), "
        f"{np.median(runs) / np.median(adaptive):.2f} x the 15-120 AOI; {int(mixed_pixels(cloud).sum())} flagged"
    )
    print()
    columns = [(tilt, distance) for tilt in TILTS for distance in DISTANCES]
    frames = [scene(distance, tilt, specimen=False) for tilt, distance in columns]
    heading = " | ".join(["window", *(f"{tilt:2.0f}/{distance:.1f}" for tilt, distance in columns)])
    errors = {window: [error_degrees(xyz, truth, window)[0] for xyz, truth in frames] for window in ERROR_WINDOWS}
    print("median AOI error |aoi - truth|, deg, of a plain wall (tilt deg / distance m)")
    print(heading)
    for window, signed in errors.items():
        print(" | ".join([label(*window), *(f"{np.median(np.abs(error)):6.2f}" for error in signed)]))
    print()
    print(f"median signed AOI error aoi - truth, deg, of a plain wall: kernel / PCA ({args.subset} windows)")
    print(heading.replace(" | ", " |   ", 1).replace(" | ", "   | "))
    for window, signed in errors.items():
        pca = [np.median(pca_error_degrees(xyz, truth, window[0], args.subset)) for xyz, truth in frames]
        cells = (f"{np.median(error):+.2f}/{reference:+.2f}" for error, reference in zip(signed, pca))
        print(" | ".join([label(*window), *cells]))


if __name__ == "__main__":
    main()
