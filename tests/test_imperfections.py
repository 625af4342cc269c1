"""The simulator's real-camera imperfections: each present in the files when on, absent when off.

Every check reads the written campaign back and compares it with an independent reference: OpenCV's
projection, the truth stores, the view reader, a least-squares fit of eq. 5.
"""

import argparse
import dataclasses
import json

import cv2
import numpy as np
import pytest
import scipy.optimize
import yaml

import surffin
from surffin.io.store import open_store
from surffin.io.viewfile import read_settings
from surffin.simulate import (
    IMPERFECT,
    PRESETS,
    STANDARD,
    VALIDATION,
    Imperfections,
    PinholeCamera,
    cli_parser,
    cli_run,
    distort,
    named_imperfections,
    undistort,
)

# The tiny preset without noise or dropouts (so that files differ only by the imperfections),
# without the repeat calibration, with fewer specimen and scene views.
QUIET = dataclasses.replace(
    PRESETS["tiny"],
    name="quiet",
    intensity_noise=0.0,
    intensity_noise_max=0.0,
    depth_noise=0.0,
    dropout=0.0,
    repeat_calibration=False,
    wall_tilts=(0.0, 15.0, 30.0),
    specimen_tilts=(0.0, 30.0),
    scene_tilts=(5.0, 35.0),
)
DISTORTION = (-0.12, 0.05, 0.001, -0.002, 0.01)
POSE_ERROR = (2.0, 0.5)
SATURATION = 2000.0
SETTINGS = (("exposure_us", 250), ("gain", "low"))
SYSTEMATICS = 0.03
SIGNED_SCALE = 0.1
IMPERFECT_CAMERA = Imperfections(
    distortion=DISTORTION,
    pose_error=POSE_ERROR,
    mixed_pixels=True,
    saturation=SATURATION,
    settings=SETTINGS,
    match_settings=True,
)


def simulate(tmp_path_factory, name, **kwargs):
    root = tmp_path_factory.mktemp(name)
    path = surffin.simulate_campaign(root / "campaign", QUIET, 0, **kwargs)
    return surffin.read_campaign(path.parent), root / "campaign-truth"


@pytest.fixture(scope="module")
def ideal(tmp_path_factory):
    return simulate(tmp_path_factory, "ideal")


@pytest.fixture(scope="module")
def imperfect(tmp_path_factory):
    return simulate(tmp_path_factory, "imperfect", imperfections=IMPERFECT_CAMERA)


def camera_yaml(camp):
    return yaml.safe_load(camp.path.read_text())["camera"]


def all_views(camp):
    return [
        *camp.calibration.wall,
        *camp.calibration.reference.views,
        *(v for i in camp.items.values() for v in i.views),
    ]


def reference_views(camp, truth):
    """(view, truth store) of every item's reference view."""
    for name, item in camp.items.items():
        store = open_store(truth / f"{name}.zarr").compute()
        yield camp.read_view(item.views[store["view"].values.tolist().index(store.attrs["reference_view"])]), store


def matrix(camera: PinholeCamera):
    return np.array([[camera.fx, 0, camera.cx], [0, camera.fy, camera.cy], [0, 0, 1]], dtype=np.float64)


def opencv_pixels(xyz, camera, distortion):
    """Project camera-frame points (N, 3) with cv2.projectPoints: (N, 2) columns, rows."""
    projected, _ = cv2.projectPoints(
        xyz.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), matrix(camera), np.array(distortion)
    )
    return projected.reshape(-1, 2)


# --- lens distortion -----------------------------------------------------------------------------


def test_lens_model_is_opencvs_and_undistort_inverts_it():
    camera = PinholeCamera(640, 480, 565.0, 579.0, DISTORTION)
    rng = np.random.default_rng(0)
    points = np.column_stack([rng.uniform(-0.6, 0.6, 500), rng.uniform(-0.45, 0.45, 500), rng.uniform(0.5, 1.5, 500)])
    points[:, :2] *= points[:, 2:]
    for coefficients in (DISTORTION[:4], DISTORTION, (*DISTORTION, 0.02, -0.01, 0.005)):
        u, v = dataclasses.replace(camera, distortion=coefficients).project(points)
        np.testing.assert_allclose(np.column_stack([u, v]), opencv_pixels(points, camera, coefficients), atol=1e-9)
        x, y = points[:, 0] / points[:, 2], points[:, 1] / points[:, 2]
        np.testing.assert_allclose(undistort(*distort(x, y, coefficients), coefficients), (x, y), atol=1e-12)
    # OpenCV's own inverse (a few fixed-point iterations) agrees with the rays
    pixels = np.stack(np.meshgrid(np.arange(0, 640, 37.0), np.arange(0, 480, 29.0)), axis=-1).reshape(-1, 1, 2)
    theirs = cv2.undistortPoints(pixels, matrix(camera), np.array(DISTORTION)).reshape(-1, 2)
    rays = camera.rays()[pixels[:, 0, 1].astype(int), pixels[:, 0, 0].astype(int)]
    np.testing.assert_allclose(rays[:, :2] / rays[:, 2:], theirs, atol=1e-6)


def test_distorted_points_project_onto_their_pixel_with_the_true_distortion(ideal, imperfect):
    for (camp, truth), distortion in ((imperfect, DISTORTION), (ideal, (0.0,) * 5)):
        for view, _ in reference_views(camp, truth):
            rows, cols = np.nonzero(view.valid)
            pixels = opencv_pixels(view.xyz[rows, cols], QUIET.camera, distortion)
            np.testing.assert_allclose(pixels, np.column_stack([cols, rows]), atol=1e-3)
    # the ideal camera's points miss their pixels through the distortion: it is measurably there
    view, _ = next(reference_views(*ideal))
    rows, cols = np.nonzero(view.valid)
    pixels = opencv_pixels(view.xyz[rows, cols], QUIET.camera, DISTORTION)
    assert np.abs(pixels - np.column_stack([cols, rows])).max() > 1.0
    assert camera_yaml(imperfect[0])["intrinsics"]["distortion"] == list(DISTORTION)
    assert "distortion" not in camera_yaml(ideal[0])["intrinsics"]
    assert imperfect[0].camera.distortion == DISTORTION


@pytest.mark.parametrize(("intrinsics", "written"), [("pinhole", {"fx", "fy", "cx", "cy"}), ("none", None)])
def test_intrinsics_may_hide_the_distortion_or_be_left_out(tmp_path_factory, intrinsics, written):
    imperfections = Imperfections(distortion=DISTORTION, intrinsics=intrinsics)
    camp, _ = simulate(tmp_path_factory, f"intrinsics-{intrinsics}", imperfections=imperfections)
    entry = camera_yaml(camp).get("intrinsics")
    assert (None if entry is None else set(entry)) == written
    assert camp.camera.distortion is None


# --- pose error ----------------------------------------------------------------------------------


def rotation_degrees(first, second):
    cosine = (np.trace(first[:3, :3].T @ second[:3, :3]) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))


def test_recorded_poses_are_off_by_the_asked_translation_and_rotation(ideal, imperfect):
    for (camp, truth), error in ((imperfect, POSE_ERROR), (ideal, (0.0, 0.0))):
        directions = []
        for name, item in camp.items.items():
            true_poses = open_store(truth / f"{name}.zarr")["pose"].values
            for path, true in zip(item.views, true_poses, strict=True):
                recorded = camp.read_view(path).pose
                shift = recorded[:3, 3] - true[:3, 3]
                assert np.linalg.norm(shift) * 1000 == pytest.approx(error[0], abs=1e-9)
                assert rotation_degrees(true, recorded) == pytest.approx(error[1], abs=1e-5)
                directions.append(shift)
        if error[0]:  # a direction of its own per view
            assert len({tuple(np.round(d, 9)) for d in directions}) == len(directions)


def test_truth_keeps_the_true_poses(imperfect, ideal):
    for name in imperfect[0].items:
        np.testing.assert_array_equal(
            open_store(imperfect[1] / f"{name}.zarr")["pose"].values,
            open_store(ideal[1] / f"{name}.zarr")["pose"].values,
        )


# --- mixed pixels --------------------------------------------------------------------------------


def neighbours(array, fill):
    padded = np.pad(array, 1, constant_values=fill)
    height, width = array.shape
    return [padded[1 + dy : 1 + dy + height, 1 + dx : 1 + dx + width] for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1))]


def test_mixed_pixels_lie_between_the_surfaces_and_only_at_depth_edges(ideal, imperfect):
    counts = {}
    for label, (camp, truth) in (("imperfect", imperfect), ("ideal", ideal)):
        counts[label] = 0
        for view, store in reference_views(camp, truth):
            true = store["distance"].values
            surface = store["surface"].values
            measured = np.linalg.norm(view.xyz, axis=-1)
            moved = view.valid & (np.abs(measured - true) > 1e-6)
            between = np.zeros_like(moved)
            for other, other_surface in zip(neighbours(true, np.nan), neighbours(surface, -1), strict=True):
                edge = (other_surface != surface) & (other_surface >= 0) & (np.abs(other - true) > 0.002)
                low, high = np.fmin(true, other), np.fmax(true, other)
                between |= edge & (measured > low) & (measured < high)
            assert (between[moved]).all(), label  # every moved range lies between its surface and one across an edge
            counts[label] += int(moved.sum())
    assert counts["imperfect"] > 50 and counts["ideal"] == 0


# --- saturation ----------------------------------------------------------------------------------


def test_intensities_clip_at_the_saturation(ideal, imperfect):
    highest = {}
    for label, (camp, _) in (("imperfect", imperfect), ("ideal", ideal)):
        intensities = np.concatenate([camp.read_view(path).intensity.ravel() for path in all_views(camp)])
        highest[label] = (intensities.max(), int((intensities == SATURATION).sum()))
    assert highest["imperfect"][0] == SATURATION and highest["imperfect"][1] > 100
    assert highest["ideal"][0] > 1.1 * SATURATION and highest["ideal"][1] == 0
    assert camera_yaml(imperfect[0])["saturation"] == SATURATION and imperfect[0].camera.saturation == SATURATION
    assert "saturation" not in camera_yaml(ideal[0])


# --- settings sidecars ---------------------------------------------------------------------------


def test_settings_sidecars_and_match_settings(ideal, imperfect):
    camp = imperfect[0]
    for path in all_views(camp):
        assert read_settings(path) == dict(SETTINGS)
        assert camp.read_view(path).settings == dict(SETTINGS)
    assert camera_yaml(camp)["match_settings"] == [name for name, _ in SETTINGS]
    assert camp.camera.match_settings == ("exposure_us", "gain")
    assert not list(ideal[0].root.rglob("*.meta.json")) and "match_settings" not in camera_yaml(ideal[0])


# --- residual instrument systematics -------------------------------------------------------------


def wall_samples(camp):
    """Per wall view: intensity, distance (m) and angle of incidence (rad) from the files (wall normal -Z)."""
    for path in camp.calibration.wall:
        view = camp.read_view(path)
        distance = np.linalg.norm(view.xyz, axis=-1)
        normal = view.pose[:3, :3].T @ np.array([0.0, 0.0, -1.0])
        aoi = np.arccos(np.clip(np.abs(view.xyz @ normal) / distance, 0.0, 1.0))
        yield view, distance, aoi


def eq5_residual(distance, aoi, target):
    """RMS relative residual of the best ``(A + B/d^2)(C theta^2 + D theta + 1)`` fit to ``target``."""

    def residual(p):
        return (p[0] + p[1] / distance**2) * (p[2] * aoi**2 + p[3] * aoi + 1.0) / target - 1.0

    start = np.array([np.mean(target), 0.0, 0.0, 0.0])
    fit = scipy.optimize.least_squares(residual, start, x_scale="jac", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    return float(np.sqrt(np.mean(fit.fun**2)))


def test_systematics_change_the_intensity_by_the_asked_amount_outside_eq5(tmp_path_factory, ideal):
    systematic, _ = simulate(tmp_path_factory, "systematics", imperfections=Imperfections(systematics=SYSTEMATICS))
    ratios, distances, angles = [], [], []
    for (view, distance, aoi), (other, _, _) in zip(wall_samples(systematic), wall_samples(ideal[0]), strict=True):
        both = view.valid & other.valid
        np.testing.assert_array_equal(view.xyz[both], other.xyz[both])  # the geometry is untouched
        ratios.append(np.where(both, view.intensity, np.nan) / np.where(both, other.intensity, np.nan))
        distances.append(distance)
        angles.append(aoi)
        assert both.mean() > 0.9
    ratio, distance, aoi = (np.stack(arrays) for arrays in (ratios, distances, angles))
    deviation = np.abs(ratio - 1.0)
    assert 0.9 * SYSTEMATICS < np.nanmax(deviation) <= SYSTEMATICS * 1.0001
    assert np.nanmedian(deviation) > 0.2 * SYSTEMATICS
    # per pixel, over the wall views: eq. 5 fits its own form exactly, but not the systematics
    residuals, controls = [], []
    for row, column in ((15, 20), (30, 40), (45, 60), (20, 55)):
        d, theta, target = distance[:, row, column], aoi[:, row, column], ratio[:, row, column]
        ok = np.isfinite(target)
        residuals.append(eq5_residual(d[ok], theta[ok], target[ok]))
        controls.append(eq5_residual(d[ok], theta[ok], (0.3 + 1.0 / d[ok] ** 2) * (-0.25 * theta[ok] ** 2 + 1.0)))
    assert max(controls) < 1e-8
    assert min(residuals) > 0.1 * SYSTEMATICS, residuals


# --- signed raw files ----------------------------------------------------------------------------


def test_signed_raw_files_read_back_as_the_npz_render(tmp_path_factory, ideal):
    imperfections = Imperfections(signed_raw=SIGNED_SCALE)
    signed, _ = simulate(tmp_path_factory, "signed", fmt="raw", units="mm", imperfections=imperfections)
    assert camera_yaml(signed)["abcy16"] == {"signed": True, "scale": SIGNED_SCALE}
    for path, other in zip(all_views(signed), all_views(ideal[0]), strict=True):
        view, reference = signed.read_view(path), ideal[0].read_view(other)
        np.testing.assert_array_equal(view.valid, reference.valid)
        valid = view.valid
        np.testing.assert_allclose(view.xyz[valid], reference.xyz[valid], rtol=0, atol=SIGNED_SCALE / 2000 + 1e-7)
        np.testing.assert_allclose(view.intensity[valid], reference.intensity[valid], rtol=0, atol=0.5)
        # the buffer itself: int16 A, B, C = round(mm / scale), -32768 on invalid pixels
        channels = np.fromfile(path, dtype="<i2").reshape(*QUIET.camera.shape, 4)
        np.testing.assert_array_equal(channels[~valid][:, :3], -32768)
        codes = np.rint(reference.xyz[valid] * 1000 / SIGNED_SCALE)
        assert np.abs(channels[valid][:, :3] - codes).max() <= 1
    with pytest.raises(ValueError, match="signed raw files need fmt"):
        surffin.simulate_campaign(tmp_path_factory.mktemp("npz") / "c", QUIET, imperfections=imperfections)


# --- names, the command line and the validation campaigns ----------------------------------------


def test_named_imperfections():
    every = named_imperfections("all")
    assert every.distortion[:2] == (-0.12, 0.05) and every.intrinsics == "pinhole"
    assert every.pose_error == (1.0, 0.2) and every.mixed_pixels and every.systematics == 0.03
    assert every.saturation is None and not every.settings and every.signed_raw is None
    assert named_imperfections("pose, mixed") == Imperfections(pose_error=(1.0, 0.2), mixed_pixels=True)
    assert not Imperfections().any and named_imperfections("settings").any
    with pytest.raises(ValueError, match="not known"):
        named_imperfections("pose,blur")
    with pytest.raises(ValueError, match="intrinsics"):
        named_imperfections("distortion,unknown-distortion")
    with pytest.raises(ValueError, match="match_settings needs settings"):
        Imperfections(match_settings=True)


def test_cli_passes_the_imperfections(monkeypatch, tmp_path):
    calls = []

    def record(directory, preset, seed, **options):
        calls.append((preset.name, options["imperfections"], options["fmt"]))
        return tmp_path / "campaign.yaml"

    monkeypatch.setattr("surffin.simulate.acquire.simulate_campaign", record)
    parser = argparse.ArgumentParser()
    cli_parser(parser)
    for argv in (
        ["--imperfections", "pose,mixed"],
        ["--validation", "val-all"],
        ["--validation", "val-all", "--imperfections", "none"],
    ):
        assert cli_run(parser.parse_args([str(tmp_path / "c"), *argv])) == 0
    assert calls == [
        ("paper", named_imperfections("pose,mixed"), "npz"),
        ("val-all", named_imperfections("all"), "npz"),
        ("val-all", Imperfections(), "npz"),
    ]
    with pytest.raises(SystemExit):
        parser.parse_args([str(tmp_path / "c"), "--imperfections", "blur"])


def test_validation_campaigns_render_each_imperfection_alone_and_all_together():
    assert set(IMPERFECT) <= set(VALIDATION)
    imperfections = {name: VALIDATION[name].imperfections for name in IMPERFECT}
    assert all(value.any for value in imperfections.values())
    assert imperfections["val-all"] == named_imperfections("all")
    for name in ("distortion", "pose", "mixed", "saturation", "systematics"):
        assert named_imperfections(name) in imperfections.values(), name
    bare = VALIDATION["val-bare-raw"]
    assert bare.fmt == "raw" and not bare.poses and bare.imperfections.intrinsics == "none"
    assert VALIDATION["val-signed-raw"].fmt == "raw" and VALIDATION["val-signed-raw"].imperfections.signed_raw
    assert {"distortion", "all"} <= set(STANDARD)


def test_settings_alone_leave_the_view_files_byte_identical(tmp_path_factory, ideal):
    camp, _ = simulate(tmp_path_factory, "settings", imperfections=Imperfections(settings=SETTINGS))
    for path, other in zip(all_views(camp), all_views(ideal[0]), strict=True):
        assert path.read_bytes() == other.read_bytes()
        assert json.loads(path.with_name(path.stem + ".meta.json").read_text()) == dict(SETTINGS)
