"""Tests of surffin.io.campaign: read_campaign's validation and read_truth."""

import hashlib
import json
import threading

import numpy as np
import pytest
import xarray as xr
import yaml

from surffin.cli import main
from surffin.errors import CampaignError, StoreError, ViewFileError
from surffin.grid import Roi
from surffin.io import campaign as campaign_module
from surffin.io.campaign import Camera, check_pixels, read_campaign, read_truth
from surffin.io.ingest import describe_file, ingest_item
from surffin.io.store import open_store, write_store
from surffin.io.viewfile import (
    ABCY16_DEFAULT,
    META_SUFFIX,
    POSE_JSON_SUFFIX,
    check_view_pixels,
    list_views,
    sidecar_path,
    write_view,
)
from surffin.pipeline.parameters import read_config
from surffin.pipeline.workflow import Plan

VIEW_FILES = {
    "calibration/wall": ["w0.npz", "w1.ply", "w2.raw"],
    "calibration/spectralon": ["p0.npz", "p1.npz"],
    "specimens/S1": ["v0.npz", "v1.npz"],
    "specimens/S2": ["v0.raw", "v1.ply"],
    "scenes/T1": ["v0.npz", "v1.npz"],
}
TRUTH = "scenes/T1/truth.npz"


def truth_label(height=6, width=8, top=1):
    """A label image with values -1..top."""
    return (np.arange(height * width).reshape(height, width) % (top + 2)) - 1


def write_truth(path, label, classes=("S1", "S2")):
    np.savez(path, label=label, classes=np.array(classes))


@pytest.fixture
def campaign(tmp_path, synthetic_view):
    """A valid campaign directory (``tmp_path/camp``) and its campaign.yaml as a dict, not yet written.

    ``tmp_path/outside`` holds two more views, outside the campaign.
    """
    xyz, intensity, _ = synthetic_view
    root = tmp_path / "camp"
    for folder, names in {**VIEW_FILES, "../outside": ["o0.npz", "o1.npz"]}.items():
        (root / folder).mkdir(parents=True)
        for name in names:
            write_view(root / folder / name, xyz, intensity)
    write_truth(root / TRUTH, truth_label())
    doc = {
        "name": "demo",
        "camera": {
            "width": 8,
            "height": 6,
            "units": "m",
            "intrinsics": {"fx": 7.0, "fy": 7.5, "cx": 3.5, "cy": 2.5},
        },
        "crop": {"y": [1, 5], "x": [1, 7]},
        "calibration": {
            "wall": "calibration/wall",
            "reference": {
                "views": "calibration/spectralon",
                "reflectance": 0.6,
                "roi": {"y": [0, 3], "x": [2, 4]},
            },
        },
        "specimens": {
            "S1": {
                "class": "S1",
                "views": "specimens/S1",
                "roi": {"y": [0, 4], "x": [2, 8]},
                "roughness_mm": 0.0068,
            },
            "S2": {"class": "S2", "views": "specimens/S2", "reference": "v1"},
        },
        "scenes": {"T1": {"views": "scenes/T1", "truth": TRUTH}},
    }
    return root, doc


def write_yaml(root, doc):
    (root / "campaign.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))


def test_valid_campaign(campaign):
    root, doc = campaign
    write_yaml(root, doc)
    camp = read_campaign(root)

    assert camp.root == root.resolve() and camp.path == root.resolve() / "campaign.yaml"
    assert camp.name == "demo"
    assert camp.camera == Camera(8, 6, "m", {"fx": 7.0, "fy": 7.5, "cx": 3.5, "cy": 2.5}, dict(ABCY16_DEFAULT))
    assert camp.crop == Roi((1, 5), (1, 7))
    assert [path.name for path in camp.calibration.wall] == ["w0.npz", "w1.ply", "w2.raw"]
    reference = camp.calibration.reference
    assert [path.name for path in reference.views] == ["p0.npz", "p1.npz"]
    assert reference.reflectance == 0.6 and reference.roi == Roi((1, 3), (2, 4))
    assert list(camp.items) == ["S1", "S2", "T1"] and camp.classes == ["S1", "S2"]

    s1, s2, t1 = camp.specimens["S1"], camp.specimens["S2"], camp.scenes["T1"]
    assert (s1.kind, s1.cls, s1.roi, s1.roughness_mm, s1.reference, s1.truth) == (
        "specimen",
        "S1",
        Roi((1, 4), (2, 7)),
        0.0068,
        "v0",
        None,
    )
    assert s1.views == (root.resolve() / "specimens/S1/v0.npz", root.resolve() / "specimens/S1/v1.npz")
    assert s2.view_stems == ("v0", "v1") and s2.reference == "v1" and s2.reference_view.name == "v1.ply"
    assert s2.roi is None and s2.roughness_mm is None
    assert (t1.kind, t1.cls, t1.view_stems, t1.truth) == ("scene", None, ("v0", "v1"), root.resolve() / TRUTH)

    view = camp.read_view(t1.views[0])
    assert view.xyz.shape == (6, 8, 3) and view.valid.sum() == 44


def test_defaults_and_campaign_file_path(campaign):
    root, doc = campaign
    for key in ("name", "crop", "calibration"):
        del doc[key]
    doc["camera"] = {"width": 8, "height": 6, "units": "mm", "abcy16": {"scale": 0.5}}
    write_yaml(root, doc)

    camp = read_campaign(root / "campaign.yaml", require_calibration=False)
    assert camp.name == "camp" and camp.calibration is None
    assert camp.crop == Roi((0, 6), (0, 8))
    assert camp.camera.intrinsics is None
    assert camp.camera.abcy16 == {"signed": False, "scale": 0.5, "offset": ABCY16_DEFAULT["offset"]}
    assert (camp.camera.ply_intensity, camp.camera.saturation, camp.camera.hand_eye) == ("intensity", None, None)
    assert camp.camera.match_settings == () and camp.camera.distortion is None
    assert camp.specimens["S1"].roi == Roi((0, 4), (2, 8))
    view = camp.read_view(camp.specimens["S1"].views[0])
    assert np.nanmin(view.xyz[..., 2]) < 0.001  # the metre values were read as mm


HAND_EYE = [[0.0, -1.0, 0.0, 0.01], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.05], [0.0, 0.0, 0.0, 1.0]]


def test_real_camera_keys(campaign, synthetic_view):
    """Every key a real camera needs: signed ABCY16 with per-axis scale, the PLY intensity name, saturation,
    the hand-eye transform, settings that must match, lens distortion."""
    root, doc = campaign
    xyz, intensity, _ = synthetic_view
    signed = {"signed": True, "scale": [0.25, 0.25, 0.125]}
    for path in root.glob("*/*/*.raw"):
        write_view(path, xyz, intensity, abcy16=signed)
    for path in root.glob("*/*/*.ply"):
        path.write_bytes(path.read_bytes().replace(b"property float intensity\n", b"property float amplitude\n", 1))
    for path in (path for folder in VIEW_FILES for path in list_views(root / folder)):
        sidecar_path(path, META_SUFFIX).write_text('{"exposure_us": 250, "gain": "low", "temperature_c": 41.2}')
    pose = sidecar_path(root / "specimens/S1/v0.npz", POSE_JSON_SUFFIX)
    pose.write_text('{"translation": [0.1, 0.2, 0.3], "quaternion": [0, 0, 0, 1]}')  # 180 deg about z
    doc["camera"].update(
        abcy16=signed,
        ply_intensity="amplitude",
        saturation=900,
        hand_eye=HAND_EYE,
        match_settings=["exposure_us", "gain"],
    )
    doc["camera"]["intrinsics"]["distortion"] = [-0.1, 0.02, 0.001, -0.002, 0.0]
    write_yaml(root, doc)

    camera = read_campaign(root).camera
    assert camera.abcy16 == {"signed": True, "scale": (0.25, 0.25, 0.125), "offset": (0.0, 0.0, 0.0)}
    assert (camera.ply_intensity, camera.saturation, camera.match_settings) == (
        "amplitude",
        900.0,
        ("exposure_us", "gain"),
    )
    assert camera.distortion == (-0.1, 0.02, 0.001, -0.002, 0.0)
    np.testing.assert_array_equal(camera.view_kwargs["hand_eye"], HAND_EYE)
    assert json.loads(json.dumps(camera.settings)) == camera.settings
    assert camera.settings["hand_eye"] == HAND_EYE and camera.settings["abcy16"]["scale"] == [0.25, 0.25, 0.125]

    camp = read_campaign(root)
    view = camp.read_view(root / "specimens/S1/v0.npz")
    flange = np.diag([-1.0, -1.0, 1.0, 1.0])
    flange[:3, 3] = [0.1, 0.2, 0.3]
    np.testing.assert_allclose(view.pose, flange @ np.array(HAND_EYE), atol=1e-12)
    assert view.settings == {"exposure_us": 250, "gain": "low", "temperature_c": 41.2}
    assert view.saturated.sum() == (view.valid & (view.intensity >= 900)).sum() > 0
    raw = camp.read_view(root / "specimens/S2/v0.raw")
    np.testing.assert_allclose(raw.xyz[raw.valid], xyz[raw.valid], atol=0.125e-3)
    ply = camp.read_view(root / "specimens/S2/v1.ply")
    np.testing.assert_allclose(ply.intensity[ply.valid], intensity[ply.valid], rtol=1e-6)


def test_ingest_keeps_saturated_points_for_geometry_only(campaign, synthetic_view, tmp_path):
    root, doc = campaign
    xyz, intensity, valid = synthetic_view
    doc["camera"]["saturation"] = 500
    sidecar_path(root / "specimens/S1/v1.npz", META_SUFFIX).write_text('{"exposure_us": 250, "gain": "low"}')
    write_yaml(root, doc)
    ds = ingest_item(read_campaign(root), "S1")

    rows, cols = slice(1, 5), slice(1, 7)  # the crop
    saturated = (valid & (intensity >= 500))[rows, cols]
    assert saturated.any()
    for view in ("v0", "v1"):
        np.testing.assert_array_equal(ds["saturated"].sel(view=view), saturated)
        np.testing.assert_array_equal(ds["valid"].sel(view=view), valid[rows, cols] & ~saturated)
        assert np.isfinite(ds["xyz"].sel(view=view).values[saturated]).all()  # the geometry keeps them
    assert ds.attrs["saturated_pixels"] == {"v0": int(saturated.sum()), "v1": int(saturated.sum())}
    assert ds.attrs["settings"] == {"v0": {}, "v1": {"exposure_us": 250, "gain": "low"}}
    assert ds.attrs["camera"]["saturation"] == 500.0 and ds.attrs["camera"]["intrinsics"]["fx"] == 7.0
    back = open_store(write_store(ds, tmp_path / "S1.zarr"), stage="ingest")
    assert back.attrs["settings"] == ds.attrs["settings"] and back.attrs["camera"] == ds.attrs["camera"]
    np.testing.assert_array_equal(back["saturated"], ds["saturated"])


def test_ingest_cube_holds_the_views_cropped_and_rounded_to_float32(campaign):
    root, doc = campaign
    doc["camera"]["units"] = "mm"  # metres from millimetres: float64 values that float32 rounds
    write_yaml(root, doc)
    camp = read_campaign(root)
    ds = ingest_item(camp, "S2")
    views = [camp.read_view(path) for path in camp.item("S2").views]
    rows, cols = camp.crop.slices
    for name, dtype in (("xyz", np.float32), ("intensity", np.float32), ("valid", bool), ("saturated", bool)):
        assert ds[name].dtype == dtype
    expected = np.stack([view.xyz[rows, cols] for view in views]).astype(np.float32)
    assert ds["xyz"].values.tobytes() == expected.tobytes()
    assert not np.array_equal(expected.astype(np.float64), np.stack([view.xyz[rows, cols] for view in views]))
    expected = np.stack([view.intensity[rows, cols] for view in views]).astype(np.float32)
    assert ds["intensity"].values.tobytes() == expected.tobytes()


@pytest.mark.parametrize("size", [0, 1, 3 << 20])
def test_describe_file(tmp_path, size):
    content = np.random.default_rng(size).bytes(size)
    path = tmp_path / "file.npz"
    path.write_bytes(content)
    assert describe_file(path) == {"size": size, "sha256": hashlib.sha256(content).hexdigest()}


def test_ingest_records_its_view_files(campaign):
    root, doc = campaign
    write_yaml(root, doc)
    inputs = ingest_item(read_campaign(root), "S2").attrs["surffin_inputs"]
    assert inputs == {
        f"specimens/S2/{name}": {"size": len(data), "sha256": hashlib.sha256(data).hexdigest()}
        for name, data in ((name, (root / "specimens/S2" / name).read_bytes()) for name in ("v0.raw", "v1.ply"))
    }


@pytest.mark.parametrize("size", [4, 8])
def test_distortion_sizes(campaign, size):
    root, doc = campaign
    doc["camera"]["intrinsics"]["distortion"] = list(range(size))
    write_yaml(root, doc)
    assert read_campaign(root).camera.distortion == tuple(float(value) for value in range(size))


def test_yaml_anchors_and_merge_keys_are_not_duplicates(campaign):
    root, doc = campaign
    text = yaml.safe_dump(doc, sort_keys=False)
    text = text.replace("crop:\n", "crop: &crop\n", 1)
    text += "  T2:\n    views: scenes/T1\n    truth: scenes/T1/truth.npz\n    <<: {reference: v1}\n"
    text = text.replace("  S2:\n    class: S2\n", "  S2:\n    <<: {class: S2}\n    class: S2\n    roi: *crop\n", 1)
    (root / "campaign.yaml").write_text(text)
    camp = read_campaign(root)
    assert camp.scenes["T2"].reference == "v1"
    assert camp.specimens["S2"].roi == camp.crop == Roi((1, 5), (1, 7))


def test_check_views_can_be_skipped(campaign):
    root, doc = campaign
    write_yaml(root, doc)
    (root / "specimens/S1/v1.npz").write_bytes(b"broken")
    assert read_campaign(root, check_views=False).specimens["S1"].view_stems == ("v0", "v1")
    with pytest.raises(CampaignError, match=r"specimens\.S1\.views: .*v1\.npz: unreadable"):
        read_campaign(root)


def test_items_builds_only_the_named_items(campaign):
    root, doc = campaign
    write_yaml(root, doc)
    whole = read_campaign(root)
    for name in whole.items:
        camp = read_campaign(root, items=[name])
        assert list(camp.items) == [name] and camp.item(name) == whole.item(name)
        assert (camp.name, camp.camera, camp.crop, camp.calibration) == (
            whole.name,
            whole.camera,
            whole.crop,
            whole.calibration,
        )


def test_items_leaves_the_other_items_files_unread(campaign):
    root, doc = campaign
    write_yaml(root, doc)
    (root / "specimens/S2/v0.raw").write_bytes(b"broken")
    (root / TRUTH).write_bytes(b"broken")
    assert read_campaign(root, items=["S1"]).specimens["S1"].view_stems == ("v0", "v1")
    with pytest.raises(CampaignError, match=r"specimens\.S2\.views: .*v0\.raw: 6 bytes"):
        read_campaign(root, items=["S2"])
    with pytest.raises(CampaignError, match=r"scenes\.T1\.truth: .*unreadable truth file"):
        read_campaign(root, items=["T1"])
    (root / TRUTH).unlink()
    with pytest.raises(CampaignError, match=r"scenes\.T1\.truth: got 'scenes/T1/truth.npz'; expected an existing"):
        read_campaign(root, items=["S1"])


def test_unknown_item_names_the_campaign_s_items(campaign):
    root, doc = campaign
    write_yaml(root, doc)
    message = "campaign.yaml: no item named 'S3'; the campaign has: S1, S2, T1$"
    with pytest.raises(CampaignError, match=message):
        read_campaign(root, items=["S1", "S3"])
    with pytest.raises(CampaignError, match=message):
        read_campaign(root).item("S3")
    with pytest.raises(CampaignError, match=message):
        ingest_item(read_campaign(root), "S3")
    with pytest.raises(CampaignError, match="no item named 'S2'; the campaign has: S1$"):
        read_campaign(root, items=["S1"]).item("S2")


def test_campaign_directory_without_yaml(tmp_path):
    with pytest.raises(CampaignError, match="no such file; expected a campaign directory holding campaign.yaml"):
        read_campaign(tmp_path)


# --- bad campaigns ------------------------------------------------------------------------------


def set_key(dotted, value):
    """Mutation: set ``doc[a][b]... = value`` for ``dotted == "a.b..."``; None deletes the key."""

    def mutate(root, doc):
        *parents, last = dotted.split(".")
        for part in parents:
            doc = doc[part]
        if value is None:
            del doc[last]
        else:
            doc[last] = value

    return mutate


def edit_text(old, new):
    """Mutation of the YAML text: replace ``old`` by ``new`` once."""

    def mutate(root, doc):
        text = yaml.safe_dump(doc, sort_keys=False)
        assert old in text
        return text.replace(old, new, 1)

    return mutate


def then(*mutations):
    def mutate(root, doc):
        texts = [mutation(root, doc) for mutation in mutations]
        return next((text for text in texts if text is not None), None)

    return mutate


def link_outside(root, doc):
    (root / "specimens/link").symlink_to(root.parent / "outside", target_is_directory=True)


def remove(relative):
    def mutate(root, doc):
        (root / relative).unlink()

    return mutate


def write_bytes(relative, content):
    def mutate(root, doc):
        (root / relative).write_bytes(content)

    return mutate


def truth_of(label, classes=("S1", "S2")):
    def mutate(root, doc):
        write_truth(root / TRUTH, label, classes)

    return mutate


def settings_in(changes):
    """Mutation: every view (of VIEW_FILES) gets exposure_us 250 and gain 2 in its meta.json, then ``changes``.

    ``changes`` maps a view (relative path) to its settings, or to None for no sidecar at all.
    """

    def mutate(root, doc):
        doc["camera"]["match_settings"] = ["exposure_us", "gain"]
        for path in (path for folder in VIEW_FILES for path in list_views(root / folder)):
            sidecar_path(path, META_SUFFIX).write_text('{"exposure_us": 250, "gain": 2}')
        for relative, settings in changes.items():
            sidecar = sidecar_path(root / relative, META_SUFFIX)
            if settings is None:
                sidecar.unlink()
            else:
                sidecar.write_text(json.dumps(settings))

    return mutate


def copy_view(source, target):
    def mutate(root, doc):
        (root / target).write_bytes((root / source).read_bytes())

    return mutate


BAD = {
    "unknown-key": (set_key("camera.widht", 8), r"camera\.widht: unknown key 'widht' \(did you mean 'width'\?\)"),
    "unknown-section": (set_key("specimen", {}), r"specimen: unknown key 'specimen' \(did you mean 'specimens'"),
    "scene-roi": (set_key("scenes.T1.roi", {"y": [0, 2], "x": [0, 2]}), r"scenes\.T1\.roi: unknown key 'roi'"),
    "duplicate-key": (
        edit_text("name: demo\n", "name: demo\nname: again\n"),
        r"line 2: duplicate key 'name' \(first on line 1\)",
    ),
    "duplicate-item": (
        edit_text("scenes:\n", "scenes:\n  T1:\n    views: scenes/T1\n"),
        r"duplicate key 'T1' \(first on line \d+",
    ),
    "bad-item-name": (
        then(set_key("specimens.-S1", {"class": "S1", "views": "specimens/S1"}), set_key("specimens.S1", None)),
        r"specimens\.-S1: got '-S1'; expected a name matching",
    ),
    "bad-class-name": (set_key("specimens.S1.class", "S 1"), r"specimens\.S1\.class: got 'S 1'; expected a name"),
    "numeric-class-name": (set_key("specimens.S1.class", 1), r"specimens\.S1\.class: got 1; .*quote it"),
    "escaping-path": (
        set_key("specimens.S1.views", "../outside"),
        r"specimens\.S1\.views: got '\.\./outside'; "
        r"expected a path that stays inside the campaign directory",
    ),
    "absolute-path": (
        set_key("specimens.S1.views", "/tmp"),
        r"specimens\.S1\.views: got '/tmp'; expected a path "
        r"relative to the campaign directory",
    ),
    "symlink-escape": (
        then(link_outside, set_key("specimens.S1.views", "specimens/link")),
        r"specimens\.S1\.views: got 'specimens/link'; expected a path that stays inside",
    ),
    "truth-escape": (set_key("scenes.T1.truth", "scenes/../../x.npz"), r"scenes\.T1\.truth: .*stays inside"),
    "crop-outside-sensor": (set_key("crop.y", [1, 7]), r"crop\.y: got \[1, 7\]; expected a range within the"),
    "crop-reversed": (set_key("crop.x", [5, 2]), r"crop\.x: got \[5, 2\]; expected a half-open pixel range"),
    "roi-outside-crop": (
        set_key("specimens.S1.roi", {"y": [5, 6], "x": [0, 8]}),
        r"specimens\.S1\.roi: got .*; expected a roi overlapping the crop \{y: \[1, 5\], x: \[1, 7\]\}",
    ),
    "item-with-one-view": (remove("specimens/S1/v1.npz"), r"specimens\.S1\.views: .*at least 2 view files"),
    "wall-with-one-view": (
        then(remove("calibration/wall/w0.npz"), remove("calibration/wall/w1.ply")),
        r"calibration\.wall: .*at least 2 view files",
    ),
    "missing-folder": (set_key("specimens.S1.views", "specimens/S9"), r"S1\.views: got .*an existing folder"),
    "missing-reference-stem": (
        set_key("specimens.S2.reference", "v7"),
        r"specimens\.S2\.reference: got 'v7'; expected the stem of one of the item's views: v0, v1",
    ),
    "reflectance-0": (set_key("calibration.reference.reflectance", 0), r"reflectance: got 0; expected .*\(0, 1\]"),
    "reflectance-1.5": (set_key("calibration.reference.reflectance", 1.5), r"reflectance: got 1\.5; expected"),
    "truth-shape": (truth_of(truth_label(height=5)), r"T1\.truth: .*truth\.npz: 'label' is int64 of shape"),
    "truth-values": (truth_of(truth_label(top=2)), r"scenes\.T1\.truth: .*'label' spans -1\.\.2 with 2 classes"),
    "truth-classes": (truth_of(truth_label(), classes=("S1", "S1")), r"'classes' repeats a name"),
    "truth-garbage": (write_bytes(TRUTH, b"garbage"), r"scenes\.T1\.truth: .*unreadable truth file"),
    "truth-missing": (set_key("scenes.T1.truth", "scenes/T1/none.npz"), r"scenes\.T1\.truth: .*an existing file"),
    "calibration-missing": (set_key("calibration", None), r"calibration: missing"),
    "width-bool": (set_key("camera.width", True), r"camera\.width: got True; expected a positive integer"),
    "width-float": (set_key("camera.width", 8.0), r"camera\.width: got 8\.0; expected a positive integer"),
    "width-text": (set_key("camera.width", "8"), r"camera\.width: got '8'; expected a positive integer"),
    "units": (set_key("camera.units", "cm"), r"camera\.units: got 'cm'; expected one of m, mm"),
    "fx-zero": (set_key("camera.intrinsics.fx", 0), r"camera\.intrinsics\.fx: got 0; expected a number > 0"),
    "cy-missing": (set_key("camera.intrinsics.cy", None), r"camera\.intrinsics\.cy: missing"),
    "abcy16-scale": (set_key("camera.abcy16", {"scale": -1}), r"abcy16\.scale: got -1; expected a number > 0"),
    "abcy16-offset": (set_key("camera.abcy16", {"offset": [1, 2]}), r"abcy16\.offset: .*three finite numbers"),
    "abcy16-signed": (
        set_key("camera.abcy16", {"signed": "yes"}),
        r"abcy16\.signed: got 'yes'; expected true or false",
    ),
    "abcy16-scale-axes": (
        set_key("camera.abcy16", {"scale": [0.25, 0.25]}),
        r"abcy16\.scale: got \[0\.25, 0\.25\]; expected a number > 0 \(mm per code\) or three, one per axis",
    ),
    "abcy16-scale-axis-zero": (set_key("camera.abcy16", {"scale": [0.25, 0, 0.25]}), r"abcy16\.scale: got \[0\.25, 0"),
    "abcy16-misspelt": (
        set_key("camera.abcy16", {"signd": True}),
        r"camera\.abcy16\.signd: unknown key 'signd' \(did you mean 'signed'\?\)",
    ),
    "abcy16-other-form": (
        set_key("camera.abcy16", {"signed": True}),
        r"calibration\.wall: .*w2\.raw: looks like Coord3D_ABCY16 data, not Coord3D_ABCY16s",
    ),
    "ply-intensity-words": (
        set_key("camera.ply_intensity", "scalar Intensity"),
        r"camera\.ply_intensity: got 'scalar Intensity'; expected a PLY property name",
    ),
    "ply-intensity-absent": (
        set_key("camera.ply_intensity", "reflectance"),
        r"wall: .*w1\.ply: no vertex property of the intensity \(reflectance, scalar_Intensity, intensities\)",
    ),
    "saturation-zero": (set_key("camera.saturation", 0), r"camera\.saturation: got 0; expected a number > 0"),
    "hand-eye-shape": (
        set_key("camera.hand_eye", HAND_EYE[:3]),
        r"camera\.hand_eye: got .*; expected a rigid 4x4 transform \(flange-to-camera\), four rows of four numbers$",
    ),
    "hand-eye-scaled": (
        set_key("camera.hand_eye", [[2.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]]),
        r"camera\.hand_eye: got .*; expected a rigid 4x4 transform .*: rotation part is not a rotation",
    ),
    "hand-eye-mirror": (
        set_key("camera.hand_eye", [[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, -1.0, 0], [0, 0, 0, 1.0]]),
        r"camera\.hand_eye: .*det -1",
    ),
    "hand-eye-text": (set_key("camera.hand_eye", "identity"), r"camera\.hand_eye: got 'identity'; expected a rigid"),
    "match-settings-text": (
        set_key("camera.match_settings", "exposure_us"),
        r"camera\.match_settings: got 'exposure_us'; expected a list of setting names",
    ),
    "match-settings-twice": (
        set_key("camera.match_settings", ["gain", "gain"]),
        r"camera\.match_settings: got \['gain', 'gain'\]; expected each setting name once",
    ),
    "match-settings-differ": (
        settings_in({"specimens/S2/v1.ply": {"exposure_us": 500, "gain": 2}, "scenes/T1/v0.npz": {"exposure_us": 500}}),
        r"camera\.match_settings: setting 'exposure_us' differs between views \(250 in 9 view\(s\): "
        r"calibration/wall/w0\.npz, calibration/wall/w1\.ply, calibration/wall/w2\.raw, \.\.\.; 500 in 2 view\(s\): "
        r"specimens/S2/v1\.ply, scenes/T1/v0\.npz\); expected one value in every view",
    ),
    "match-settings-missing": (
        settings_in({"calibration/spectralon/p1.npz": {"exposure_us": 250}, "scenes/T1/v1.npz": {"exposure_us": 250}}),
        r"setting 'gain' differs between views \(2 in 9 view\(s\): .*; missing in 2 view\(s\): "
        r"calibration/spectralon/p1\.npz, scenes/T1/v1\.npz\)",
    ),
    "match-settings-type": (
        settings_in({"specimens/S1/v0.npz": {"exposure_us": "250", "gain": 2}}),
        r"'exposure_us' differs between views \(250 in 10 view\(s\).*; '250' in 1 view\(s\): specimens/S1/v0\.npz\)",
    ),
    "settings-broken": (
        then(settings_in({}), write_bytes("specimens/S1/v1.meta.json", b'{"gain": [1]}')),
        r"specimens\.S1\.views: .*v1\.meta\.json: setting 'gain' is \[1\]; expected",
    ),
    "pose-json-and-txt": (
        then(
            write_bytes("scenes/T1/v1.pose.txt", b"1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1"),
            write_bytes("scenes/T1/v1.pose.json", b'{"translation": [0, 0, 0], "quaternion": [1, 0, 0, 0]}'),
        ),
        r"scenes\.T1\.views: .*v1\.npz: 2 poses given: .*v1\.pose\.txt and .*v1\.pose\.json",
    ),
    "distortion-6": (
        set_key("camera.intrinsics.distortion", [0, 0, 0, 0, 0, 0]),
        r"camera\.intrinsics\.distortion: got \[0, 0, 0, 0, 0, 0\]; expected a list of 4, 5, 8 finite numbers",
    ),
    "distortion-text": (
        set_key("camera.intrinsics.distortion", ["k1", 0, 0, 0]),
        r"intrinsics\.distortion: got \['k1'",
    ),
    "roughness-negative": (set_key("specimens.S1.roughness_mm", -0.1), r"roughness_mm: got -0\.1; expected a"),
    "shared-name": (
        set_key("scenes.S1", {"views": "scenes/T1"}),
        r"scenes\.S1: the name is also a specimen's; specimens and scenes share one namespace",
    ),
    "no-items": (
        then(set_key("specimens", None), set_key("scenes", None)),
        r"specimens: no specimens and no scenes; expected at least one item",
    ),
    "duplicate-stem": (
        copy_view("specimens/S2/v0.raw", "specimens/S1/v0.raw"),
        r"specimens\.S1\.views: .*two view files with the stem 'v0'",
    ),
    "broken-view": (write_bytes("specimens/S2/v0.raw", b"short"), r"specimens\.S2\.views: .*v0\.raw: 5 bytes"),
    "camera-missing": (set_key("camera", None), r"camera: missing"),
    "not-a-mapping": (lambda root, doc: "- a\n- b\n", r"\(top level\): got \['a', 'b'\]; expected a mapping"),
    "not-yaml": (lambda root, doc: "camera: [1, 2\n", "not valid YAML"),
}


@pytest.mark.parametrize(("mutate", "match"), BAD.values(), ids=BAD.keys())
def test_bad_campaign(campaign, mutate, match):
    root, doc = campaign
    text = mutate(root, doc)
    if text is None:
        write_yaml(root, doc)
    else:
        (root / "campaign.yaml").write_text(text)
    with pytest.raises(CampaignError, match=match) as raised:
        read_campaign(root)
    assert str(root.resolve() / "campaign.yaml") in str(raised.value)


# --- truth files and rois -------------------------------------------------------------------------


def test_read_truth(tmp_path):
    label = truth_label()
    write_truth(tmp_path / "t.npz", label.astype(np.int16), classes=("rough", "smooth"))
    read_label, classes = read_truth(tmp_path / "t.npz", width=8, height=6)
    np.testing.assert_array_equal(read_label, label)
    assert classes == ["rough", "smooth"]


@pytest.mark.parametrize(
    ("arrays", "match"),
    [
        ({"label": truth_label()}, r"lacks \['classes'\]"),
        ({"label": truth_label().astype(float), "classes": np.array(["a", "b"])}, "'label' is float64"),
        ({"label": truth_label(), "classes": np.array([1, 2])}, "'classes' is int64"),
        ({"label": truth_label(), "classes": np.array(["a", None], dtype=object)}, "unreadable truth file"),
    ],
)
def test_bad_truth(tmp_path, arrays, match):
    np.savez(tmp_path / "t.npz", **arrays)
    with pytest.raises(CampaignError, match=match) as raised:
        read_truth(tmp_path / "t.npz", width=8, height=6)
    assert str(tmp_path / "t.npz") in str(raised.value)


def test_roi():
    roi = Roi((2, 10), (0, 5))
    assert roi.shape == (8, 5)
    assert np.zeros((20, 20))[roi.slices].shape == (8, 5)
    assert roi.clip(Roi((4, 20), (1, 3))) == Roi((4, 10), (1, 3))
    with pytest.raises(ValueError, match="does not overlap"):
        roi.clip(Roi((10, 12), (0, 5)))


# --- a campaign the workflow refuses -----------------------------------------------------------------


def test_scenes_without_specimens_or_extra_training_are_refused_before_any_job(campaign, tmp_path, capsys):
    root, doc = campaign
    write_yaml(root, doc)
    assert main(["check", str(root)]) == 0 and "no specimens" not in capsys.readouterr().out
    del doc["specimens"]
    write_yaml(root, doc)
    config = {**read_config(), "campaign": str(root), "processed": str(tmp_path / "out")}
    with pytest.raises(CampaignError) as raised:
        Plan.read(root, config)
    message = str(raised.value)
    assert message.startswith(f"{root.resolve() / 'campaign.yaml'}: specimens: none")
    assert "nothing to train the classifier of the scenes (T1) on" in message and "extra_training" in message
    assert Plan.read(root, {**config, "extra_training": ["other/training.zarr"]}).campaign.specimens == {}
    assert not (tmp_path / "out").exists()
    # surffin check validates the campaign alone, and says what the workflow will need
    assert main(["check", str(root)]) == 0 and "no specimens: the workflow runs it only with extra_training" in (
        capsys.readouterr().out
    )


def test_surffin_check_reads_every_view_s_pixels(campaign, capsys):
    root, doc = campaign
    write_yaml(root, doc)
    camp = read_campaign(root)
    views = [*(view for item in camp.items.values() for view in item.views), *camp.calibration.wall]
    views += camp.calibration.reference.views
    assert main(["check", str(root)]) == 0
    assert f"is valid (the pixels of its {len(views)} view files read)" in capsys.readouterr().out
    arrays = dict(np.load(views[0]))
    arrays["intensity"][np.isfinite(arrays["xyz"]).all(axis=-1)] = -2.0
    np.savez(views[0], **arrays)
    assert main(["check", str(root)]) == 2
    assert f"{views[0]}: intensity is NaN, infinite or negative on " in capsys.readouterr().err


def test_check_pixels_names_the_broken_files_in_the_order_of_the_views(campaign, synthetic_view, monkeypatch):
    root, doc = campaign
    write_yaml(root, doc)
    camp = read_campaign(root)
    views = camp.view_files[::-1]  # any order: the files are read in threads, and named in this one
    assert len(views) == 11 and campaign_module.PIXEL_READERS > 1
    assert list(check_pixels(camp, views)["views"]) == [str(view) for view in views]
    xyz, intensity, _ = synthetic_view
    broken = [*views[1:4], *views[7::2]]  # every form: npz, ply and raw
    assert {view.suffix for view in broken} == {".npz", ".ply", ".raw"}
    for view in broken:
        write_view(view, np.full_like(xyz, np.nan), intensity)
    # the first broken file is done last: its check waits for the last view's
    last_done = threading.Event()

    def first_broken_last(path, **camera):
        if path == str(broken[0]):
            assert last_done.wait(timeout=30)
        try:
            check_view_pixels(path, **camera)
        finally:
            if path == str(views[-1]):
                last_done.set()

    monkeypatch.setattr(campaign_module, "check_view_pixels", first_broken_last)
    monkeypatch.setattr(campaign_module, "SHOWN_BROKEN", 3)
    with pytest.raises(ViewFileError) as raised:
        check_pixels(camp, views)
    assert last_done.is_set()
    assert str(raised.value).splitlines() == [
        f"5 of {len(views)} view files break the campaign contract:",
        *(f"{view}: no valid pixel (every pixel has xyz NaN or z <= 0); expected at least one" for view in broken[:3]),
        "... and 2 more",
    ]


# --- an external calibration store acquired with other settings ------------------------------------------


def test_external_calibration_without_recorded_settings_is_refused_naming_the_store(campaign, tmp_path):
    root, doc = campaign
    settings_in({})(root, doc)  # every view: exposure_us 250, gain 2
    doc.pop("calibration", None)
    doc["camera"]["match_settings"] = ["exposure_us"]
    write_yaml(root, doc)
    # a calibration store of the campaign's 8 x 6 sensor, made by hand, that records no settings
    coef = xr.DataArray(np.ones((5, 6, 8)), dims=("term", "y", "x"), coords={"y": np.arange(6), "x": np.arange(8)})
    store = write_store(
        xr.Dataset({"coef": coef}, attrs={"surffin_stage": "calibration", "scale_k": 1.0}), tmp_path / "cal.zarr"
    )
    with pytest.raises(StoreError) as raised:
        Plan.read(root, {**read_config(), "campaign": str(root), "calibration_store": str(store)})
    message = str(raised.value)
    assert message.startswith(f"{store}: the calibration records no acquisition settings, but ")
    assert f"{root.resolve() / 'campaign.yaml'} asks camera.match_settings ['exposure_us'] to match" in message
