import argparse
import dataclasses
import filecmp
from pathlib import Path

import numpy as np
import pytest
import scipy.ndimage
import yaml

import surffin
from surffin.cli import main
from surffin.errors import CampaignError
from surffin.io.store import open_store
from surffin.simulate import (
    FORMATS,
    PRESETS,
    UNITS,
    Material,
    PinholeCamera,
    Scene,
    Texture,
    box_faces,
    cli_parser,
    cli_run,
    draw_instrument,
    keyed_rng,
    look_at_pose,
    observe,
    plan_campaign,
    plane_face,
    render,
)
from surffin.simulate.presets import SceneLayout, another_piece
from surffin.simulate.validation import VALIDATION

TINY = PRESETS["tiny"]
NOISE_FREE = dataclasses.replace(TINY, depth_noise=0.0, intensity_noise=0.0, dropout=0.0)


def simulate(tmp_path_factory, name, preset=TINY, **kwargs):
    root = tmp_path_factory.mktemp(name)
    path = surffin.simulate_campaign(root / "campaign", preset, **kwargs)
    return path.parent, root / "campaign-truth"


@pytest.fixture(scope="module")
def noisy(tiny_campaign):
    """The session's tiny campaign (seed 0) and its truth."""
    return tiny_campaign, Path(f"{tiny_campaign}-truth")


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    return simulate(tmp_path_factory, "clean", NOISE_FREE)


def truth_of(truth, item):
    return open_store(truth / f"{item}.zarr").compute()


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
        on_top &= (
            truth.edge_distance.values[np.rint(np.nan_to_num(v)).astype(int), np.rint(np.nan_to_num(u)).astype(int)]
            > 0.01
        )
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
    material = Material(
        "grainy", 0.8, 1.2, R0_texture=(Texture(0.2, 0.003, 0.25),), n_texture=(Texture(0.1, 0.003, 0.25),)
    )
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
    instrument = open_store(clean[1] / "instrument.zarr").compute()
    truth = truth_of(clean[1], item)
    view = read(clean[0], item, 0)
    valid = view.valid
    assert valid.mean() > 0.95
    R = truth.R0.values * np.cos((2 - 1 / truth.n.values) * truth.aoi.values) ** truth.n.values
    f = instrument_function(instrument.coef.values, truth.distance.values, truth.aoi.values)
    expected = instrument.attrs["scale_k"] * f * R
    np.testing.assert_allclose(view.intensity[valid], expected[valid], rtol=1e-6)
    # and the raw, un-normalised instrument gives the same intensity
    raw = instrument.attrs["gain"] * instrument_function(
        instrument.coef_raw.values, truth.distance.values, truth.aoi.values
    )
    np.testing.assert_allclose(view.intensity[valid], (raw * R)[valid], rtol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(view.xyz[valid], axis=-1), truth.distance.values[valid], rtol=1e-6)


def test_instrument_truth_gauge_and_variability(clean):
    instrument = open_store(clean[1] / "instrument.zarr").compute()
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
    instrument = open_store(noisy[1] / "instrument.zarr").compute()
    R = truth.R0.values * np.cos((2 - 1 / truth.n.values) * truth.aoi.values) ** truth.n.values
    signal = (
        instrument.attrs["scale_k"]
        * instrument_function(instrument.coef.values, truth.distance.values, truth.aoi.values)
        * R
    )
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
    args = parser.parse_args(
        [str(tmp_path / "c"), "--preset", "tiny", "--seed", "2", "--format", "ply", "--units", "mm"]
    )
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


def test_default_presets_write_their_crop_and_first_view_references(noisy):
    config = yaml.safe_load((noisy[0] / "campaign.yaml").read_text())
    assert config["crop"] == {"y": list(TINY.crop[0]), "x": list(TINY.crop[1])}
    items = {**config["specimens"], **config["scenes"]}
    assert list(items) == ["S1", "S2", "S3", "S4", "T1"]
    assert not any("reference" in entry for entry in items.values())
    assert all(truth_of(noisy[1], name).attrs["reference_view"] == "v00" for name in items)


# --- design options --------------------------------------------------------------------------

# tiny without noise, no crop, the second view as reference, and a second scene of other pieces
VARIANT = dataclasses.replace(
    NOISE_FREE,
    name="tiny-variant",
    crop=None,
    reference_view=1,
    scenes=(
        SceneLayout(TINY.specimens, TINY.scene_rotations, TINY.scene_distance, TINY.scene_tilts),
        SceneLayout(
            tuple(another_piece(s, "b") for s in TINY.specimens[:3]), (0.0, 90.0, 180.0), 0.6, (10.0, 30.0, 40.0)
        ),
    ),
)


@pytest.fixture(scope="module")
def variant(tmp_path_factory):
    return simulate(tmp_path_factory, "variant", VARIANT, fmt="mixed")


def test_a_later_reference_view_is_written_and_read(variant):
    config = yaml.safe_load((variant[0] / "campaign.yaml").read_text())
    assert "crop" not in config
    items = {**config["specimens"], **config["scenes"]}
    assert list(items) == ["S1", "S2", "S3", "S4", "T1", "T2"]
    assert all(entry["reference"] == "v01" for entry in items.values())
    assert main(["check", str(variant[0])]) == 0
    camp = surffin.read_campaign(variant[0])
    assert (camp.crop.y, camp.crop.x) == ((0, TINY.camera.height), (0, TINY.camera.width))
    rows, cols = np.indices(TINY.camera.shape)
    for name, item in camp.items.items():
        assert item.reference == "v01" and item.reference_view.stem == "v01"
        truth = truth_of(variant[1], name)
        assert truth.attrs["reference_view"] == "v01"
        # the truth lies on the reference view's grid: its points, its AOI, its own coordinates
        view = camp.read_view(item.reference_view)
        np.testing.assert_allclose(
            np.linalg.norm(view.xyz[view.valid], axis=-1), truth.distance.values[view.valid], rtol=1e-6
        )
        np.testing.assert_array_equal(truth.aoi.values, truth.aoi_view[1].values)
        np.testing.assert_allclose(truth.u_ref[1].values, cols, atol=1e-9)
        np.testing.assert_allclose(truth.v_ref[1].values, rows, atol=1e-9)
        assert not np.allclose(truth.u_ref[0].values, cols, equal_nan=True)
    for name, item in camp.specimens.items():
        truth = truth_of(variant[1], name)
        roi_rows, roi_cols = item.roi.slices
        assert (truth.label.values[roi_rows, roi_cols] == camp.classes.index(item.cls)).all()
    with np.load(camp.scenes["T2"].truth) as stored:
        truth = truth_of(variant[1], "T2")
        inner = truth.edge_distance.values >= TINY.label_margin
        np.testing.assert_array_equal(stored["label"], np.where(inner, truth.label.values, -1))


def test_two_scenes_give_two_truth_stores_of_their_own_pieces(variant):
    assert sorted(path.name for path in variant[1].glob("T*.zarr")) == ["T1.zarr", "T2.zarr"]
    first, second = truth_of(variant[1], "T1"), truth_of(variant[1], "T2")
    assert "T1.S1.top" in first.surface.attrs["surfaces"]
    assert {"T2.S1-b.top", "T2.S2-b.top", "T2.S3-b.top"} <= set(second.surface.attrs["surfaces"])
    assert set(np.unique(second.label.values)) == {-1, 0, 1, 2}
    assert second.distance.values[TINY.camera.height // 2, TINY.camera.width // 2] > 0.55


def test_another_piece_is_another_draw_of_its_class():
    camera = PinholeCamera(width=64, height=64, fx=70.0, fy=70.0)
    pose = look_at_pose((0.0, 0.0, -0.01), 0.3, 0.0, 0.0)
    specimen = PRESETS["paper"].specimens[2]
    maps = [
        render(Scene(box_faces("S", (0.0, 0.0), 0.2, 0.01, 0.0, piece.material, 0), seed=0), camera, pose)
        for piece in (specimen, another_piece(specimen, "b"))
    ]
    top = maps[0].label == 0
    for key in ("R0", "n"):
        one, other = getattr(maps[0], key)[top], getattr(maps[1], key)[top]
        assert np.corrcoef(one, other)[0, 1] < 0.5  # other textures ...
        assert other.mean() == pytest.approx(one.mean(), rel=0.03)  # ... of the same class
    piece = another_piece(specimen, "b", thickness=0.02)
    assert (piece.name, piece.cls, piece.material.name) == ("S3-b", "S3", "plaster-S3-b")


def test_specimens_may_have_their_own_thickness():
    thick = dataclasses.replace(TINY.specimens[1], thickness=0.02)
    preset = dataclasses.replace(TINY, specimens=(TINY.specimens[0], thick, *TINY.specimens[2:]))
    plan = {acquisition.name: acquisition for acquisition in plan_campaign(preset, 0)}
    tops = {face.name: face.centre[2] for face in (*plan["S1"].faces, *plan["S2"].faces, *plan["T1"].faces)}
    assert tops["S1.top"] == -TINY.specimen_thickness and tops["S2.top"] == -0.02
    assert tops["T1.S1.top"] == -TINY.specimen_thickness and tops["T1.S2.top"] == -0.02


@pytest.mark.parametrize(
    "change, message",
    [
        ({"reference_view": 3}, "reference_view 3 must index"),
        (
            {"reference_view": 2, "scenes": (SceneLayout(TINY.specimens, TINY.scene_rotations, 0.5, (0.0, 20.0)),)},
            "0 to 1",
        ),
        (
            {
                "specimens": TINY.specimens[:2],
                "scenes": (SceneLayout(TINY.specimens[2:3], (0.0,), 0.5, TINY.scene_tilts),),
            },
            "piece S3 is of class 'S3', which no specimen has",
        ),
    ],
)
def test_bad_designs_are_refused(change, message):
    with pytest.raises(ValueError, match=message):
        plan_campaign(dataclasses.replace(TINY, **change), 0)


def test_intensity_floor_and_range_noise_grow_on_weak_returns():
    camera = PinholeCamera(width=160, height=120, fx=150.0, fy=150.0)
    preset = dataclasses.replace(
        TINY,
        camera=camera,
        intensity_noise=0.02,
        intensity_noise_max=0.02,
        intensity_floor=6.0,
        noise_reference=1000.0,
        depth_noise=0.0009,
        depth_noise_max=0.004,
        dropout=0.0,
        min_intensity=-np.inf,
    )
    instrument = draw_instrument(camera, TINY.coef_mean, TINY.coef_variability, TINY.gain, keyed_rng(0, "i"))
    pose = look_at_pose((0.0, 0.0, 0.0), 0.5, 0.0, 0.0)
    depth_std = {}
    for R0, name in ((0.9, "strong"), (0.04, "weak"), (0.004, "capped")):
        geometry = render(Scene([plane_face("wall", Material(name, R0, 1.0))], seed=0), camera, pose)
        xyz, intensity = observe(geometry, instrument, preset, keyed_rng(0, "view", name))
        f = instrument_function(instrument.coef, geometry.distance, geometry.aoi)
        signal = instrument.gain * f * R0 * np.cos(geometry.aoi)  # Lambertian
        intensity_sigma = np.hypot(0.02 * signal, 6.0)
        depth_sigma = np.clip(0.0009 * np.sqrt(1000.0 / signal), 0.0009, 0.004)
        depth_error = np.linalg.norm(xyz, axis=-1) - geometry.distance
        assert ((intensity - signal) / intensity_sigma).std() == pytest.approx(1.0, rel=0.03), name
        assert (depth_error / depth_sigma).std() == pytest.approx(1.0, rel=0.03), name
        depth_std[name] = depth_error.std()
    # 0.9 mm on strong returns (> 1000 counts), over 3 times more at ~60 counts, the 4 mm cap at ~6 counts
    assert depth_std["strong"] == pytest.approx(0.0009, rel=0.03)
    assert 3 * 0.0009 < depth_std["weak"] < 0.0039
    assert depth_std["capped"] == pytest.approx(0.004, rel=0.03)


# --- validation campaigns ----------------------------------------------------------------------

PAPER_CAMERA = PinholeCamera(width=640, height=480, fx=565.0, fy=579.0)


def centre_aoi(acquisition):
    """Angle of incidence at the aim point of each view, degrees (the faces aimed at face -Z)."""
    return [float(np.degrees(np.arccos(abs(pose[2, 2])))) for pose in acquisition.poses]


@pytest.mark.parametrize("name", sorted(VALIDATION))
def test_validation_campaign_design(name):
    validation = VALIDATION[name]
    preset = validation.preset
    assert preset.name == name and preset.camera == PAPER_CAMERA
    assert validation.fmt in FORMATS and validation.units in UNITS and isinstance(validation.poses, bool)
    plan = plan_campaign(preset, 0)
    by_kind = {kind: [a for a in plan if a.kind == kind] for kind in ("wall", "reference", "specimen", "scene")}
    assert [len(a.poses) for a in by_kind["wall"]] == [48]
    assert [len(a.poses) for a in by_kind["reference"]] == [3]
    assert min(preset.wall_distances) == 0.3 and max(preset.wall_distances) == 1.0
    assert min(preset.wall_tilts) == 0.0 and max(preset.wall_tilts) == 30.0
    # specimens: 20 cm, 10-20 mm thick, 5 views at 0.45 m, centre AOIs of 1.5 to 39 deg
    assert preset.specimen_size == 0.2 and preset.specimen_distance == 0.45
    assert all(0.01 <= preset.thickness(specimen) <= 0.02 for specimen in preset.specimens)
    for specimen in by_kind["specimen"]:
        np.testing.assert_allclose(centre_aoi(specimen), (1.5, 11.0, 20.0, 29.0, 39.0), atol=1e-9)
    # scenes T1, T2, ...: farther, at angles at least 4 deg from the specimens'
    assert [scene.name for scene in by_kind["scene"]] == [f"T{k + 1}" for k in range(len(by_kind["scene"]))]
    assert by_kind["scene"]
    for scene, layout in zip(by_kind["scene"], preset.scene_layouts, strict=True):
        assert layout.distance >= preset.specimen_distance + 0.14
        assert (np.abs(np.subtract(centre_aoi(scene), centre_aoi(by_kind["specimen"][0]))) >= 4.0).all()
        assert sorted({rotation % 360 for rotation in layout.rotations}) == [90.0, 180.0, 270.0]
    # classes close in n (neighbours 7-9 % apart), R0 means within 5 %, on a darker board
    n = np.sort([specimen.material.n for specimen in preset.specimens])
    assert ((np.diff(n) / n[:-1] >= 0.07) & (np.diff(n) / n[:-1] <= 0.09)).all()
    R0 = [specimen.material.R0 for specimen in preset.specimens]
    assert max(R0) / min(R0) <= 1.05 and preset.board.R0 < 0.75 * min(R0)
    assert all(specimen.roughness_mm is None for specimen in preset.specimens)
    # noise: 2 % plus a floor, range noise 0.9 mm growing on weak returns
    assert (preset.intensity_noise, preset.intensity_noise_max, preset.depth_noise) == (0.02, 0.02, 0.0009)
    assert preset.intensity_floor > 0 and preset.depth_noise_max > preset.depth_noise


def test_validation_campaigns_cover_the_required_kinds():
    presets = {name: validation.preset for name, validation in VALIDATION.items()}
    assert len(VALIDATION) >= 6
    assert any(v.fmt == "ply" and v.units == "mm" and v.preset.crop is None and v.poses for v in VALIDATION.values())
    assert any(v.fmt == "raw" for v in VALIDATION.values()) and any(v.fmt == "mixed" for v in VALIDATION.values())
    assert any(preset.reference_view > 0 for preset in presets.values())
    assert any(len(preset.scene_layouts) >= 2 for preset in presets.values())
    assert any(max(layout.distance for layout in preset.scene_layouts) >= 0.75 for preset in presets.values())
    other_pieces = [
        name
        for name, preset in presets.items()
        if all(piece not in preset.specimens for piece in preset.scene_layouts[-1].pieces)
    ]
    assert other_pieces
    assert any(max(s.material.R0 for s in preset.specimens) < 0.6 for preset in presets.values())  # darker


@pytest.mark.parametrize("name", ["val-plaster", "val-concrete"])
def test_validation_classes_spread_and_overlap_like_the_paper(name):
    # each specimen's reference view at full size; R0 and n smoothed by the method's 7 x 7 Gaussian
    preset = VALIDATION[name].preset
    ranges = {}
    for acquisition in plan_campaign(preset, 0):
        if acquisition.kind != "specimen":
            continue
        geometry = render(Scene(acquisition.faces, seed=0), preset.camera, acquisition.poses[0])
        inside = (geometry.label >= 0) & (geometry.edge_distance >= 0.01)
        assert inside.sum() > 40_000
        for key in ("R0", "n"):
            smooth = scipy.ndimage.gaussian_filter(np.nan_to_num(getattr(geometry, key)), 1.4, truncate=3 / 1.4)
            low, middle, high = np.percentile(smooth[inside], [5, 50, 95])
            ranges[acquisition.name, key] = (low, high)
            spread = (high - low) / middle
            assert (0.07 <= spread <= 0.10) if key == "R0" else (0.028 <= spread <= 0.042), (
                acquisition.name,
                key,
                spread,
            )
    names = [specimen.name for specimen in preset.specimens]
    for first in names:  # every two classes' R0 ranges overlap, their n ranges do not
        for second in names[names.index(first) + 1 :]:
            (a, b), (c, d) = ranges[first, "R0"], ranges[second, "R0"]
            assert a < d and c < b, (first, second)
            (a, b), (c, d) = ranges[first, "n"], ranges[second, "n"]
            assert b < c or d < a, (first, second)


def test_cli_renders_a_validation_campaign_in_its_own_format(monkeypatch, tmp_path):
    calls = []

    def record(directory, preset, seed, **options):
        calls.append((preset.name, seed, options))
        return Path(directory) / "campaign.yaml"

    monkeypatch.setattr("surffin.simulate.acquire.simulate_campaign", record)
    parser = argparse.ArgumentParser()
    cli_parser(parser)
    for argv in (
        ["--validation", "val-concrete", "--seed", "3"],
        ["--validation", "val-concrete", "--format", "npz", "--no-poses"],
        ["--preset", "tiny"],
        [],
    ):
        assert cli_run(parser.parse_args([str(tmp_path / "c"), *argv])) == 0
    assert [(name, seed, options["fmt"], options["units"], options["poses"]) for name, seed, options in calls] == [
        ("val-concrete", 3, "ply", "mm", True),
        ("val-concrete", 0, "npz", "mm", False),
        ("tiny", 0, "npz", "m", True),
        ("paper", 0, "npz", "m", True),
    ]
    with pytest.raises(SystemExit):
        parser.parse_args([str(tmp_path / "c"), "--preset", "tiny", "--validation", "val-raw"])
