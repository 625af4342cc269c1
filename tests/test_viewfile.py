"""Tests of surffin.io.viewfile: the three view forms, poses, validation and listing."""

import numpy as np
import plyfile
import pytest
from scipy.spatial.transform import Rotation

from surffin.errors import ViewFileError
from surffin.io.viewfile import (
    META_SUFFIX,
    POSE_JSON_SUFFIX,
    check_view,
    check_view_pixels,
    list_views,
    pose_sidecar_path,
    read_settings,
    read_view,
    sidecar_path,
    valid_pixels,
    write_view,
)

RAW_QUANTUM_M = 0.125e-3 + 1e-12
"""Worst rounding error of an ABCY16 coordinate with scale 0.25 mm, in metres."""


def rigid_pose(translation=(0.1, -0.2, 0.3), angle=0.4) -> np.ndarray:
    """A camera-to-world transform: rotation about y, then ``translation`` (metres)."""
    cos, sin = np.cos(angle), np.sin(angle)
    pose = np.eye(4)
    pose[:3, :3] = [[cos, 0.0, sin], [0.0, 1.0, 0.0], [-sin, 0.0, cos]]
    pose[:3, 3] = translation
    return pose


def snapshot(folder):
    """Names, sizes and modification times of a folder's files."""
    return {path.name: (path.stat().st_size, path.stat().st_mtime_ns) for path in folder.iterdir()}


def vertex_element(columns: dict[str, np.ndarray]) -> plyfile.PlyElement:
    """A PLY ``vertex`` element from named 1-D columns (their dtypes become the property types)."""
    size = len(next(iter(columns.values())))
    vertices = np.empty(size, dtype=[(name, column.dtype) for name, column in columns.items()])
    for name, column in columns.items():
        vertices[name] = column
    return plyfile.PlyElement.describe(vertices, "vertex")


# --- round trips and independent decoding ---------------------------------------------------------


@pytest.mark.parametrize(
    ("name", "options"),
    [
        pytest.param("v.npz", {"units": "m"}, id="npz-m"),
        pytest.param("v.npz", {"units": "mm"}, id="npz-mm"),
        pytest.param("v.npz", {"units": "m", "pose_sidecar": True}, id="npz-m-sidecar"),
        pytest.param("v.ply", {"units": "m"}, id="ply-binary-m"),
        pytest.param("v.ply", {"units": "mm", "binary": False}, id="ply-ascii-mm"),
        pytest.param("v.raw", {}, id="raw"),
    ],
)
def test_round_trip(tmp_path, synthetic_view, sensor, name, options):
    xyz, intensity, valid = synthetic_view
    pose = rigid_pose()
    path = tmp_path / name
    write_view(path, xyz, intensity, pose=pose, **options)
    view = read_view(path, units=options.get("units", "m"), **sensor)
    raw = path.suffix == ".raw"

    assert view.path == path
    np.testing.assert_array_equal(view.valid, valid)
    assert view.xyz.dtype == np.float64 and view.intensity.dtype == np.float32
    np.testing.assert_allclose(view.xyz[valid], xyz[valid], rtol=0, atol=RAW_QUANTUM_M if raw else 1e-6)
    np.testing.assert_allclose(view.intensity[valid], intensity[valid], rtol=0 if raw else 1e-6, atol=0.5 if raw else 0)
    assert np.isnan(view.xyz[~valid]).all() and (view.intensity[~valid] == 0).all()
    np.testing.assert_allclose(view.pose, pose, rtol=0, atol=1e-12)
    in_sidecar = path.suffix != ".npz" or options.get("pose_sidecar", False)
    assert pose_sidecar_path(path).exists() == in_sidecar
    check_view(path, units=options.get("units", "m"), **sensor)


def test_view_without_pose(tmp_path, synthetic_view, sensor):
    xyz, intensity, _ = synthetic_view
    write_view(tmp_path / "v.ply", xyz, intensity)
    assert read_view(tmp_path / "v.ply", **sensor).pose is None
    assert sorted(snapshot(tmp_path)) == ["v.ply"]


@pytest.mark.parametrize("name", ["v.npz", "v.ply"])
def test_units_scale_xyz_and_pose(tmp_path, synthetic_view, sensor, name):
    xyz, intensity, valid = synthetic_view
    write_view(tmp_path / name, xyz, intensity, units="mm", pose=rigid_pose())
    as_metres = read_view(tmp_path / name, units="m", **sensor)
    np.testing.assert_allclose(as_metres.xyz[valid], 1000 * xyz[valid], rtol=1e-6)
    np.testing.assert_allclose(as_metres.pose[:3, 3], 1000 * rigid_pose()[:3, 3])


def test_raw_decodes_coord3d_abcy16(tmp_path, sensor):
    height, width = sensor["height"], sensor["width"]
    channels = np.zeros((height, width, 4), dtype="<u2")
    channels[..., 0] = 32768 + np.arange(width)
    channels[..., 1] = 30000 + np.arange(height)[:, None]
    channels[..., 2] = 4000
    channels[..., 3] = 500
    channels[1, 1, 2] = 65535
    channels[2, 3, 0] = 65535
    path = tmp_path / "v.raw"
    path.write_bytes(channels.tobytes())

    view = read_view(path, **sensor)
    expected_valid = np.ones((height, width), dtype=bool)
    expected_valid[1, 1] = expected_valid[2, 3] = False
    np.testing.assert_array_equal(view.valid, expected_valid)
    np.testing.assert_allclose(view.xyz[0, 5], [5 * 0.25e-3, (30000 * 0.25 - 8192) * 1e-3, 1.0])
    assert (view.intensity[expected_valid] == 500).all()

    custom = read_view(path, abcy16={"scale": 0.5, "offset": (0.0, 0.0, 10.0)}, **sensor)
    np.testing.assert_allclose(custom.xyz[0, 5], [(32773 * 0.5) * 1e-3, 15.0, 2.01])


def test_ply_big_endian_with_extra_properties_and_elements(tmp_path, synthetic_view, sensor):
    xyz, intensity, valid = synthetic_view
    flat = xyz.reshape(-1, 3)
    vertex = vertex_element(
        {
            "confidence": np.full(len(flat), 7, dtype=np.uint8),
            "x": flat[:, 0],
            "y": flat[:, 1],
            "z": flat[:, 2],
            "intensity": np.rint(intensity).astype(np.uint16).ravel(),
        }
    )
    faces = plyfile.PlyElement.describe(np.array([([0, 1, 2],)], dtype=[("vertex_indices", "i4", (3,))]), "face")
    path = tmp_path / "v.ply"
    plyfile.PlyData([vertex, faces], byte_order=">", comments=["made by hand"]).write(path)

    view = read_view(path, **sensor)
    np.testing.assert_array_equal(view.valid, valid)
    np.testing.assert_allclose(view.xyz[valid], xyz[valid], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(view.intensity[valid], np.rint(intensity)[valid])


def test_npz_with_integer_intensity_and_extra_array(tmp_path, synthetic_view, sensor):
    xyz, intensity, valid = synthetic_view
    path = tmp_path / "v.npz"
    np.savez(path, xyz=xyz.astype(np.float32), intensity=np.rint(intensity).astype(np.uint16), note=np.arange(3))
    view = read_view(path, **sensor)
    np.testing.assert_array_equal(view.intensity[valid], np.rint(intensity)[valid])
    assert view.pose is None


@pytest.mark.parametrize(("binary", "header_line"), [(True, b"binary_little_endian 1.0"), (False, b"ascii 1.0")])
def test_ply_writer_format(tmp_path, synthetic_view, binary, header_line):
    xyz, intensity, _ = synthetic_view
    write_view(tmp_path / "v.ply", xyz, intensity, binary=binary)
    assert b"format " + header_line + b"\n" in (tmp_path / "v.ply").read_bytes()[:200]


# --- vendor formats, written by other means than write_view ---------------------------------------

ABCY16_PIXEL = np.dtype([("a", "<i2"), ("b", "<i2"), ("c", "<i2"), ("y", "<u2")])
ABCY16_PIXEL_UNSIGNED = np.dtype([("a", "<u2"), ("b", "<u2"), ("c", "<u2"), ("y", "<u2")])


def abcy16_bytes(sensor, a, b, c, y, *, signed):
    """A Coord3D_ABCY16(s) buffer from channel images, packed field by field."""
    pixels = np.zeros((sensor["height"], sensor["width"]), dtype=ABCY16_PIXEL if signed else ABCY16_PIXEL_UNSIGNED)
    for name, channel in zip("abcy", (a, b, c, y)):
        pixels[name] = channel
    return pixels.tobytes()


def lateral_codes(sensor, scale=(0.25, 0.25)):
    """A and B codes (signed) of a scene about 1 m in front of the camera: x, y within +-0.2 m."""
    rows, cols = np.mgrid[0 : sensor["height"], 0 : sensor["width"]]
    return np.rint((cols - 4) * 40 / scale[0]).astype(int), np.rint((rows - 3) * 40 / scale[1]).astype(int)


def test_raw_signed_abcy16s_with_per_axis_scale(tmp_path, sensor):
    scale = (0.25, 0.5, 0.125)
    a, b = lateral_codes(sensor, scale)
    c = np.full(a.shape, 8000)  # 1000 mm
    c[1, 1] = -32768
    a[2, 3] = -32768
    path = tmp_path / "v.raw"
    path.write_bytes(abcy16_bytes(sensor, a, b, c, 700, signed=True))
    abcy16 = {"signed": True, "scale": list(scale)}

    check_view(path, abcy16=abcy16, **sensor)
    view = read_view(path, abcy16=abcy16, **sensor)
    expected_valid = np.ones(a.shape, dtype=bool)
    expected_valid[1, 1] = expected_valid[2, 3] = False
    np.testing.assert_array_equal(view.valid, expected_valid)
    np.testing.assert_allclose(view.xyz[0, 0], [-0.16, -0.12, 1.0])  # offset [0, 0, 0]: the signed default
    np.testing.assert_allclose(view.xyz[5, 7], [0.12, 0.08, 1.0])
    assert (view.intensity[expected_valid] == 700).all()


def test_raw_unsigned_with_per_axis_scale_and_offset(tmp_path, sensor):
    a, b = lateral_codes(sensor, (0.5, 0.25))
    abcy16 = {"scale": [0.5, 0.25, 0.25], "offset": [-16384.0, -8192.0, 0.0]}
    path = tmp_path / "v.raw"
    path.write_bytes(abcy16_bytes(sensor, a + 32768, b + 32768, 4000, 9, signed=False))
    view = read_view(path, abcy16=abcy16, **sensor)
    assert view.valid.all()
    np.testing.assert_allclose(view.xyz[0, 0], [-0.16, -0.12, 1.0])


@pytest.mark.parametrize("signed", [True, False])
def test_raw_of_the_other_signedness_is_refused(tmp_path, sensor, signed):
    """A file written as one form and read as the other: x, y near +-8192 mm; refused naming the file."""
    a, b = lateral_codes(sensor)
    path = tmp_path / "v.raw"
    if signed:  # an ABCY16s file (offset 0) read as unsigned ABCY16
        path.write_bytes(abcy16_bytes(sensor, a, b, 4000, 500, signed=True))
    else:  # an ABCY16 file (offset -8192) read as signed ABCY16s
        path.write_bytes(abcy16_bytes(sensor, a + 32768, b + 32768, 4000, 500, signed=False))
    read_as = {"signed": not signed}
    match = (
        rf"v\.raw: looks like Coord3D_ABCY16{'s' if signed else ''} data, not Coord3D_ABCY16{'' if signed else 's'} "
        rf"\(camera\.abcy16\.signed: {str(not signed).lower()}\).*set camera\.abcy16\.signed: {str(signed).lower()}"
    )
    with pytest.raises(ViewFileError, match=match) as raised:
        check_view(path, abcy16=read_as, **sensor)
    assert str(path) in str(raised.value)
    with pytest.raises(ViewFileError, match=match):
        read_view(path, abcy16=read_as, **sensor)
    assert read_view(path, abcy16={"signed": signed}, **sensor).valid.all()


def test_signed_invalid_marker_read_as_unsigned_is_refused(tmp_path, sensor):
    """Most pixels invalid (-32768 in A, B, C): read as unsigned they become (0, 0, 8192 mm) points."""
    a, b = lateral_codes(sensor)
    c = np.full(a.shape, 4000)
    a[2:], b[2:], c[2:] = -32768, -32768, -32768
    path = tmp_path / "v.raw"
    path.write_bytes(abcy16_bytes(sensor, a, b, c, 500, signed=True))
    with pytest.raises(ViewFileError, match=r"v\.raw: looks like Coord3D_ABCY16s data.*invalid marker") as raised:
        read_view(path, **sensor)
    assert str(raised.value).startswith(f"{path}: ")
    assert read_view(path, abcy16={"signed": True}, **sensor).valid.sum() == 2 * sensor["width"]


def test_write_view_signed_raw_round_trip(tmp_path, synthetic_view, sensor):
    xyz, intensity, valid = synthetic_view
    xyz = xyz.copy()
    xyz[..., 0] -= 0.2  # negative x: codes below zero
    path = tmp_path / "v.raw"
    abcy16 = {"signed": True, "scale": [0.25, 0.25, 0.125]}
    write_view(path, xyz, intensity, abcy16=abcy16)
    pixels = np.frombuffer(path.read_bytes(), dtype=ABCY16_PIXEL).reshape(xyz.shape[:2])
    assert (pixels["a"][~valid] == -32768).all() and (pixels["a"][valid] < 0).any()
    np.testing.assert_array_equal(pixels["c"][valid], np.rint(xyz[valid][:, 2] * 1000 / 0.125))
    view = read_view(path, abcy16=abcy16, **sensor)
    np.testing.assert_array_equal(view.valid, valid)
    np.testing.assert_allclose(view.xyz[valid], xyz[valid], rtol=0, atol=RAW_QUANTUM_M)
    with pytest.raises(ValueError, match=r"ABCY16 codes .*expected -32767\.\.32767"):
        write_view(path, np.full_like(xyz, 9.0), intensity, abcy16={"signed": True})


def ply_file(header, rows, *, newline=b"\n", binary_rows=None):
    """PLY bytes from header lines and either ascii rows (lists of numbers) or a binary body."""
    text = newline.join(line.encode("ascii") for line in ["ply", *header, "end_header"]) + newline
    if binary_rows is not None:
        return text + binary_rows
    return text + b"".join(" ".join(f"{value:.9g}" for value in row).encode("ascii") + newline for row in rows)


def cloudcompare_header(count):
    return [
        "format ascii 1.0",
        "comment Created by CloudCompare v2.12.4",
        "obj_info Generated by CloudCompare!",
        f"element vertex {count}",
        "property float x",
        "property float y",
        "property float z",
        "property uchar red",
        "property uchar green",
        "property uchar blue",
        "property float scalar_Intensity",
    ]


@pytest.mark.parametrize("newline", [b"\n", b"\r\n", b"\r"], ids=["lf", "crlf", "cr"])
def test_ply_as_cloudcompare_writes_it(tmp_path, synthetic_view, sensor, newline):
    xyz, intensity, valid = synthetic_view
    flat = xyz.reshape(-1, 3)  # NaN written as nan
    rows = [[*point, 10, 20, 30, level] for point, level in zip(flat, intensity.ravel())]
    path = tmp_path / "v.ply"
    path.write_bytes(ply_file(cloudcompare_header(len(rows)), rows, newline=newline))
    check_view(path, **sensor)
    view = read_view(path, **sensor)
    np.testing.assert_array_equal(view.valid, valid)
    np.testing.assert_allclose(view.xyz[valid], xyz[valid], rtol=1e-6)
    np.testing.assert_allclose(view.intensity[valid], intensity[valid], rtol=1e-6)


@pytest.mark.parametrize("newline", [b"\n", b"\r"], ids=["lf", "cr"])
def test_ply_as_open3d_writes_it(tmp_path, synthetic_view, sensor, newline):
    xyz, intensity, valid = synthetic_view
    header = [
        "format binary_little_endian 1.0",
        "comment Created by Open3D",
        f"element vertex {xyz.shape[0] * xyz.shape[1]}",
        *(f"property double {name}" for name in ("x", "y", "z", "nx", "ny", "nz", "intensities")),
    ]
    table = np.column_stack([xyz.reshape(-1, 3), np.zeros((xyz.shape[0] * xyz.shape[1], 3)), intensity.ravel()])
    path = tmp_path / "v.ply"
    path.write_bytes(ply_file(header, None, newline=newline, binary_rows=table.astype("<f8").tobytes()))
    check_view(path, **sensor)
    view = read_view(path, **sensor)
    np.testing.assert_array_equal(view.valid, valid)
    np.testing.assert_allclose(view.xyz[valid], xyz[valid], rtol=0, atol=1e-15)
    np.testing.assert_allclose(view.intensity[valid], intensity[valid], rtol=1e-7)


def test_ply_intensity_property_named_by_the_camera(tmp_path, synthetic_view, sensor):
    xyz, intensity, valid = synthetic_view
    flat = xyz.reshape(-1, 3)
    path = tmp_path / "v.ply"
    columns = {"x": flat[:, 0], "y": flat[:, 1], "z": flat[:, 2], "intensity": np.zeros(len(flat), "u2")}
    columns["reflectance"] = intensity.ravel().astype("f4")
    plyfile.PlyData([vertex_element(columns)]).write(path)
    assert (read_view(path, **sensor).intensity == 0).all()
    named = read_view(path, ply_intensity="reflectance", **sensor)
    np.testing.assert_allclose(named.intensity[valid], intensity[valid], rtol=1e-6)
    del columns["intensity"], columns["reflectance"]
    columns["intensities"] = intensity.ravel()
    plyfile.PlyData([vertex_element(columns)]).write(path)
    fallback = read_view(path, ply_intensity="reflectance", **sensor)  # absent: Open3D's name is taken
    np.testing.assert_allclose(fallback.intensity[valid], intensity[valid], rtol=1e-7)


def test_ply_with_filtered_points_is_refused(tmp_path, synthetic_view, sensor):
    """An Arena SDK export with filterPoints on keeps only the valid pixels."""
    xyz, intensity, valid = synthetic_view
    kept = np.column_stack([xyz[valid], intensity[valid]])
    header = ["format binary_little_endian 1.0", "comment Lucid Vision Labs", f"element vertex {len(kept)}"]
    header += [f"property float {name}" for name in ("x", "y", "z", "intensity")]
    path = tmp_path / "v.ply"
    path.write_bytes(ply_file(header, None, binary_rows=kept.astype("<f4").tobytes()))
    match = r"v\.ply: 44 vertices, fewer than width\*height = 8\*6 = 48.*filterPoints on.*turn filterPoints off"
    for read in (check_view, read_view):
        with pytest.raises(ViewFileError, match=match) as raised:
            read(path, **sensor)
        assert str(raised.value).startswith(f"{path}: ")


# --- pose and settings sidecars -----------------------------------------------------------------


def write_json(path, text):
    path.write_text(text)
    return path


def test_pose_json_sidecar_against_scipy_and_hand_eye(tmp_path, synthetic_view, sensor):
    xyz, intensity, _ = synthetic_view
    path = tmp_path / "v.npz"
    write_view(path, xyz, intensity, units="mm")
    quaternion = np.array([0.9, -0.1, 0.3, 0.2])  # not quite unit: normalised
    quaternion *= 1.0005 / np.linalg.norm(quaternion)
    write_json(
        sidecar_path(path, POSE_JSON_SUFFIX), f'{{"translation": [100, -20, 350], "quaternion": {quaternion.tolist()}}}'
    )
    flange = np.eye(4)
    flange[:3, :3] = Rotation.from_quat(quaternion, scalar_first=True).as_matrix()
    flange[:3, 3] = [100, -20, 350]

    view = read_view(path, units="mm", **sensor)
    expected = flange.copy()
    expected[:3, 3] /= 1000
    np.testing.assert_allclose(view.pose, expected, atol=1e-12)

    hand_eye = rigid_pose(translation=(5.0, 0.0, 60.0), angle=0.1)  # mm, as the pose
    camera = read_view(path, units="mm", hand_eye=hand_eye, **sensor).pose
    expected = flange @ hand_eye
    expected[:3, 3] /= 1000
    np.testing.assert_allclose(camera, expected, atol=1e-12)


def test_settings_sidecar(tmp_path, synthetic_view, sensor):
    xyz, intensity, _ = synthetic_view
    path = tmp_path / "v.ply"
    write_view(path, xyz, intensity)
    assert read_settings(path) == {} and read_view(path, **sensor).settings == {}
    settings = {"exposure_us": 250, "gain": "low", "accumulation": 4, "temperature_c": 41.2}
    write_json(
        sidecar_path(path, META_SUFFIX), '{"exposure_us": 250, "gain": "low", "accumulation": 4, "temperature_c": 41.2}'
    )
    assert read_settings(path) == settings and read_view(path, **sensor).settings == settings


def test_saturated_pixels(tmp_path, synthetic_view, sensor):
    xyz, intensity, valid = synthetic_view
    path = tmp_path / "v.npz"
    write_view(path, xyz, intensity)
    assert read_view(path, **sensor).saturated is None
    view = read_view(path, saturation=500.0, **sensor)
    np.testing.assert_array_equal(view.saturated, valid & (intensity >= 500.0))
    np.testing.assert_array_equal(view.radiometric, valid & (intensity < 500.0))
    assert 0 < view.saturated.sum() < valid.sum()
    np.testing.assert_array_equal(view.intensity[view.saturated], intensity[view.saturated].astype(np.float32))


def test_rewrite_removes_stale_pose_json(tmp_path, synthetic_view, sensor):
    xyz, intensity, _ = synthetic_view
    path = tmp_path / "v.npz"
    write_view(path, xyz, intensity)
    write_json(sidecar_path(path, POSE_JSON_SUFFIX), '{"translation": [0, 0, 0], "quaternion": [1, 0, 0, 0]}')
    write_view(path, xyz, intensity, pose=rigid_pose())
    assert sorted(snapshot(tmp_path)) == ["v.npz"]
    np.testing.assert_allclose(read_view(path, **sensor).pose, rigid_pose())


# --- broken files -------------------------------------------------------------------------------


def npz_with(**changes):
    """Maker of an npz holding the synthetic arrays, with ``changes`` (None removes an array)."""

    def make(folder, xyz, intensity):
        arrays = {"xyz": xyz, "intensity": intensity, **changes}
        path = folder / "v.npz"
        np.savez(path, **{name: array for name, array in arrays.items() if array is not None})
        return path, path

    return make


def npz_with_pose(pose):
    return npz_with(pose=np.asarray(pose))


def pose_with(row, col, value):
    pose = rigid_pose()
    pose[row, col] = value
    return pose


def pose_scaled(factor):
    pose = rigid_pose()
    pose[:3, :3] *= factor
    return pose


def written(name, **options):
    """Maker of a view written by write_view."""

    def make(folder, xyz, intensity):
        path = folder / name
        write_view(path, xyz, intensity, **options)
        return path, path

    return make


def edited(make_view, edit):
    """Maker: ``make_view``, then ``edit(path)`` of the file it wrote."""

    def make(folder, xyz, intensity):
        path, named = make_view(folder, xyz, intensity)
        edit(path)
        return path, named

    return make


def truncated(size_change):
    def edit(path):
        path.write_bytes(path.read_bytes()[:size_change])

    return edit


def replaced(old, new):
    def edit(path):
        path.write_bytes(path.read_bytes().replace(old, new, 1))

    return edit


def sidecar_text(text):
    """Maker of a ply view whose pose sidecar holds ``text``."""

    def make(folder, xyz, intensity):
        path = folder / "v.ply"
        write_view(path, xyz, intensity)
        pose_sidecar_path(path).write_text(text)
        return path, pose_sidecar_path(path)

    return make


def json_sidecar(suffix, text, name="v.ply", pose=None):
    """Maker of a view with the JSON sidecar ``<stem><suffix>`` holding ``text``."""

    def make(folder, xyz, intensity):
        path = folder / name
        write_view(path, xyz, intensity, pose=pose)
        return path, write_json(sidecar_path(path, suffix), text)

    return make


def two_pose_sidecars(folder, xyz, intensity):
    path = folder / "v.ply"
    write_view(path, xyz, intensity, pose=rigid_pose())
    write_json(sidecar_path(path, POSE_JSON_SUFFIX), '{"translation": [0, 0, 0], "quaternion": [1, 0, 0, 0]}')
    return path, sidecar_path(path, POSE_JSON_SUFFIX)


def ply_of(**changes):
    """Maker of a binary PLY of the synthetic arrays, with ``changes`` (None removes a property)."""

    def make(folder, xyz, intensity):
        columns = {"x": xyz[..., 0], "y": xyz[..., 1], "z": xyz[..., 2], "intensity": intensity, **changes}
        path = folder / "v.ply"
        kept = {name: np.ravel(column) for name, column in columns.items() if column is not None}
        plyfile.PlyData([vertex_element(kept)]).write(path)
        return path, path

    return make


def file_bytes(name, content):
    def make(folder, xyz, intensity):
        path = folder / name
        path.write_bytes(content)
        return path, path

    return make


def with_arrays(transform, name="v.npz"):
    """Maker of a view written from ``transform(xyz, intensity)``."""

    def make(folder, xyz, intensity):
        path = folder / name
        write_view(path, *transform(xyz.copy(), intensity.copy()))
        return path, path

    return make


def intensity_set(value, pixels):
    def transform(xyz, intensity):
        for pixel in pixels:
            intensity[pixel] = value
        return xyz, intensity

    return transform


def all_invalid(xyz, intensity):
    return np.zeros_like(xyz), intensity


def rows_invalid(xyz, intensity, rows):
    xyz[rows] = 0.0
    return xyz, intensity


def pose_in_npz_and_sidecar(folder, xyz, intensity):
    path = folder / "v.npz"
    write_view(path, xyz, intensity, pose=rigid_pose())
    pose_sidecar_path(path).write_text("1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1")
    return path, path


# (maker, message pattern, caught by the cheap check_view too)
BROKEN = {
    "npz-object-array": (npz_with(xyz=np.array([None, 1], dtype=object)), "object array", True),
    "npz-integer-xyz": (npz_with(xyz=np.ones((6, 8, 3), dtype=int)), r"'xyz' is int64.*expected a float", True),
    "npz-xyz-shape": (npz_with(xyz=np.ones((6, 7, 3))), r"'xyz' is float64 of shape \(6, 7, 3\)", True),
    "npz-no-intensity": (npz_with(intensity=None), r"no array 'intensity'", True),
    "npz-text-intensity": (npz_with(intensity=np.full((6, 8), "a")), r"'intensity' is <U1.*numeric", True),
    "npz-not-a-zip": (file_bytes("v.npz", b"not a zip archive"), "unreadable", True),
    "npz-truncated": (edited(written("v.npz"), truncated(-100)), "unreadable", True),
    "npz-pose-shape": (npz_with_pose(np.eye(4)[:3]), r"'pose' is float64 of shape \(3, 4\); expected", True),
    "npz-pose-last-row": (npz_with_pose(pose_with(3, 0, 0.5)), r"malformed pose: last row", True),
    "npz-pose-scaled": (npz_with_pose(pose_scaled(1.001)), "malformed pose: .*not a rotation", True),
    "npz-pose-mirror": (npz_with_pose(np.diag([1.0, 1.0, -1.0, 1.0])), "malformed pose: .*det -1", True),
    "npz-pose-nan": (npz_with_pose(pose_with(0, 3, np.nan)), "malformed pose: non-finite", True),
    "pose-in-npz-and-sidecar": (
        pose_in_npz_and_sidecar,
        r"2 poses given: the npz's array 'pose' and .*v\.pose\.txt; expected at most one pose per view",
        True,
    ),
    "sidecar-15-numbers": (sidecar_text("1 " * 15), "holds 15 numbers; expected 16", True),
    "sidecar-word": (sidecar_text("1 " * 15 + "one"), "unreadable pose sidecar", True),
    "sidecar-malformed": (sidecar_text("1 0 0 0 0 1 0 0 0 0 1 0 0 0 1 1"), "malformed pose: last row", True),
    "pose-txt-and-json": (
        two_pose_sidecars,
        r"2 poses given: .*v\.pose\.txt and .*v\.pose\.json; expected at most one pose per view",
        True,
    ),
    "pose-npz-and-json": (
        json_sidecar(POSE_JSON_SUFFIX, '{"translation": [0, 0, 0], "quaternion": [1, 0, 0, 0]}', "v.npz", rigid_pose()),
        r"2 poses given: the npz's array 'pose' and .*v\.pose\.json",
        True,
    ),
    "pose-json-not-unit": (
        json_sidecar(POSE_JSON_SUFFIX, '{"translation": [0, 0, 0], "quaternion": [1, 0.1, 0, 0]}'),
        r"'quaternion' \[1, 0\.1, 0, 0\] has norm 1\.00499; expected a unit quaternion \[w, x, y, z\]",
        True,
    ),
    "pose-json-zero": (
        json_sidecar(POSE_JSON_SUFFIX, '{"translation": [0, 0, 0], "quaternion": [0, 0, 0, 0]}'),
        "has norm 0; expected a unit quaternion",
        True,
    ),
    "pose-json-short": (
        json_sidecar(POSE_JSON_SUFFIX, '{"translation": [0, 0], "quaternion": [1, 0, 0, 0]}'),
        r"'translation' is \[0, 0\]; expected 3 finite numbers",
        True,
    ),
    "pose-json-matrix": (
        json_sidecar(POSE_JSON_SUFFIX, '{"matrix": [1, 0, 0, 0]}'),
        r"pose sidecar holds .*; expected \{\"translation\": \[x, y, z\], \"quaternion\": \[w, x, y, z\]\}",
        True,
    ),
    "pose-json-garbled": (
        json_sidecar(POSE_JSON_SUFFIX, '{"translation": [0, 0, 0],'),
        "unreadable pose sidecar",
        True,
    ),
    "pose-json-infinite": (
        json_sidecar(POSE_JSON_SUFFIX, '{"translation": [0, 0, 1e999], "quaternion": [1, 0, 0, 0]}'),
        r"unreadable pose sidecar \(1e999 is not a finite number\)",
        True,
    ),
    "settings-not-object": (json_sidecar(META_SUFFIX, "[250, 4]"), "settings sidecar holds list; expected one", True),
    "settings-nested": (
        json_sidecar(META_SUFFIX, '{"exposure_us": {"value": 250}}'),
        r"setting 'exposure_us' is \{'value': 250\}; expected one JSON object of setting names to numbers or strings",
        True,
    ),
    "settings-bool": (json_sidecar(META_SUFFIX, '{"hdr": true}'), "setting 'hdr' is True; expected", True),
    "settings-nan": (
        json_sidecar(META_SUFFIX, '{"gain": NaN}'),
        r"unreadable settings sidecar \(NaN is not a finite",
        True,
    ),
    "settings-repeated": (
        json_sidecar(META_SUFFIX, '{"gain": 1, "gain": 2}'),
        r"unreadable settings sidecar \(repeated key\(s\) \['gain'\]\)",
        True,
    ),
    "ply-vertex-count": (
        with_arrays(lambda x, i: (np.concatenate([x, x[:1]]), np.concatenate([i, i[:1]])), "v.ply"),
        r"56 vertices; expected width\*height = 8\*6 = 48",
        True,
    ),
    "ply-no-intensity": (
        ply_of(intensity=None),
        r"no vertex property of the intensity \(intensity, scalar_Intensity, intensities\).*camera\.ply_intensity",
        True,
    ),
    "ply-list-intensity": (
        file_bytes(
            "v.ply",
            ply_file(
                ["format ascii 1.0", "element vertex 48", *(f"property float {name}" for name in "xyz")]
                + ["property list uchar float intensity"],
                [[0.0, 0.0, 1.0, 1, 5.0]] * 48,
                newline=b"\r",
            ),
        ),
        r"vertex property 'intensity' is a list; expected a scalar numeric property",
        True,
    ),
    "ply-cr-not-ply": (file_bytes("v.ply", b"PLY\rformat ascii 1.0\r"), "does not start with the line 'ply'", True),
    "ply-integer-x": (ply_of(x=np.zeros(48, "i4")), "'x' is int32; expected a scalar float or double", True),
    "ply-truncated": (edited(written("v.ply"), truncated(-10)), "truncated PLY", True),
    "ply-garbled-ascii": (
        edited(written("v.ply", binary=False), replaced(b"end_header\nnan", b"end_header\nabc")),
        "unreadable",
        False,
    ),
    "ply-not-ply": (file_bytes("v.ply", b"hello\n"), "'ply'", True),
    "ply-big-format": (
        edited(written("v.ply"), replaced(b"binary_little_endian", b"binary_middle_endian")),
        "not understood",
        True,
    ),
    "ply-no-end-header": (file_bytes("v.ply", b"ply\nformat ascii 1.0\nelement vertex 48\n"), "end_header", True),
    "ply-two-vertex-elements": (
        edited(written("v.ply", binary=False), replaced(b"end_header", b"element vertex 0\nend_header")),
        "2 'vertex' elements; expected exactly one",
        True,
    ),
    "raw-size": (edited(written("v.raw"), truncated(-2)), r"382 bytes; expected width\*height\*8 = 384", True),
    "intensity-nan": (
        with_arrays(intensity_set(np.nan, [(0, 0), (3, 3), (4, 4)])),
        "NaN, infinite or negative on 2 of 44 valid pixels",
        False,
    ),
    "intensity-negative": (
        with_arrays(intensity_set(-1.0, [(1, 1), (3, 3), (4, 6)]), "v.ply"),
        "NaN, infinite or negative on 3 of 44 valid pixels",
        False,
    ),
    "intensity-infinite": (
        with_arrays(intensity_set(np.inf, [(2, 2)])),
        r"NaN, infinite or negative on 1 of 44 valid pixels \(first at row 2, column 2: inf\)",
        False,
    ),
    "intensity-negative-middle-row-invalid": (
        with_arrays(lambda xyz, intensity: rows_invalid(xyz, intensity_set(-2.0, [(4, 4)])(xyz, intensity)[1], [3])),
        r"NaN, infinite or negative on 1 of 36 valid pixels \(first at row 4, column 4: -2\.0\)",
        False,
    ),
    "no-valid-pixel": (with_arrays(all_invalid, "v.raw"), "no valid pixel", False),
    "no-valid-pixel-npz": (with_arrays(all_invalid), "no valid pixel", False),
    "not-a-view-suffix": (file_bytes("v.txt", b""), "not a view form", True),
    "missing-file": (lambda folder, xyz, intensity: (folder / "v.npz",) * 2, "unreadable", True),
}


@pytest.mark.parametrize(("make", "match", "structural"), BROKEN.values(), ids=BROKEN.keys())
def test_broken_view_file(tmp_path, synthetic_view, sensor, make, match, structural):
    xyz, intensity, _ = synthetic_view
    path, named = make(tmp_path, xyz, intensity)
    before = snapshot(tmp_path)

    with pytest.raises(ViewFileError, match=match) as raised:
        read_view(path, **sensor)
    assert str(named) in str(raised.value)
    assert snapshot(tmp_path) == before

    if structural:
        with pytest.raises(ViewFileError, match=match):
            check_view(path, **sensor)
    else:  # the structure passes, the pixels do not
        check_view(path, **sensor)
        with pytest.raises(ViewFileError, match=match) as raised:
            check_view_pixels(path, **sensor)
        assert str(named) in str(raised.value)
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize(
    "rows", [[3], [1, 2, 3, 4, 5], [0, 1, 2, 3, 4]], ids=["middle-row-invalid", "first-row-valid", "last-row-valid"]
)
@pytest.mark.parametrize("name", ["v.npz", "v.raw"])
def test_pixel_rules_hold_off_the_middle_row_and_on_invalid_pixels(tmp_path, synthetic_view, sensor, rows, name):
    xyz, intensity, valid = synthetic_view
    xyz, intensity = rows_invalid(xyz.copy(), intensity.copy(), rows)
    valid[rows] = False
    intensity[~valid] = -5.0 if name == "v.raw" else np.nan  # a raw file's intensity is uint16
    path = tmp_path / name
    write_view(path, xyz, intensity)
    check_view_pixels(path, **sensor)
    np.testing.assert_array_equal(read_view(path, **sensor).valid, valid)


@pytest.mark.parametrize("save", ["savez", "savez_compressed", "fortran"])
@pytest.mark.parametrize("broken", [None, (0, 5), (5, 1)], ids=["sound", "first-row", "last-row"])
def test_pixel_check_of_npz_members_stored_compressed_or_fortran(tmp_path, synthetic_view, sensor, save, broken):
    """Stored members are tested in place, compressed ones loaded: the same verdict and message as read_view's."""
    xyz, intensity, _ = synthetic_view
    intensity = intensity.copy()
    if broken is not None:
        intensity[broken] = -3.0
    arrays = {"xyz": xyz.astype(np.float32), "intensity": intensity}
    if save == "fortran":
        arrays = {name: np.asfortranarray(array) for name, array in arrays.items()}
    path = tmp_path / "v.npz"
    (np.savez_compressed if save == "savez_compressed" else np.savez)(path, **arrays)
    check_view(path, **sensor)
    if broken is None:
        check_view_pixels(path, **sensor)
        return
    with pytest.raises(ViewFileError) as read:
        read_view(path, **sensor)
    with pytest.raises(ViewFileError) as checked:
        check_view_pixels(path, **sensor)
    assert str(checked.value) == str(read.value)
    assert f"first at row {broken[0]}, column {broken[1]}: -3.0" in str(checked.value)


def test_pixel_check_reads_only_the_intensity_and_middle_row_of_a_stored_npz(tmp_path, synthetic_view, sensor):
    """A stored npz is tested on its bytes in place: a damaged xyz row off the middle passes the pixel check
    (its checksum is not read), and read_view refuses the file."""
    xyz, intensity, _ = synthetic_view
    path = tmp_path / "v.npz"
    write_view(path, xyz, intensity)
    first_row = xyz[0].astype(np.float32).tobytes()
    data = path.read_bytes()
    assert data.count(first_row) == 1
    path.write_bytes(data.replace(first_row, np.full_like(xyz[0], 0.25, dtype=np.float32).tobytes()))
    check_view_pixels(path, **sensor)
    with pytest.raises(ViewFileError, match=f"{path}.*CRC"):
        read_view(path, **sensor)


# --- writing ------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("name", "change", "match"),
    [
        ("v.txt", {}, "not a view form"),
        ("v.npz", {"xyz": np.zeros((6, 8, 2))}, r"xyz has shape \(6, 8, 2\)"),
        ("v.npz", {"intensity": np.zeros((6, 7))}, "intensity is float64 \\(6, 7\\)"),
        ("v.npz", {"pose": np.eye(3)}, "malformed pose argument"),
        ("v.npz", {"units": "cm"}, "units 'cm'"),
        ("v.raw", {"xyz": np.full((6, 8, 3), 100.0)}, "ABCY16 codes"),
    ],
)
def test_write_view_refuses_and_writes_nothing(tmp_path, synthetic_view, name, change, match):
    xyz, intensity, _ = synthetic_view
    arguments = {"xyz": xyz, "intensity": intensity, **change}
    with pytest.raises(ValueError, match=match):
        write_view(tmp_path / name, **arguments)
    assert snapshot(tmp_path) == {}


def test_write_view_replaces_and_leaves_no_temporary(tmp_path, synthetic_view, sensor):
    xyz, intensity, _ = synthetic_view
    path = tmp_path / "v.raw"
    write_view(path, xyz, intensity)
    write_view(path, xyz, 2 * intensity)
    assert sorted(snapshot(tmp_path)) == ["v.raw"]
    view = read_view(path, **sensor)
    np.testing.assert_allclose(view.intensity[view.valid], 2 * intensity[view.valid], atol=0.5)


@pytest.mark.parametrize(("name", "options"), [("v.ply", {}), ("v.npz", {"pose": rigid_pose()})])
def test_rewrite_removes_stale_sidecar(tmp_path, synthetic_view, sensor, name, options):
    xyz, intensity, _ = synthetic_view
    path = tmp_path / name
    write_view(path, xyz, intensity, pose=rigid_pose(angle=0.1), pose_sidecar=True)
    assert pose_sidecar_path(path).exists()
    write_view(path, xyz, intensity, **options)
    assert not pose_sidecar_path(path).exists()
    pose = read_view(path, **sensor).pose
    assert (pose is None) if "pose" not in options else np.allclose(pose, options["pose"])


# --- listing ------------------------------------------------------------------------------------


def test_list_views(tmp_path):
    for name in ["b.ply", "a.npz", "c.raw", "a.pose.txt", "notes.txt", ".hidden.npz", "truth.npz", "sub/d.npz"]:
        (tmp_path / name).parent.mkdir(exist_ok=True)
        (tmp_path / name).touch()
    (tmp_path / "folder.npz").mkdir()
    assert [path.name for path in list_views(tmp_path)] == ["a.npz", "b.ply", "c.raw", "truth.npz"]
    excluded = list_views(tmp_path, exclude=[tmp_path / "sub" / ".." / "truth.npz"])
    assert excluded == [tmp_path / "a.npz", tmp_path / "b.ply", tmp_path / "c.raw"]


def test_list_views_refuses_two_files_with_one_stem(tmp_path):
    for name in ["a.npz", "b.ply", "b.raw"]:
        (tmp_path / name).touch()
    with pytest.raises(ViewFileError, match=r"b\.ply and .*b\.raw: two view files with the stem 'b'"):
        list_views(tmp_path)


def test_list_views_of_missing_folder(tmp_path):
    with pytest.raises(ViewFileError, match="cannot list the view files"):
        list_views(tmp_path / "nowhere")


def test_valid_pixels():
    xyz = np.array([[1.0, 2.0, 3.0], [0.0, 0.0, 0.0], [1.0, np.nan, 3.0], [1.0, 1.0, -1.0], [0.0, 0.0, 1e-9]])
    np.testing.assert_array_equal(valid_pixels(xyz), [True, False, False, False, True])
    infinite = np.array([[np.inf, 0.0, 1.0], [0.0, -np.inf, 1.0], [0.0, 0.0, np.inf], [0.0, 0.0, np.nan]])
    np.testing.assert_array_equal(valid_pixels(infinite), [False] * 4)
    grid = np.random.default_rng(0).normal(size=(6, 8, 3))
    grid[grid > 1.5] = np.inf
    np.testing.assert_array_equal(valid_pixels(grid), np.isfinite(grid).all(axis=-1) & (grid[..., 2] > 0))
