import argparse
import dataclasses
import filecmp

import numpy as np
import pytest
import xarray as xr

import surffin
from surffin.cli import main
from surffin.errors import CampaignError
from surffin.simulate import (
    PRESETS,
    PinholeCamera,
    Material,
    Scene,
    Texture,
    box_faces,
    cli_parser,
    cli_run,
    draw_instrument,
    keyed_rng,
    look_at_pose,
    observe,
    render,
)

TINY = PRESETS["tiny"]
NOISE_FREE = dataclasses.replace(TINY, depth_noise=0.0, intensity_noise=0.0, dropout=0.0)


def simulate(tmp_path_factory, name, preset=TINY, **kwargs):
    root = tmp_path_factory.mktemp(name)
    path = surffin.simulate_campaign(root / "campaign", preset, **kwargs)
    return path.parent, root / "campaign-truth"


@pytest.fixture(scope="module")
def noisy(tmp_path_factory):
    return simulate(tmp_path_factory, "noisy")


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    return simulate(tmp_path_factory, "clean", NOISE_FREE)


def truth_of(truth, item):
    return xr.open_zarr(truth / f"{item}.zarr").compute()


def read(campaign_dir, item, index):
    camp = surffin.read_campaign(campaign_dir)
    return camp.read_view(camp.items[item].views[index])


def same_tree(left, right):
    compared = filecmp.dircmp(left, right)
    assert not (compared.left_only or compared.right_only or compared.funny_files)
    _, mismatch, errors = filecmp.cmpfiles(left, right, compared.common_files, shallow=False)
    assert not mismatch and not errors, mismatch
    for sub in compared.common_dirs:
        same_tree(left / sub, right / sub)


# --- determinism -----------------------------------------------------------------------------


def test_same_seed_gives_identical_files(tmp_path_factory, noisy):
    again = simulate(tmp_path_factory, "again")
    same_tree(noisy[0], again[0])
    same_tree(noisy[1], again[1])


def test_other_seed_gives_other_data(tmp_path_factory, noisy):
    other, other_truth = simulate(tmp_path_factory, "other", seed=1)
    first, second = read(noisy[0], "S1", 0), read(other, "S1", 0)
    assert not np.array_equal(first.intensity, second.intensity)
    assert not np.allclose(truth_of(noisy[1], "S1").R0, truth_of(other_truth, "S1").R0, equal_nan=True)


def test_views_do_not_depend_on_the_other_views(tmp_path_factory, noisy):
    # fewer wall views, same seed: the specimens' files are byte-identical
    fewer, _ = simulate(tmp_path_factory, "fewer", dataclasses.replace(TINY, wall_distances=(0.4,)))
    assert len(list((fewer / "calibration/wall").glob("*.npz"))) == len(TINY.wall_tilts)
    same_tree(noisy[0] / "specimens", fewer / "specimens")


# --- geometry --------------------------------------------------------------------------------


def test_points_project_onto_their_own_pixel(clean):
    camera = TINY.camera
    scene = Scene(box_faces("S", (0.0, 0.0), 0.1, 0.01, 0.3, TINY.specimens[0].material, 0), seed=0)
    pose = look_at_pose((0.0, 0.0, -0.01), 0.3, np.deg2rad(25.0), 1.0, np.deg2rad(3.0))
    instrument = draw_instrument(camera, TINY.coef_mean, TINY.coef_variability, TINY.gain, keyed_rng(0, "i"))
    xyz, _ = observe(render(scene, camera, pose), instrument, NOISE_FREE, keyed_rng(0, "v"))
    rows, cols = np.indices(camera.shape)
    u, v = camera.project(xyz)
    ok = np.isfinite(u)
    assert ok.sum() > 300
    np.testing.assert_allclose(u[ok], cols[ok], rtol=0, atol=1e-6)
    np.testing.assert_allclose(v[ok], rows[ok], rtol=0, atol=1e-6)
    # through a view file (xyz stored as float32)
    view = read(clean[0], "T1", 1)
    u, v = camera.project(view.xyz)
    np.testing.assert_allclose(u[view.valid], cols[view.valid], rtol=0, atol=1e-4)
    np.testing.assert_allclose(v[view.valid], rows[view.valid], rtol=0, atol=1e-4)


def test_look_at_pose_places_the_camera():
    target = np.array([0.1, -0.2, 0.0])
    tilt, azimuth = np.deg2rad(30.0), np.deg2rad(60.0)
    pose = look_at_pose(target, 0.5, tilt, azimuth, np.deg2rad(4.0))
    np.testing.assert_allclose(pose[:3, :3] @ pose[:3, :3].T, np.eye(3), atol=1e-12)
    assert np.linalg.det(pose[:3, :3]) == pytest.approx(1.0)
    expected = target + 0.5 * np.array([np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth), -np.cos(tilt)])
    np.testing.assert_allclose(pose[:3, 3], expected, atol=1e-12)
    np.testing.assert_allclose(pose[:3, 2], (target - expected) / 0.5, atol=1e-12)  # optical axis at target
    assert np.degrees(np.arccos(pose[2, 2])) == pytest.approx(30.0)  # tilt from the wall normal
    assert pose[1, 1] > 0.8  # image y roughly along world +Y
    fronto = look_at_pose(target, 0.5, 0.0, 0.0)
    np.testing.assert_allclose(fronto[:3, :3], np.eye(3), atol=1e-12)  # image x, y along world X, Y


def test_aoi_matches_an_independent_plane_fit(clean):
    truth = truth_of(clean[1], "S2")
    top = truth.surface.attrs["surfaces"].index("S2.top")
    for index in range(len(TINY.specimen_tilts)):
        view = read(clean[0], "S2", index)
        # top-face pixels of this view: those that map into the reference view's top face
        u = truth.u_ref[index].values
        v = truth.v_ref[index].values
        seen = np.isfinite(u) & view.valid
        on_top = np.zeros_like(seen)
        on_top[seen] = truth.surface.values[np.rint(v[seen]).astype(int), np.rint(u[seen]).astype(int)] == top
        on_top &= truth.edge_distance.values[
            np.rint(np.nan_to_num(v)).astype(int), np.rint(np.nan_to_num(u)).astype(int)
        ] > 0.01
        points = view.xyz[on_top]
        assert len(points) > 100
        centred = points - points.mean(axis=0)
        normal = np.linalg.svd(centred, full_matrices=False)[2][-1]
        rays = points / np.linalg.norm(points, axis=1, keepdims=True)
        expected = np.arccos(np.abs(rays @ normal))
        np.testing.assert_allclose(truth.aoi_view[index].values[on_top], expected, rtol=0, atol=2e-5)
    assert truth.aoi_view.max() > np.deg2rad(max(TINY.specimen_tilts) - 10)


def test_reference_coordinates_follow_the_poses(clean):
    camera = TINY.camera
    truth = truth_of(clean[1], "T1")
    rows, cols = np.indices(camera.shape)
    np.testing.assert_allclose(truth.u_ref[0].values, cols, atol=1e-9)
    np.testing.assert_allclose(truth.v_ref[0].values, rows, atol=1e-9)
    reference_pose = truth.pose[0].values
    for index in range(1, len(TINY.scene_tilts)):
        view = read(clean[0], "T1", index)
        np.testing.assert_allclose(view.pose, truth.pose[index].values, atol=1e-12)
        world = view.xyz @ view.pose[:3, :3].T + view.pose[:3, 3]
        local = (world - reference_pose[:3, 3]) @ reference_pose[:3, :3]
        u, v = camera.project(local)
        known = np.isfinite(truth.u_ref[index].values)
        assert 0.2 < known.mean() < 1.0  # some of the scene is hidden or outside the reference view
        np.testing.assert_allclose(u[known & view.valid], truth.u_ref[index].values[known & view.valid], atol=1e-3)
        np.testing.assert_allclose(v[known & view.valid], truth.v_ref[index].values[known & view.valid], atol=1e-3)


def test_texture_turns_with_the_specimen():
    camera = PinholeCamera(width=64, height=64, fx=70.0, fy=70.0)
    material = Material("grainy", 0.8, 1.2, R0_texture=(Texture(0.2, 0.003, 0.25),), n_texture=(Texture(0.1, 0.003, 0.25),))
    pose = look_at_pose((0.2, 0.1, -0.01), 0.3, 0.0, 0.0)
    maps = {}
    for quarter in (0, 1):
        faces = box_faces("S", (0.2, 0.1), 0.2, 0.01, quarter * np.pi / 2, material, 0)
        maps[quarter] = render(Scene(faces, seed=3), camera, pose)
    top = (maps[0].label == 0) & (maps[0].edge_distance > 1e-6) & (np.rot90(maps[1].label, 1) == 0)
    assert top.sum() > 1000
    for name in ("R0", "n"):
        unturned, turned = getattr(maps[0], name), getattr(maps[1], name)
        # a quarter turn from world X towards world Y turns the image the same way
        np.testing.assert_allclose(np.rot90(turned, 1)[top], unturned[top], rtol=1e-9)
        assert not np.allclose(turned[top], unturned[top], rtol=1e-3)


# --- radiometry ------------------------------------------------------------------------------


def instrument_function(coef, distance, aoi):
    return (coef[0] + coef[1] / distance**2) * (coef[2] * aoi**2 + coef[3] * aoi + coef[4])


@pytest.mark.parametrize("item", ["S3", "T1"])
def test_noise_free_intensity_is_scale_k_f_R(clean, item):
    instrument = xr.open_zarr(clean[1] / "instrument.zarr").compute()
    truth = truth_of(clean[1], item)
    view = read(clean[0], item, 0)
    valid = view.valid
    assert valid.mean() > 0.95
    R = truth.R0.values * np.cos((2 - 1 / truth.n.values) * truth.aoi.values) ** truth.n.values
    f = instrument_function(instrument.coef.values, truth.distance.values, truth.aoi.values)
    expected = instrument.attrs["scale_k"] * f * R
    np.testing.assert_allclose(view.intensity[valid], expected[valid], rtol=1e-6)
    # and the raw, un-normalised instrument gives the same intensity
    raw = instrument.attrs["gain"] * instrument_function(instrument.coef_raw.values, truth.distance.values, truth.aoi.values)
    np.testing.assert_allclose(view.intensity[valid], (raw * R)[valid], rtol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(view.xyz[valid], axis=-1), truth.distance.values[valid], rtol=1e-6)


def test_instrument_truth_gauge_and_variability(clean):
    instrument = xr.open_zarr(clean[1] / "instrument.zarr").compute()
    coef, raw = instrument.coef.values, instrument.coef_raw.values
    assert instrument.attrs["scale_k"] == pytest.approx(1 / TINY.wall.R0)
    np.testing.assert_array_equal(coef[4], 1.0)
    level = instrument.attrs["gain"] * instrument.attrs["rho_wall"] * raw[4]
    np.testing.assert_allclose(coef[:2], level * raw[:2], rtol=1e-12)
    np.testing.assert_allclose(coef[2:4], raw[2:4] / raw[4], rtol=1e-12)
    variability = raw.std(axis=(1, 2)) / np.abs(raw.mean(axis=(1, 2)))
    np.testing.assert_allclose(variability, TINY.coef_variability, rtol=1e-9)
    np.testing.assert_allclose(raw.mean(axis=(1, 2)), TINY.coef_mean, rtol=1e-9)


def test_noise_levels(noisy):
    truth = truth_of(noisy[1], "S1")
    view = read(noisy[0], "S1", 0)
    error = np.linalg.norm(view.xyz[view.valid], axis=-1) - truth.distance.values[view.valid]
    assert error.std() == pytest.approx(TINY.depth_noise, rel=0.05)
    assert abs(error.mean()) < 4 * TINY.depth_noise / np.sqrt(error.size)
    # intensity: relative noise between the configured bounds
    instrument = xr.open_zarr(noisy[1] / "instrument.zarr").compute()
    R = truth.R0.values * np.cos((2 - 1 / truth.n.values) * truth.aoi.values) ** truth.n.values
    signal = instrument.attrs["scale_k"] * instrument_function(
        instrument.coef.values, truth.distance.values, truth.aoi.values
    ) * R
    relative = view.intensity[view.valid] / signal[view.valid] - 1
    assert TINY.intensity_noise * 0.9 < relative.std() < TINY.intensity_noise_max
    # dropouts: a small fraction of otherwise good pixels is invalid
    assert 0 < (~view.valid).sum() < 0.02 * view.valid.size


# --- campaign --------------------------------------------------------------------------------


@pytest.mark.parametrize("fmt", ["npz", "ply", "raw", "mixed"])
@pytest.mark.parametrize("units", ["m", "mm"])
def test_round_trip_through_read_campaign(tmp_path_factory, fmt, units):
    directory, truth = simulate(tmp_path_factory, f"{fmt}-{units}", fmt=fmt, units=units)
    camp = surffin.read_campaign(directory)
    assert camp.camera.units == units
    assert list(camp.specimens) == ["S1", "S2", "S3", "S4"] and list(camp.scenes) == ["T1"]
    assert camp.classes == ["S1", "S2", "S3", "S4"]
    assert len(camp.calibration.wall) == len(TINY.wall_distances) * len(TINY.wall_tilts)
    assert camp.calibration.reference.reflectance == 0.6
    for item in camp.items.values():
        suffixes = {path.suffix for path in item.views}
        assert suffixes == ({".npz", ".ply", ".raw"} if fmt == "mixed" else {f".{fmt}"})
        stored = truth_of(truth, item.name)
        for index, path in enumerate(item.views):
            view = camp.read_view(path)
            np.testing.assert_allclose(view.pose, stored.pose[index].values, atol=1e-9)
    # the points lie at the true distance, up to depth noise (raw: and its 0.25 mm coding)
    view = camp.read_view(camp.items["S1"].views[0])
    error = np.linalg.norm(view.xyz[view.valid], axis=-1) - truth_of(truth, "S1").distance.values[view.valid]
    assert np.abs(error).max() < 6 * TINY.depth_noise + 0.5e-3


def test_rois_lie_on_their_faces(noisy):
    camp = surffin.read_campaign(noisy[0])
    for name, item in camp.specimens.items():
        truth = truth_of(noisy[1], name)
        rows, cols = item.roi.slices
        assert (truth.label.values[rows, cols] == camp.classes.index(item.cls)).all()
        assert (truth.edge_distance.values[rows, cols] >= TINY.label_margin).all()
    reference = camp.calibration.reference
    rows, cols = reference.roi.slices
    assert reference.roi.shape[0] > 5 and reference.roi.shape[1] > 5
    for path in reference.views:
        view = camp.read_view(path)
        # the Lambertian panel at normal incidence is brighter than the wall around it (0.6 vs 0.5)
        assert np.median(view.intensity[rows, cols]) > 1.1 * np.median(view.intensity[view.valid])


def test_no_poses(tmp_path_factory):
    directory, _ = simulate(tmp_path_factory, "no-poses", fmt="mixed", poses=False)
    camp = surffin.read_campaign(directory)
    assert all(camp.read_view(path).pose is None for item in camp.items.values() for path in item.views)
    assert not list(directory.rglob("*.pose.txt"))


def test_scene_truth_labels_are_the_store_labels_inside_the_margin(clean):
    camp = surffin.read_campaign(clean[0])
    with np.load(camp.scenes["T1"].truth) as stored:
        label, classes = stored["label"], stored["classes"]
    assert classes.dtype.kind == "U" and classes.tolist() == ["S1", "S2", "S3", "S4"]
    assert label.dtype == np.int16 and label.shape == TINY.camera.shape
    truth = truth_of(clean[1], "T1")
    inner = truth.edge_distance.values >= TINY.label_margin
    np.testing.assert_array_equal(label, np.where(inner, truth.label.values, -1))
    assert set(np.unique(label)) == {-1, 0, 1, 2, 3}
    assert ((truth.label.values >= 0) & ~inner).any()  # the margin removes something
    names = np.array(truth.surface.attrs["surfaces"])
    assert all(name.endswith(".top") for name in names[truth.surface.values[label >= 0]])


def test_materials_follow_the_paper_qualitatively():
    n = [specimen.material.n for specimen in PRESETS["paper"].specimens]
    R0 = [specimen.material.R0 for specimen in PRESETS["paper"].specimens]
    assert n == sorted(n, reverse=True)
    assert R0[0] < R0[1] < R0[2] and abs(R0[3] - R0[0]) < 0.05
    grain = [specimen.material.R0_texture[0].amplitude for specimen in PRESETS["paper"].specimens]
    assert grain == sorted(grain) and grain[3] > 2 * grain[0]


def test_refuses_to_overwrite_a_campaign(noisy):
    yaml_path = noisy[0] / "campaign.yaml"
    before = yaml_path.read_bytes()
    with pytest.raises(CampaignError, match="already exists"):
        surffin.simulate_campaign(noisy[0], "tiny", seed=5)
    assert yaml_path.read_bytes() == before


def test_rerun_completes_an_interrupted_campaign(tmp_path_factory, noisy):
    directory, truth = simulate(tmp_path_factory, "interrupted")
    (directory / "campaign.yaml").unlink()  # as if killed before the last write
    (directory / "scenes/T1/v02.npz").unlink()
    surffin.simulate_campaign(directory, TINY)
    same_tree(noisy[0], directory)
    same_tree(noisy[1], truth)


def test_refuses_stale_view_files(tmp_path):
    stray = tmp_path / "c" / "specimens" / "S1" / "v07.npz"
    stray.parent.mkdir(parents=True)
    stray.write_bytes(b"")
    with pytest.raises(CampaignError, match="v07.npz"):
        surffin.simulate_campaign(tmp_path / "c", "tiny")
    assert not (tmp_path / "c" / "campaign.yaml").exists()


@pytest.mark.parametrize(
    "kwargs, message",
    [({"fmt": "tif"}, "fmt"), ({"units": "cm"}, "units"), ({"preset": "huge"}, "preset"), ({"seed": -1}, "seed")],
)
def test_bad_arguments(tmp_path, kwargs, message):
    with pytest.raises(ValueError, match=message):
        surffin.simulate_campaign(tmp_path / "c", **{"preset": "tiny", **kwargs})
    assert not (tmp_path / "c").exists()


def test_truth_inside_the_campaign_is_refused(tmp_path):
    with pytest.raises(ValueError, match="inside"):
        surffin.simulate_campaign(tmp_path / "c", "tiny", truth=tmp_path / "c" / "truth")


def test_cli(tmp_path, capsys):
    parser = argparse.ArgumentParser()
    cli_parser(parser)
    args = parser.parse_args([str(tmp_path / "c"), "--preset", "tiny", "--seed", "2", "--format", "ply", "--units", "mm"])
    assert cli_run(args) == 0
    out, err = capsys.readouterr()
    assert out.strip() == str(tmp_path / "c" / "campaign.yaml")
    assert "views rendered" in err
    camp = surffin.read_campaign(tmp_path / "c")
    assert camp.camera.units == "mm" and camp.items["S1"].views[0].suffix == ".ply"
    assert (tmp_path / "c-truth" / "T1.zarr").is_dir()
    # through the surffin command: a second run is refused with a one-line error
    assert main(["simulate", str(tmp_path / "c"), "--preset", "tiny"]) == 2
    assert "already exists" in capsys.readouterr().err
