import csv
import io

import numpy as np
import pytest
from PIL import Image
from plyfile import PlyData

from surffin.cli import main
from surffin.io.store import open_store
from surffin.method.classify import UNCLASSIFIED, UNCLASSIFIED_REASONS
from surffin.report.export import PLY_FIELDS, class_areas, label_png, pixel_area
from surffin.report.figures import class_colours


def tilted_plane(tilt_deg):
    """Unit normal (facing the camera) of a plane tilted about the camera's y axis."""
    tilt = np.radians(tilt_deg)
    return np.array([np.sin(tilt), 0.0, -np.cos(tilt)])


def rays_on_plane(rays, normal, distance):
    """Where rays from the camera centre meet the plane through (0, 0, distance) with this normal."""
    return rays * ((distance * normal[2]) / (rays @ normal))[..., None]


def plane_view(fx=500.0, fy=520.0, width=64, height=48, distance=0.6, tilt_deg=35.0):
    """A pinhole camera looking at a tilted plane: each pixel's point and angle of incidence."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    rays = np.stack([(u - (width - 1) / 2) / fx, (v - (height - 1) / 2) / fy, np.ones_like(u)], axis=-1)
    normal = tilted_plane(tilt_deg)
    cos_aoi = -(rays @ normal) / np.linalg.norm(rays, axis=-1)
    return rays_on_plane(rays, normal, distance), np.arccos(cos_aoi)


def corner_polygon_area(fx, fy, width, height, distance, tilt_deg):
    """The area of the plane the whole sensor sees: the quadrilateral of the outer pixel corners' rays."""
    corners = [(-0.5, -0.5), (width - 0.5, -0.5), (width - 0.5, height - 0.5), (-0.5, height - 0.5)]
    rays = np.array([[(u - (width - 1) / 2) / fx, (v - (height - 1) / 2) / fy, 1.0] for u, v in corners])
    a, b, c, d = rays_on_plane(rays, tilted_plane(tilt_deg), distance)
    return 0.5 * np.linalg.norm(np.cross(c - a, d - b))


@pytest.mark.parametrize("tilt", [0.0, 35.0, 60.0])
def test_pixel_areas_add_up_to_the_plane_the_sensor_sees(tilt):
    points, aoi = plane_view(tilt_deg=tilt)
    area = pixel_area(points, aoi, 500.0, 520.0)
    expected = corner_polygon_area(500.0, 520.0, 64, 48, 0.6, tilt)
    assert area.sum() == pytest.approx(expected, rel=2e-3)


def test_pixel_area_is_nan_without_a_point():
    points, aoi = plane_view()
    points[0, 0] = np.nan
    aoi[1, 1] = np.nan
    area = pixel_area(points, aoi, 500.0, 520.0)
    assert np.isnan(area[0, 0]) and np.isnan(area[1, 1]) and np.isfinite(area).sum() == area.size - 2


def test_class_areas_match_a_brute_force_count():
    rng = np.random.default_rng(3)
    classes = ["fine", "rough", "smooth"]
    label = rng.integers(-1, 3, (30, 40)).astype(np.int16)
    reason = np.where(label == UNCLASSIFIED, rng.integers(1, 4, label.shape), 0)
    area = rng.random(label.shape)
    area[0, :5] = np.nan
    rows = {row["class"]: row for row in class_areas(label, reason, area, classes)}
    assert sum(row["pixels"] for row in rows.values()) == label.size
    for index, name in enumerate(classes):
        picked = [area[y, x] for y in range(30) for x in range(40) if label[y, x] == index]
        assert rows[name]["area_m2"] == pytest.approx(np.nansum(picked))
        assert rows[name]["pixels_without_area"] == int(np.isnan(picked).sum())
    for code, name in enumerate(UNCLASSIFIED_REASONS, start=1):
        assert rows[f"unclassified: {name}"]["pixels"] == int(((label == -1) & (reason == code)).sum())


def test_label_png_is_indexed_with_the_figure_colours():
    classes = ["S1", "S2", "S3"]
    label = np.array([[-1, 0, 1], [2, 2, -1]], dtype=np.int16)
    image = Image.open(io.BytesIO(label_png(label, classes)))
    assert image.mode == "P" and image.size == (3, 2)
    np.testing.assert_array_equal(np.asarray(image), label + 1)
    palette = np.array(image.getpalette()[: 3 * (len(classes) + 1)]).reshape(-1, 3)
    assert palette[0].tolist() == [0, 0, 0]
    colours = class_colours(classes)
    for index, name in enumerate(classes, start=1):
        assert palette[index].tolist() == [round(255 * c) for c in colours[name][:3]]


@pytest.mark.slow  # reads the session's complete run of the tiny campaign
def test_export_of_a_run(tiny_run, tmp_path):
    processed = tiny_run / "processed"
    out = tmp_path / "export"
    assert main(["export", str(processed), str(out)]) == 0
    labels = open_store(processed / "labels" / "T1.zarr").compute()
    classes = labels["label"].attrs["flag_meanings"].split()
    # the label image at sensor resolution (the crop), its values the filtered labels + 1
    image = np.asarray(Image.open(out / "T1-labels.png"))
    np.testing.assert_array_equal(image, labels["label_filtered"].values + 1)
    assert (out / "T1-labels-legend.png").stat().st_size > 0
    rows = list(csv.DictReader((out / "T1-classes.csv").open()))
    assert [row["class"] for row in rows[: len(classes)]] == classes
    assert sum(int(row["pixels"]) for row in rows) == labels["label_filtered"].size
    # the tiny scene is 0.6-0.7 m away, 60 x 40 px of a camera with fx = 70.6, fy = 72.4:
    # about 9 mm pixels, at most 0.25 m² in all
    total = sum(float(row["area_m2"]) for row in rows)
    assert 0.1 < total < 0.3
    assert (out / "T1-report.pdf").read_bytes().startswith(b"%PDF")
    # the workflow's export rule wrote the same table
    assert (processed / "export" / "T1-classes.csv").read_text() == (out / "T1-classes.csv").read_text()
    for name in ("T1", "S1", "S2", "S3", "S4"):
        ply = PlyData.read(str(out / f"{name}.ply"))
        assert ply.header.split("\n")[1].startswith("format binary_little_endian")
        vertex = ply["vertex"]
        names = [prop.name for prop in vertex.properties]
        # CloudCompare reads scalar_* as scalar fields; Open3D keeps them as attributes
        assert names == ["x", "y", "z", *(f"scalar_{field}" for field in PLY_FIELDS)]
        ingest = open_store(processed / "ingest" / f"{name}.zarr")
        grid = open_store(processed / "features" / f"{name}.zarr")
        # the reference view's valid points where the item has features: a specimen's roi and margin, a scene's crop
        reference = ingest.sel(view=ingest.attrs["reference_view"], y=grid["y"], x=grid["x"])
        assert vertex.count == int(reference["valid"].sum())
        assert (reference.sizes["y"] < ingest.sizes["y"]) == (name != "T1")
        if name == "T1":  # posed views: the points are in the world frame
            pose = reference["pose"].values
            first = reference["xyz"].values[reference["valid"].values][0]
            expected = pose[:3, :3] @ first + pose[:3, 3]
            np.testing.assert_allclose([vertex["x"][0], vertex["y"][0], vertex["z"][0]], expected, atol=1e-5)
    specimen = PlyData.read(str(out / "S2.ply"))["vertex"]
    assert set(np.unique(specimen["scalar_class"])) == {classes.index("S2")}


def test_export_of_nothing_names_the_missing_store(tmp_path, capsys):
    assert main(["export", str(tmp_path / "none"), str(tmp_path / "out")]) == 2
    assert "training.zarr" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
