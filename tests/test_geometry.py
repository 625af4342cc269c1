"""AOI, plane normals and mixed pixels of organized clouds (surffin.method.geometry) against independent references."""

import warnings
from dataclasses import replace

import dask
import numpy as np
import pytest
import xarray as xr
from hypothesis import given, settings
from hypothesis import strategies as st

import surffin
from surffin.grid import Roi
from surffin.io.ingest import ingest_item
from surffin.method.calibration import TERMS
from surffin.method.geometry import (
    DEFAULT_JUMP,
    DEFAULT_MAX_WINDOW,
    DEFAULT_WINDOW,
    angle_of_incidence,
    frame_angle_of_incidence,
    mixed_pixels,
    plane_normals,
)
from surffin.method.stages import aoi_stage, reflectance_stage
from surffin.simulate.presets import PRESETS

FOCAL = 565.0


def rays(height, width, focal=FOCAL):
    """Unit rays (H, W, 3) of a pinhole camera with its principal point at the image centre."""
    rows, cols = np.mgrid[0:height, 0:width].astype(float)
    ray = np.stack([(cols - (width - 1) / 2) / focal, (rows - (height - 1) / 2) / focal, np.ones_like(rows)], axis=-1)
    return ray / np.linalg.norm(ray, axis=-1, keepdims=True)


def plane(normal, offset, height=40, width=50, noise=0.0, seed=0, focal=FOCAL):
    """Points (H, W, 3) of the plane n . P = -offset seen by the camera, the unit normal and the true AOI.

    ``offset`` may be an (H, W) array (parallel planes); noise is Gaussian, metres, along the ray.
    """
    normal = np.asarray(normal, float) / np.linalg.norm(normal)
    ray = rays(height, width, focal)
    cosine = ray @ normal
    depth = -np.asarray(offset) / cosine
    if noise:
        depth = depth + np.random.default_rng(seed).normal(0.0, noise, (height, width))
    return ray * depth[..., None], normal, np.arccos(np.abs(cosine))


def inverse_depth_fit(points):
    """Brute-force plane fit of points (k, 3): least squares of 1/z on (x/z, y/z, 1).

    Returns the mean squared residual of 1/z times mean(1/z)^-4 (depth units, m^2)
    and the unit normal, unoriented.
    """
    x, y, z = points.T
    q = 1.0 / z
    design = np.stack([x / z, y / z, np.ones_like(z)], axis=1)
    coefficients, *_ = np.linalg.lstsq(design, q, rcond=None)
    residual = np.mean((q - design @ coefficients) ** 2) / np.mean(q) ** 4
    return residual, coefficients / np.linalg.norm(coefficients)


def pca_normals(windows):
    """Total least squares (PCA) normals (n, 3) of point sets (n, k, 3): what geometry did before, biased."""
    centred = windows - windows.mean(axis=1, keepdims=True)
    return np.linalg.svd(centred, full_matrices=False)[2][:, -1]


def reference_normal(xyz, row, col, window):
    """The kernel's rule for one pixel by brute force, for clouds without depth jumps.

    Candidates: the windows centred on the pixel and half a window away (8 directions),
    centres inside the image, with at least half the window's pixels valid.
    The first in this order whose mean squared (depth) residual is at most twice the smallest.
    Returns the normal and the candidate's number (0: centred), or None if no candidate
    is usable.
    """
    half = window // 2
    height, width = xyz.shape[:2]
    min_count = int(np.ceil(0.5 * window**2))
    fits = []
    for sy, sx in ((0, 0), (-1, 0), (1, 0), (0, -1), (0, 1), (-1, -1), (-1, 1), (1, -1), (1, 1)):
        cy, cx = row + sy * half, col + sx * half
        block = xyz[max(cy - half, 0) : cy + half + 1, max(cx - half, 0) : cx + half + 1].reshape(-1, 3)
        block = block[np.isfinite(block).all(axis=1)]
        inside = 0 <= cy < height and 0 <= cx < width
        fits.append(inverse_depth_fit(block) if inside and len(block) >= min_count else None)
    usable = [fit for fit in fits if fit is not None]
    if not usable:
        return None
    smallest = min(fit[0] for fit in usable)
    number = next(k for k, fit in enumerate(fits) if fit is not None and fit[0] <= 2 * smallest)
    return fits[number][1], number


def angle_between(a, b):
    """Angle (radians) between unit vectors regardless of sign, stable near 0."""
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.abs(np.sum(a * b, axis=-1)))


# (1) analytic planes ---------------------------------------------------------------------------


@settings(max_examples=25, deadline=None)
@given(
    polar=st.floats(0.0, np.deg2rad(70.0)),  # beyond 76 deg (diagonal slopes) the depth-jump test cuts it
    azimuth=st.floats(0.0, 2 * np.pi),
    offset=st.floats(0.3, 3.0),
    window=st.sampled_from([3, 5, 9, 15]),
)
def test_analytic_plane_matches_closed_form(polar, azimuth, offset, window):
    normal = [np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), -np.cos(polar)]
    xyz, unit, truth = plane(normal, offset)
    aoi, distance = frame_angle_of_incidence(xyz, window)
    assert np.isfinite(aoi).all()
    # the inverse depth is exactly linear in x/z, y/z: only rounding remains (~1e-12 rad)
    np.testing.assert_allclose(aoi, truth, rtol=0, atol=1e-9)
    np.testing.assert_allclose(distance, np.linalg.norm(xyz, axis=-1), rtol=1e-15)
    normals = plane_normals(xyz, window)
    np.testing.assert_allclose(normals, np.broadcast_to(unit, normals.shape), rtol=0, atol=1e-9)
    assert (np.sum(normals * xyz, axis=-1) < 0).all()


# (2) brute force on a noisy surface --------------------------------------------------------------


def noisy_surface(height=48, width=56, seed=3):
    rng = np.random.default_rng(seed)
    ray = rays(height, width)
    rows, cols = np.mgrid[0:height, 0:width]
    depth = 0.6 + 4e-4 * cols + 2e-4 * rows + 3e-6 * (cols - 20.0) ** 2 + rng.normal(0, 0.9e-3, (height, width))
    xyz = ray * depth[..., None]
    xyz[rng.random((height, width)) < 0.1] = np.nan
    return xyz


@pytest.mark.parametrize("window", [3, 7, 15])
def test_normals_equal_brute_force_regression(window):
    xyz = noisy_surface()
    normals = plane_normals(xyz, window)
    rng = np.random.default_rng(window)
    # random pixels, and the corners and borders where the centred window is too empty
    pixels = [*zip(rng.integers(0, 48, 60), rng.integers(0, 56, 60)), (0, 0), (47, 55), (0, 30), (20, 55)]
    checked = shifted = 0
    for row, col in pixels:
        if not np.isfinite(xyz[row, col]).all():
            assert np.isnan(normals[row, col]).all()
            continue
        reference = reference_normal(xyz, row, col, window)
        if reference is None:
            assert np.isnan(normals[row, col]).all()
            continue
        assert angle_between(normals[row, col], reference[0]) < 1e-8
        assert normals[row, col] @ xyz[row, col] < 0
        checked += 1
        shifted += reference[1] > 0
    assert checked >= 40 and shifted >= 3


def test_far_plane_keeps_float64_precision():
    # plane 5 m away beside one at 0.3 m in the same rows: sliding sums see both
    xyz, _, truth = plane([0.1, -0.2, -1.0], 0.3, height=30, width=60)
    far, _, far_truth = plane([0.1, -0.2, -1.0], 5.0, height=30, width=60)
    xyz[:, 30:], truth[:, 30:] = far[:, 30:], far_truth[:, 30:]
    aoi, _ = frame_angle_of_incidence(xyz, 3)
    interior = np.isfinite(aoi)
    assert interior.sum() > 0.9 * aoi.size
    np.testing.assert_allclose(aoi[interior], truth[interior], rtol=0, atol=1e-7)


# (3) no bias from depth noise along the ray -----------------------------------------------------


def test_range_noise_does_not_bias_the_aoi():
    # ToF noise lies along the ray: a PCA (total least squares) plane tilts away from the ray
    # (~N sigma^2 v v^T in the scatter matrix: ~+1 deg here); the inverse depth is linear in the
    # ray coordinates, which carry no noise, so its least squares fit is unbiased
    tilt, window = np.deg2rad(30.0), 21
    xyz, _, truth = plane([np.sin(tilt), 0.0, -np.cos(tilt)], 0.35 * np.cos(tilt), 480, 640, noise=0.9e-3, seed=1)
    aoi, _ = frame_angle_of_incidence(xyz, window)
    error = np.rad2deg(aoi - truth)
    assert np.isfinite(error).mean() > 0.99
    assert abs(np.nanmedian(error)) < 0.1
    assert 0.15 < np.nanmedian(np.abs(error)) < 0.6  # the noise is there: ~0.27 deg
    # the same windows fitted by PCA
    rng = np.random.default_rng(0)
    rows, cols = rng.integers(window, 480 - window, 400), rng.integers(window, 640 - window, 400)
    offsets = np.arange(window) - window // 2
    windows = xyz[rows[:, None, None] + offsets[:, None], cols[:, None, None] + offsets].reshape(400, -1, 3)
    ray = xyz[rows, cols] / np.linalg.norm(xyz[rows, cols], axis=-1, keepdims=True)
    pca = np.arccos(np.abs(np.sum(pca_normals(windows) * ray, axis=-1)))
    assert np.rad2deg(np.median(pca - truth[rows, cols])) > 0.5
    assert abs(np.median(error[rows, cols])) < 0.2  # same pixels


# (4) depth discontinuities -----------------------------------------------------------------------


def step_scene(noise=0.0, band=None, seed=0, height=60, width=80):
    """Two parallel planes 2 cm apart, 0.5 m from the camera, tilted 20 deg; the step runs down column width/2.

    ``band`` fills that column with "nan" (invalid pixels) or "mixed" (points halfway between the planes).
    """
    step = width // 2
    offset = np.full((height, width), 0.5)
    offset[:, step:] += 0.02
    normal = [0.0, np.sin(np.deg2rad(20.0)), -np.cos(np.deg2rad(20.0))]
    xyz, _, truth = plane(normal, offset, height, width, noise, seed)
    if band == "nan":
        xyz[:, step] = np.nan
    elif band == "mixed":
        near, _, _ = plane(normal, 0.5, height, width)
        xyz[:, step] = 0.5 * (near[:, step] + xyz[:, step])
    return xyz, truth


@pytest.mark.parametrize("max_window", [None, 120])
@pytest.mark.parametrize("band", [None, "nan", "mixed"])
def test_step_is_not_bridged(band, max_window):
    # the mixed pixels sit ~1.85% in depth from either side: the default threshold between neighbours
    # (1% beyond the 1.0% of an 80 deg slope at this focal length) misses both halves of the step and
    # must catch it over the pair of pixels two apart (3.0% against 3.7%)
    xyz, truth = step_scene(band=band)
    aoi, _ = frame_angle_of_incidence(xyz, 15, max_window=max_window)
    # only the pixels at the step lose their normal: both sides of a clean step, the band otherwise
    lost = np.flatnonzero(np.isnan(aoi).any(axis=0))
    assert list(lost) == ([39, 40] if band is None else [40])
    # everywhere else, next to the step included, the noiseless planes are recovered exactly
    assert np.nanmax(np.abs(aoi - truth)) < 1e-6


@pytest.mark.parametrize("max_window", [None, 120])
def test_surface_narrower_than_the_window_gets_no_normal(max_window):
    # a ridge 8 px wide, 2 cm proud: every 15 px window on it reaches the board
    offset = np.full((40, 80), 0.5)
    offset[:, 36:44] -= 0.02
    normal = [0.0, np.sin(np.deg2rad(20.0)), -np.cos(np.deg2rad(20.0))]
    xyz, _, truth = plane(normal, offset, 40, 80)
    aoi, _ = frame_angle_of_incidence(xyz, 15, max_window=max_window)
    assert np.isnan(aoi[:, 36:44]).all()
    assert np.isfinite(aoi[:, :35]).all() and np.isfinite(aoi[:, 45:]).all()
    assert np.nanmax(np.abs(aoi - truth)) < 1e-6
    # without the jump test, the ridge gets the normals of windows bridging it to the board
    bridged, _ = frame_angle_of_incidence(xyz, 15, jump=10.0)
    assert np.isfinite(bridged[:, 36:44]).all()
    assert np.max(np.abs(bridged - truth)[:, 36:44]) > np.deg2rad(10.0)


def test_noisy_step_near_edge_as_good_as_interior():
    errors = []
    for seed in range(3):
        xyz, truth = step_scene(noise=0.9e-3, seed=seed)
        aoi, _ = frame_angle_of_incidence(xyz, 15)  # the base windows alone: larger ones cannot fit beside the step
        errors.append(np.abs(aoi - truth))
    error = np.stack(errors)
    near = error[:, :, np.r_[33:39, 41:47]]  # within half a window of the step, off the edge columns
    interior = error[:, :, np.r_[7:25, 55:73]]
    assert np.isfinite(near).all()
    # a bridge would tilt by > 40 deg; choosing among noisy windows would bias the median up
    assert np.median(near) < 1.15 * np.median(interior)
    assert np.percentile(near, 99) < 1.3 * np.percentile(interior, 99)


@pytest.mark.parametrize("max_window", [None, 120])
def test_crease_without_depth_jump(max_window):
    # two faces 40 deg apart meeting along column 40, as a specimen's top and a visible side:
    # no depth jump, but a window across the crease mixes the faces
    ray = rays(40, 80)
    faces = [np.array(normal) / np.linalg.norm(normal) for normal in ([0.3, 0.0, -1.0], [-0.4, 0.0, -1.0])]
    apex = ray[0, 40] * 0.5
    depths = np.stack([(apex @ normal) / (ray @ normal) for normal in faces])
    xyz = ray * depths.min(axis=0)[..., None]
    seen = np.stack(faces)[depths.argmin(axis=0)]
    truth = np.arccos(np.abs(np.sum(ray * seen, axis=-1)))
    aoi, _ = frame_angle_of_incidence(xyz, 15, max_window=max_window)
    assert np.isfinite(aoi).all()
    # every pixel more than one column off the crease has a window on its own face
    error = np.abs(aoi - truth)
    off = np.abs(np.arange(80) - 39.5) > 1
    assert error[:, off].max() < 1e-6
    assert error[:, ~off].max() < np.deg2rad(20.0)


def test_larger_windows_cut_the_noise_where_the_surface_stays_planar():
    # a 2 cm proud block on a board, 0.45 m away, tilted 30 deg, with 0.9 mm range noise
    offset = np.full((240, 320), 0.45)
    offset[60:180, 80:240] -= 0.02
    normal = [0.0, np.sin(np.deg2rad(30.0)), -np.cos(np.deg2rad(30.0))]
    xyz, _, truth = plane(normal, offset, 240, 320, noise=0.9e-3, seed=3)
    base, _ = frame_angle_of_incidence(xyz, 15)
    grown, _ = frame_angle_of_incidence(xyz, 15, max_window=120)
    np.testing.assert_array_equal(np.isnan(grown), np.isnan(base))  # the same pixels get a normal
    error_base, error_grown = np.rad2deg(np.abs(base - truth)), np.rad2deg(np.abs(grown - truth))
    interior = np.zeros(truth.shape, bool)
    interior[80:160, 110:210] = True  # at least 20 px inside the block
    assert np.nanmedian(error_grown[interior]) < 0.2 * np.nanmedian(error_base[interior])
    assert abs(np.nanmedian(np.rad2deg(grown - truth)[interior])) < 0.05  # no bias
    # next to the block's edges the larger windows never straddle it: no pixel worse than the base's tail
    assert np.nanmax(error_grown) < np.nanpercentile(error_base, 99.9)


@pytest.mark.parametrize("focal", [70.0, 565.0, 1130.0])
def test_depth_jump_does_not_depend_on_the_focal_length(focal):
    # a plane tilted by 60 deg (AOI up to 76 deg at 70 px focal length) is one surface for any focal
    # length; a step twice as deep as a 1 % step beyond an 80 deg slope over one pixel is an edge
    tilt = np.deg2rad(60.0)
    xyz, _, truth = plane([np.sin(tilt), 0.0, -np.cos(tilt)], 0.2, 30, 40, focal=focal)
    aoi, _ = frame_angle_of_incidence(xyz, 9)
    assert np.isfinite(aoi).all()
    offset = np.full((30, 40), 0.5)
    offset[:, 20:] += 2 * 0.5 * (DEFAULT_JUMP + np.tan(np.deg2rad(80.0)) / focal)
    xyz, _, _ = plane([0.0, np.sin(np.deg2rad(20.0)), -np.cos(np.deg2rad(20.0))], offset, 30, 40, focal=focal)
    aoi, _ = frame_angle_of_incidence(xyz, 9)
    assert np.isnan(aoi[:, 19:21]).all() and np.isfinite(aoi[:, :15]).all()


def test_steep_continuous_surface_is_one_surface():
    # a plane at 75 deg AOI: depth changes by ~0.7% per pixel, ~6% across a window; not an edge
    tilt = np.deg2rad(75.0)
    xyz, _, truth = plane([np.sin(tilt), 0.0, -np.cos(tilt)], 0.1, 30, 40)
    aoi, _ = frame_angle_of_incidence(xyz, 9)
    assert np.ptp(xyz[..., 2]) / xyz[..., 2].min() > 0.2
    assert np.isfinite(aoi).all()
    np.testing.assert_allclose(aoi, truth, rtol=0, atol=1e-6)


# (5) invalid pixels and too few points -----------------------------------------------------------


def test_invalid_pixels_are_excluded():
    xyz, _, truth = plane([0.3, 0.1, -1.0], 0.8)
    rng = np.random.default_rng(0)
    invalid = rng.random(xyz.shape[:2]) < 0.15
    garbage = rng.choice([np.nan, np.inf, -1.0, 0.0], size=invalid.sum())
    xyz[invalid, 2] = garbage  # NaN, inf, z < 0, z == 0 are all invalid
    xyz[invalid, :2] = 1e3  # would ruin any plane they entered
    aoi, distance = frame_angle_of_incidence(xyz, 7)
    assert np.isnan(aoi[invalid]).all() and np.isnan(distance[invalid]).all()
    assert np.isfinite(aoi[~invalid]).all()
    np.testing.assert_allclose(aoi[~invalid], truth[~invalid], rtol=0, atol=1e-6)


@pytest.mark.parametrize("max_window", [7, 56])
def test_what_an_invalid_pixel_holds_changes_no_bit(max_window):
    """NaN, inf, z <= 0 or wild x, y at the invalid pixels: the AOI, distance, normals and mixed pixels of NaN there.

    To the bit: the kernels compute over every pixel and clear the invalid ones after.
    """
    xyz, _, _ = plane([0.3, 0.1, -1.0], 0.8, 60, 70, noise=0.9e-3)
    rng = np.random.default_rng(1)
    invalid = rng.random(xyz.shape[:2]) < 0.15
    clean = xyz.copy()
    clean[invalid] = np.nan
    xyz[invalid, 2] = rng.choice([np.nan, np.inf, -1.0, 0.0, -0.0], size=invalid.sum())
    xyz[invalid, :2] = rng.choice([1e3, np.inf, -np.inf, np.nan, 1e150], size=(invalid.sum(), 2))
    for got, expected in zip(
        frame_angle_of_incidence(xyz, 7, max_window=max_window),
        frame_angle_of_incidence(clean, 7, max_window=max_window),
    ):
        assert np.array_equal(got, expected, equal_nan=True)
        assert np.isfinite(got[~invalid]).all()
    assert np.array_equal(
        plane_normals(xyz, 7, max_window=max_window), plane_normals(clean, 7, max_window=max_window), equal_nan=True
    )
    masks = [mixed_pixels(xr.DataArray(cloud[None], dims=("view", "y", "x", "axis"))).values for cloud in (xyz, clean)]
    assert np.array_equal(*masks)


def subset(keep):
    """A 3x3 frame of a plane with only the pixels ``keep`` (list of (row, col)) valid, and the plane's normal."""
    xyz, unit, _ = plane([0.3, 0.1, -1.0], 0.8, 3, 3)
    mask = np.zeros((3, 3), bool)
    mask[tuple(np.transpose(keep))] = True
    return np.where(mask[..., None], xyz, np.nan), mask, unit


@pytest.mark.parametrize("corner", [(slice(0, 40), slice(0, 40)), (slice(-40, None), slice(-40, None))])
def test_an_empty_corner_costs_no_aoi_elsewhere(corner):
    """Growing windows keep every AOI the smallest window gives, whatever lies in the sensor's corners.

    The slopes of the normal gather the windows half a window away; one beyond the border, or empty, adds
    nothing (it once made a NaN of every pixel with such a neighbour: 17 % of this frame with an empty
    top-left corner).
    """
    xyz, _, truth = plane([0.2, -0.1, -1.0], 0.6, 160, 200, noise=0.9e-3, seed=1)
    xyz[corner] = np.nan
    fixed, _ = frame_angle_of_incidence(xyz, 15, max_window=15)
    adaptive, _ = frame_angle_of_incidence(xyz, 15, max_window=120)
    np.testing.assert_array_equal(np.isfinite(adaptive), np.isfinite(fixed))
    assert np.isfinite(fixed).sum() == np.isfinite(xyz[..., 2]).sum()  # every valid pixel has a plane
    error = np.degrees(np.abs(adaptive - truth))[np.isfinite(adaptive)]
    # the grown windows' accuracy (a 15 px window alone: median 0.48 deg, 99 % within 1.9 deg)
    assert np.median(error) < 0.02 and np.percentile(error, 99) < 0.1


@pytest.mark.parametrize("count", [4, 5])
def test_window_needs_min_fraction_of_valid_points(count):
    # window 3 on a 3x3 frame: every pixel's centred or shifted windows hold at most the whole
    # frame; 5 = ceil(0.5 * 9) valid points are needed
    keep = [(0, 0), (0, 2), (2, 1), (1, 1), (2, 2)][:count]
    cloud, mask, unit = subset(keep)
    normals = plane_normals(cloud, 3)
    assert np.isfinite(normals[mask]).all() == (count == 5)
    assert np.isnan(normals[~mask]).all()


@pytest.mark.parametrize(
    "keep,defined",
    [([(0, 0), (2, 1)], False), ([(0, 0), (1, 1), (2, 2)], False), ([(0, 0), (2, 1), (1, 2)], True)],
    ids=["two", "collinear", "three"],
)
def test_three_points_define_a_plane_two_or_collinear_do_not(keep, defined):
    cloud, mask, unit = subset(keep)
    normals = plane_normals(cloud, 3, min_fraction=0.0)
    assert np.isfinite(normals[mask]).all() == defined
    assert np.isnan(normals[~mask]).all()
    if defined:
        np.testing.assert_allclose(normals[mask], np.broadcast_to(unit, (3, 3)), atol=1e-9)


def test_empty_frame_is_all_nan_without_warnings():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        aoi, distance = frame_angle_of_incidence(np.full((10, 12, 3), np.nan, np.float32), 5)
    assert np.isnan(aoi).all() and np.isnan(distance).all()


# (6) float32 input -------------------------------------------------------------------------------


def naive_float32_aoi(xyz, window):
    """What the kernel avoids: raw moments of x/z, y/z, 1/z in float32 integral images. Interior pixels only."""
    height, width, _ = xyz.shape
    x, y, z = np.moveaxis(xyz.astype(np.float32), -1, 0)
    u, v, q = x / z, y / z, 1 / z
    sums = []
    for moment in (np.ones_like(q), u, v, q, u * u, u * v, u * q, v * v, v * q):
        table = np.zeros((height + 1, width + 1), np.float32)
        table[1:, 1:] = moment.cumsum(0, dtype=np.float32).cumsum(1, dtype=np.float32)
        corners = table[window:, window:] + table[:-window, :-window]
        sums.append(corners - table[:-window, window:] - table[window:, :-window])
    count, su, sv, sq, suu, suv, suq, svv, svq = (s.astype(np.float64) for s in sums)
    normal_equations = np.stack([np.stack(row, -1) for row in ((suu, suv, su), (suv, svv, sv), (su, sv, count))], -2)
    normal = np.linalg.solve(normal_equations, np.stack([suq, svq, sq], -1)[..., None])[..., 0]
    half = window // 2
    inner = xyz[half : height - half, half : width - half]
    return np.arccos(
        np.abs(np.sum(normal * inner, axis=-1)) / np.linalg.norm(normal, axis=-1) / np.linalg.norm(inner, axis=-1)
    )


def test_float32_input_equals_float64_input():
    # plane 1 m away with mm noise: the spread of x/z in a window is ~1e-2, its raw second
    # moments summed over the frame ~1e3
    window = 7
    xyz, _, truth = plane([0.2, 0.1, -1.0], 1.0, 240, 320, noise=1e-3)
    single = xyz.astype(np.float32)
    aoi32, _ = frame_angle_of_incidence(single, window)
    aoi64, _ = frame_angle_of_incidence(single.astype(np.float64), window)
    np.testing.assert_array_equal(aoi32, aoi64)
    aoi, _ = frame_angle_of_incidence(xyz, window)
    # what remains is the rounding of the coordinates to float32 (~3e-8 m), not of the sums:
    # ~1e-6 rad, 1e-4 of the noise's effect (most at the border, where windows are smaller)
    difference = np.abs(aoi32 - aoi)
    assert np.median(difference) < 1.5e-6 and difference.max() < 2e-5
    # the scene does tell: float32 moments add errors several times the noise's (they grow with
    # the frame: 2x on 120x160, ~16x on 240x320, singular normal equations on 480x640)
    error = np.median(np.abs(aoi - truth))
    half = window // 2
    naive_error = np.median(np.abs(naive_float32_aoi(xyz, window) - truth[half:-half, half:-half]))
    assert naive_error > 3 * error


@pytest.mark.parametrize("region", [Roi((0, 100), (0, 120)), Roi((13, 71), (7, 99)), Roi((99, 100), (0, 1))])
def test_a_region_of_the_frame_takes_the_whole_frames_values(region):
    # the planes are fitted over the whole frame either way: to the bit, at four levels of windows
    for xyz in (blocks_scene(100, 120), noisy_surface(100, 120, seed=1)):
        whole = frame_angle_of_incidence(xyz, 7, max_window=60)
        part = frame_angle_of_incidence(xyz, 7, max_window=60, region=region)
        for values, inside in zip(whole, part, strict=True):
            np.testing.assert_array_equal(inside, values[region.slices])


# xarray layer, (7) dask ---------------------------------------------------------------------------


def blocks_scene(height, width, seed=0):
    """A tilted wall 0.6 m away with proud and sunken blocks, holes and 0.9 mm noise: edges everywhere."""
    rng = np.random.default_rng(seed)
    offset = np.full((height, width), 0.6)
    for _ in range(12):
        top, left = rng.integers(0, height), rng.integers(0, width)
        offset[top : top + rng.integers(4, 40), left : left + rng.integers(4, 40)] += rng.choice([-0.05, -0.02, 0.03])
    xyz, _, _ = plane([0.2, -0.1, -1.0], offset, height, width, noise=0.9e-3, seed=seed)
    for _ in range(6):
        top, left = rng.integers(0, height), rng.integers(0, width)
        xyz[top : top + rng.integers(2, 12), left : left + rng.integers(2, 12)] = np.nan
    return xyz


def cube(views=2, height=100, width=120, dtype=np.float32):
    """(view, y, x, axis) DataArray: noisy blocks (even views) and noisy curved surfaces with holes (odd)."""
    frames = [
        blocks_scene(height, width, seed=view) if view % 2 == 0 else noisy_surface(height, width, seed=view)
        for view in range(views)
    ]
    coords = {"view": [f"v{i}" for i in range(views)], "y": np.arange(height) + 10, "x": np.arange(width)}
    return xr.DataArray(
        np.stack(frames).astype(dtype), dims=("view", "y", "x", "axis"), coords={**coords, "axis": ["x", "y", "z"]}
    )


def test_dataset_layout_and_attributes():
    xyz = cube()
    ds = angle_of_incidence(xyz, window=7, jump=0.03)
    assert set(ds.data_vars) == {"aoi", "distance"}
    for name in ("aoi", "distance"):
        assert ds[name].dims == ("view", "y", "x") and ds[name].dtype == np.float32
        assert ds[name].attrs["units"] in ("rad", "m") and ds[name].attrs["long_name"]
    assert ds.aoi.attrs["units"] == "rad" and ds.distance.attrs["units"] == "m"
    assert ds.attrs["window"] == 7 and ds.attrs["jump"] == 0.03 and ds.attrs["max_window"] == DEFAULT_MAX_WINDOW
    xr.testing.assert_equal(ds.y, xyz.y)
    assert list(ds.view.values) == ["v0", "v1"]
    expected, distance = frame_angle_of_incidence(xyz.values[1], 7, jump=0.03, max_window=DEFAULT_MAX_WINDOW)
    np.testing.assert_allclose(ds.aoi.values[1], expected, atol=2e-7, rtol=0)
    np.testing.assert_allclose(ds.distance.values[1], distance, rtol=1e-7)
    defaults = angle_of_incidence(xyz).attrs
    assert (defaults["window"], defaults["jump"], defaults["max_window"]) == (
        DEFAULT_WINDOW,
        DEFAULT_JUMP,
        DEFAULT_MAX_WINDOW,
    )


def test_axis_coordinate_order_is_honoured():
    xyz = cube(views=1)
    shuffled = xyz.sel(axis=["z", "x", "y"])
    xr.testing.assert_identical(angle_of_incidence(shuffled, window=7), angle_of_incidence(xyz, window=7))


@pytest.mark.parametrize(
    "chunks,window",
    [
        ({"view": 1, "y": 37, "x": 41}, 7),
        ({"view": 2, "y": 37, "x": 41}, 15),
        ({"view": 1, "y": 23, "x": 120}, 31),  # halo deeper than a chunk: chunks are merged
        ({"view": 1, "y": 100, "x": 50}, 61),
    ],
)
def test_dask_equals_numpy(chunks, window):
    xyz = cube()
    expected = angle_of_incidence(xyz, window=window)

    def no_compute(*args, **kwargs):
        raise AssertionError("angle_of_incidence computed dask input eagerly")

    with dask.config.set(scheduler=no_compute):
        lazy = angle_of_incidence(xyz.chunk(chunks), window=window)
    assert lazy.aoi.chunks is not None
    result = lazy.compute()
    xr.testing.assert_equal(result.aoi.isnull(), expected.aoi.isnull())
    xr.testing.assert_allclose(result, expected, rtol=0, atol=1e-6)
    assert result.attrs == expected.attrs


@settings(max_examples=6, deadline=None)
@given(chunk_y=st.integers(5, 60), chunk_x=st.integers(5, 70), window=st.sampled_from([3, 5, 9]))
def test_dask_equals_numpy_any_chunking(chunk_y, chunk_x, window):
    xyz = cube(views=1, height=60, width=80, dtype=np.float64)
    expected = angle_of_incidence(xyz, window=window)
    result = angle_of_incidence(xyz.chunk({"y": chunk_y, "x": chunk_x}), window=window).compute()
    xr.testing.assert_equal(result.aoi.isnull(), expected.aoi.isnull())
    xr.testing.assert_allclose(result, expected, rtol=0, atol=1e-6)


@pytest.mark.parametrize("window", [2, 1, 0, -3, 4.0, 5.0, "7", True, None])
def test_bad_window_raises(window):
    with pytest.raises(ValueError, match="window must be an odd integer >= 3"):
        angle_of_incidence(cube(views=1), window=window)


@pytest.mark.parametrize("jump", [0, -0.1, np.inf, np.nan, "0.02"])
def test_bad_jump_raises(jump):
    with pytest.raises(ValueError, match="jump must be a positive finite number"):
        angle_of_incidence(cube(views=1), jump=jump)


def test_bad_dims_raise():
    xyz = cube(views=1)
    with pytest.raises(ValueError, match=r"missing \['axis'\]"):
        angle_of_incidence(xyz.rename(axis="component"))
    with pytest.raises(ValueError, match="'x', 'y', 'z'"):
        angle_of_incidence(xyz.assign_coords(axis=["a", "b", "c"]))
    with pytest.raises(ValueError, match="size 3"):
        angle_of_incidence(xyz.drop_vars("axis").isel(axis=[0, 1]))


# (8) mixed (flying) pixels ---------------------------------------------------------------------------


def mixed(xyz, **kwargs):
    """:func:`mixed_pixels` of one frame (H, W, 3): (H, W) bool."""
    return mixed_pixels(xr.DataArray(np.asarray(xyz)[None], dims=("view", "y", "x", "axis")), **kwargs).values[0]


def edge_scene(orientation, tilt, near=0.5, step=0.1, noise=1e-3, seed=0, height=240, width=320):
    """A plane ``near`` m away in front of a parallel one ``step`` m behind, both tilted by ``tilt`` deg about x.

    The foreground holds the pixels left of (``column``), above (``row``) or left of a slanted line
    (``slanted``) through the image centre. Half of its pixels next to the background, drawn at random,
    are made mixed: the point along the ray at ``(1 - w) r_near + w r_far``, w uniform in 0.2-0.8.
    Returns the points with ``noise`` m along each ray, the foreground mask and the mixed mask.
    """
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0:height, 0:width]
    foreground = {
        "column": cols < width // 2,
        "row": rows < height // 2,
        "slanted": cols - width / 2 < 0.4 * (rows - height / 2),
    }[orientation]
    normal = [0.0, np.sin(np.deg2rad(tilt)), -np.cos(np.deg2rad(tilt))]
    front, _, _ = plane(normal, near * np.cos(np.deg2rad(tilt)), height, width)
    back, _, _ = plane(normal, (near + step) * np.cos(np.deg2rad(tilt)), height, width)
    xyz = np.where(foreground[..., None], front, back)
    beside = np.zeros_like(foreground)
    beside[:-1] |= ~foreground[1:]
    beside[1:] |= ~foreground[:-1]
    beside[:, :-1] |= ~foreground[:, 1:]
    beside[:, 1:] |= ~foreground[:, :-1]
    inserted = foreground & beside & (rng.random(foreground.shape) < 0.5)
    weight = rng.uniform(0.2, 0.8, foreground.shape)[..., None]
    xyz = np.where(inserted[..., None], (1 - weight) * front + weight * back, xyz)
    ray = rays(height, width)
    return xyz + ray * rng.normal(0.0, noise, foreground.shape)[..., None], foreground, inserted


def near_pixels(mask):
    """Pixels within one pixel (8-neighbourhood) of ``mask``."""
    near = mask.copy()
    near[1:] |= mask[:-1]
    near[:-1] |= mask[1:]
    near[:, 1:] |= near[:, :-1].copy()
    near[:, :-1] |= near[:, 1:].copy()
    return near


@pytest.mark.parametrize("tilt", [0.0, 35.0])
@pytest.mark.parametrize("orientation", ["column", "row", "slanted"])
def test_inserted_mixed_pixels_are_found_and_true_edges_kept(orientation, tilt):
    found, inserted_total, edge_flagged, edge_total, elsewhere = 0, 0, 0, 0, 0
    for seed in range(3):
        xyz, foreground, inserted = edge_scene(orientation, tilt, seed=seed)
        flagged = mixed(xyz)
        found += flagged[inserted].sum()
        inserted_total += inserted.sum()
        # the pure pixels of either surface at the edge: beside an inserted pixel or the other surface
        boundary = near_pixels(inserted) | near_pixels(foreground) & near_pixels(~foreground)
        edge = boundary & ~inserted
        edge_flagged += flagged[edge].sum()
        edge_total += edge.sum()
        elsewhere += flagged[~boundary].sum()
    assert inserted_total > 300
    assert found / inserted_total >= 0.95  # measured 0.98-1.00
    assert edge_flagged / edge_total < 0.01  # measured 0
    assert elsewhere == 0


@pytest.mark.parametrize("focal", [70.0, 565.0, 1130.0])
def test_mixed_pixels_are_found_down_to_the_stated_split(focal):
    # fronto-parallel planes, a column of pixels between them splitting the step into two equal parts:
    # found when each part exceeds jump / 2 plus the rise of an 80 deg slope over the ray spacing
    limit = DEFAULT_JUMP / 2 + np.tan(np.deg2rad(80.0)) / focal
    for factor, found in ((1.1, True), (0.9, False)):
        log_depth = np.full((20, 30), np.log(0.5))
        log_depth[:, 15] += factor * limit
        log_depth[:, 16:] += 2 * factor * limit
        xyz = rays(20, 30, focal) * np.exp(log_depth)[..., None] / rays(20, 30, focal)[..., 2:]
        flagged = mixed(xyz)
        assert flagged[2:-2, 15].all() == found
        assert not flagged[:, np.r_[0:15, 16:30]].any()


@pytest.mark.parametrize("tilt", [0.0, 20.0, 40.0, 60.0])
def test_clean_planes_have_no_mixed_pixels(tilt):
    # 1 mm range noise at 0.5 m, 480 x 640; at 60 deg tilt about y the AOI reaches 89 deg at the image side
    flagged = 0
    for axis in (0, 1):
        normal = np.zeros(3)
        normal[axis], normal[2] = np.sin(np.deg2rad(tilt)), -np.cos(np.deg2rad(tilt))
        xyz, _, _ = plane(normal, 0.5 * np.cos(np.deg2rad(tilt)), 480, 640, noise=1e-3, seed=axis)
        flagged += mixed(xyz).sum()
    assert flagged / (2 * 480 * 640) < 1e-3  # measured 0


def cylinder(axis, inside=False, radius=0.3, centre=0.8, wall=None, noise=1e-3, height=240, width=320):
    """A cylinder of ``radius`` m, its axis along the image's ``axis`` ("x" or "y") ``centre`` m away.

    Its outside (or ``inside``) is seen; rays that miss it see a wall ``wall`` m away (None: invalid).
    Returns the points with ``noise`` m along each ray, the mask of the cylinder and its true AOI, deg.
    """
    ray = rays(height, width, focal=FOCAL / 3)  # a wide view: the outside is seen up to its silhouettes
    across = 0 if axis == "y" else 1  # the ray component across the axis, besides z
    a = ray[..., across] ** 2 + ray[..., 2] ** 2
    b = -2 * centre * ray[..., 2]
    discriminant = b * b - 4 * a * (centre**2 - radius**2)
    on = discriminant > 0
    root = np.sqrt(np.where(on, discriminant, 0.0))
    distance = (-b + root if inside else -b - root) / (2 * a)
    normal = ray * distance[..., None]
    normal[..., 2] -= centre
    normal[..., 1 - across] = 0.0
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    aoi = np.rad2deg(np.arccos(np.abs(np.sum(normal * ray, axis=-1))))
    if wall is not None:
        distance = np.where(on, distance, wall / ray[..., 2])
    distance = distance + np.random.default_rng(0).normal(0.0, noise, on.shape)
    xyz = ray * distance[..., None]
    if wall is None:
        xyz[~on] = np.nan
    return xyz, on, aoi


@pytest.mark.parametrize("axis", ["x", "y"])
def test_curved_surface_has_no_mixed_pixels(axis):
    # the outside of a cylinder of 0.3 m radius up to its silhouettes (AOI up to 84-89 deg), and an inside
    for kwargs in ({}, {"inside": True, "centre": 0.15}):
        xyz, on, aoi = cylinder(axis, **kwargs)
        assert on.mean() > 0.3
        assert not mixed(xyz).any()
    # in front of a wall, the last pixel before a silhouette, whose footprint straddles it, can look mixed
    # when it sees the cylinder at a grazing angle (measured: flagged at AOI >= 84.8 deg only)
    for centre in (0.6, 0.7, 0.825):  # silhouettes at several sub-pixel positions
        xyz, on, aoi = cylinder(axis, centre=centre, wall=1.5)
        flagged = mixed(xyz)
        assert not flagged[~on].any()
        assert (aoi[on & flagged] > 80.0).all()
        assert not (flagged & ~near_pixels(~on)).any()


def test_a_crease_a_steep_face_and_a_spike_are_not_mixed():
    # a specimen's top and a visible side face (a crease, no depth jump), and a 1 px wide steep face
    ray = rays(40, 80)
    faces = [np.array(normal) / np.linalg.norm(normal) for normal in ([0.3, 0.0, -1.0], [-3.0, 0.0, -1.0])]
    apex = ray[0, 40] * 0.5
    depths = np.stack([(apex @ normal) / (ray @ normal) for normal in faces])
    xyz = ray * depths.min(axis=0)[..., None]
    assert not mixed(xyz).any()
    offset = np.full((40, 80), 0.5)
    offset[:, 41:] += 0.004  # the side face of a 4 mm step: one pixel at ~66 deg between two planes
    xyz, _, _ = plane([0.0, 0.0, -1.0], offset, 40, 80)
    xyz[:, 41] = ray[:, 41] * (0.5 + 0.002) / ray[:, 41, 2:]
    assert not mixed(xyz).any()
    # a spike in front of both its neighbours is no point between two surfaces
    xyz, _, _ = plane([0.2, 0.1, -1.0], 0.5, 40, 80)
    xyz[20, 30] *= 0.9
    assert not mixed(xyz).any()


def test_mixed_pixels_layout_invalid_pixels_and_dask():
    xyz = cube(views=2, height=100, width=120)
    frame, _, inserted = edge_scene("slanted", 20.0, height=100, width=120)
    xyz[0] = frame.astype(np.float32)
    xyz[0, 10:14, 60:64] = np.nan  # holes near the edge leave their neighbours undecided, never mixed
    flagged = mixed_pixels(xyz)
    assert flagged.dims == ("view", "y", "x") and flagged.dtype == bool and flagged.name == "mixed"
    assert flagged.attrs["jump"] == DEFAULT_JUMP and flagged.attrs["long_name"]
    xr.testing.assert_equal(flagged.y, xyz.y)
    assert not flagged.values[xyz.isnull().any("axis").values].any()
    assert flagged[0].values[inserted & np.isfinite(xyz.values[0]).all(-1)].mean() > 0.9
    np.testing.assert_array_equal(flagged.values[1], mixed(xyz.values[1]))
    for chunks in ({"view": 1, "y": 37, "x": 41}, {"view": 2, "y": 5, "x": 3}, {"y": 99, "x": 119}):
        lazy = mixed_pixels(xyz.chunk(chunks))
        assert lazy.chunks is not None
        xr.testing.assert_identical(lazy.compute(), flagged)


def test_mixed_pixels_bad_input_raises():
    with pytest.raises(ValueError, match="jump must be a positive finite number"):
        mixed_pixels(cube(views=1), jump=0)
    with pytest.raises(ValueError, match=r"missing \['axis'\]"):
        mixed_pixels(cube(views=1).rename(axis="component"))
    with pytest.raises(TypeError, match="DataArray"):
        mixed_pixels(cube(views=1).values)


def step_ingest():
    """An ingest cube of two views: a step with inserted mixed pixels, and a noisy surface with holes."""
    xyz = cube(views=2, height=100, width=120)
    frame, _, inserted = edge_scene("column", 20.0, height=100, width=120)
    xyz[0] = frame.astype(np.float32)
    intensity = xr.full_like(xyz.isel(axis=0, drop=True), 500.0)
    return xr.Dataset({"xyz": xyz, "intensity": intensity, "valid": xyz.notnull().all("axis")}), inserted


def test_aoi_stage_drops_mixed_pixels_and_counts_them():
    ingest, inserted = step_ingest()
    flagged = mixed_pixels(ingest["xyz"])
    ds = aoi_stage(ingest, window=7)
    assert ds.attrs["mixed_pixels"] == {"v0": int(flagged[0].sum()), "v1": 0}
    assert flagged[0].values[inserted].mean() >= 0.95
    for name in ("aoi", "distance"):
        assert ds[name].where(flagged).isnull().all()
    # the same as the AOI of the clouds without them; a view without any is unchanged
    expected = angle_of_incidence(ingest["xyz"].where(~flagged), window=7)
    xr.testing.assert_identical(ds.drop_attrs(), expected.drop_attrs())
    xr.testing.assert_identical(
        ds.isel(view=1).drop_attrs(), angle_of_incidence(ingest["xyz"], window=7).isel(view=1).drop_attrs()
    )
    # the reflectance drops them too
    coef = xr.DataArray(
        np.broadcast_to(np.array([0.3, 1.0, -0.25, 0.05, 1.0])[:, None, None], (5, 100, 120)),
        dims=("term", "y", "x"),
        coords={"term": list(TERMS), "y": ingest.y, "x": ingest.x},
    )
    noise_model = {"noise_variance": ("bin", [4.0, 9.0]), "noise_intensity": ("bin", [100.0, 1000.0])}
    calibration = xr.Dataset({"coef": coef, **noise_model}, attrs={"scale_k": 1.0})
    out = reflectance_stage(ingest, ds, calibration)
    reflectance = out["reflectance"]
    assert reflectance.where(flagged).isnull().all()
    assert reflectance.notnull().sum() == ds["aoi"].notnull().sum()
    # its noise too: exactly where the reflectance is, though the mixed pixels are valid
    assert ingest["valid"].where(flagged, False).any()
    np.testing.assert_array_equal(out["reflectance_noise"].isnull(), reflectance.isnull())


def test_tiny_preset_has_almost_no_mixed_pixels(tiny_campaign):
    campaign = surffin.read_campaign(tiny_campaign)
    flagged = valid = 0
    for name in campaign.items:
        xyz = ingest_item(campaign, name)["xyz"]
        flagged += int(mixed_pixels(xyz).sum())
        valid += int(xyz.notnull().all("axis").sum())
    assert valid > 30_000
    assert flagged <= 5  # measured 0 of 35,750


@pytest.mark.slow
def test_paper_preset_has_almost_no_mixed_pixels(tmp_path):
    # the paper's camera and items (its calibration set cut to two views: it plays no part here)
    preset = replace(PRESETS["paper"], wall_distances=(0.5, 0.8), wall_tilts=(0.0,), repeat_calibration=False)
    campaign = surffin.read_campaign(surffin.simulate_campaign(tmp_path / "raw", preset, 0))
    flagged = []
    for name in campaign.items:
        flagged.extend(mixed_pixels(ingest_item(campaign, name)["xyz"]).sum(("y", "x")).values.tolist())
    assert len(flagged) == 25
    assert sum(flagged) <= 20 and max(flagged) <= 5  # measured 1 of 3.8 million (a noisy pixel at a step)


@pytest.mark.parametrize("shape", [(1, 7), (2, 2), (3, 9), (6, 5), (9, 4)])
def test_edges_and_mixed_pixels_are_the_same_on_the_transposed_frame(shape):
    """Rows and columns play the same part: the edge test (the AOI's NaN) and the mixed pixels of a frame and of
    its transpose (x and y swapped) agree, on frames of every aspect, however thin."""
    rng = np.random.default_rng(sum(shape))
    found = 0
    for _ in range(40):
        depth = 0.5 + 0.02 * rng.integers(0, 3, shape)
        xyz = rays(*shape) * (depth / rays(*shape)[..., 2])[..., None]
        xyz[rng.random(shape) < 0.1] = np.nan
        swapped = np.ascontiguousarray(xyz.transpose(1, 0, 2)[..., [1, 0, 2]])
        flagged = mixed(xyz)
        np.testing.assert_array_equal(mixed(swapped), flagged.T)
        aoi, _ = frame_angle_of_incidence(xyz, 3)
        np.testing.assert_array_equal(np.isnan(frame_angle_of_incidence(swapped, 3)[0]), np.isnan(aoi).T)
        found += flagged.sum()
    assert found > 0 or min(shape) < 3
