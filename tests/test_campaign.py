"""Tests of surffin.io.campaign: read_campaign's validation and read_truth."""

import numpy as np
import pytest
import yaml

from surffin.errors import CampaignError
from surffin.grid import Roi
from surffin.io.campaign import Camera, read_campaign, read_truth
from surffin.io.viewfile import ABCY16_DEFAULT, write_view

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
    assert camp.camera.abcy16 == {"scale": 0.5, "offset": ABCY16_DEFAULT["offset"]}
    assert camp.specimens["S1"].roi == Roi((0, 4), (2, 8))
    view = camp.read_view(camp.specimens["S1"].views[0])
    assert np.nanmin(view.xyz[..., 2]) < 0.001  # the metre values were read as mm


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
