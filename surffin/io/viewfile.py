"""View files: one organized point cloud and intensity image per camera view.

A view holds the full sensor grid (height x width), row-major from the top-left
pixel, in the camera frame with OpenCV axes (x right, y down, z forward). Three
forms are read and written, chosen by the file suffix:

``.npz``
    ``xyz`` float (height, width, 3), ``intensity`` numeric (height, width),
    optional ``pose`` (4, 4); loaded without pickle.
``.ply``
    ``ascii 1.0`` or ``binary_little_endian 1.0`` (``binary_big_endian`` is read
    too), one ``vertex`` element of width*height vertices with properties ``x``,
    ``y``, ``z`` (float or double) and ``intensity`` (any numeric type).
``.raw``
    The Helios ``Coord3D_ABCY16`` buffer: four little-endian uint16 channels per
    pixel (A = x, B = y, C = z, Y = intensity), coordinates in mm are
    ``raw * scale + offset``; 65535 in A, B or C marks an invalid pixel.

A pose (camera-to-world, 4x4, translation in the unit of the file's xyz) is an
array ``pose`` inside an npz or a sidecar ``<stem>.pose.txt`` of 16 numbers,
row-major; never both. A pixel is invalid when its xyz has a NaN or its z is
<= 0 (which covers all-zero xyz).
"""

from __future__ import annotations

import contextlib
import io
import zipfile
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from operator import attrgetter
from pathlib import Path
from typing import NamedTuple

import numpy as np
import plyfile

from surffin.errors import ViewFileError
from surffin.io.files import write_atomically

__all__ = [
    "ABCY16_DEFAULT",
    "VIEW_SUFFIXES",
    "POSE_SUFFIX",
    "View",
    "read_view",
    "write_view",
    "list_views",
    "check_view",
    "pose_sidecar_path",
    "valid_pixels",
    "npz_headers",
]

ABCY16_DEFAULT = {"scale": 0.25, "offset": (-8192.0, -8192.0, 0.0)}
VIEW_SUFFIXES = (".npz", ".ply", ".raw")
POSE_SUFFIX = ".pose.txt"

_METRES_PER_UNIT = {"m": 1.0, "mm": 1e-3}
_RAW_UNITS = "mm"
_RAW_INVALID = 65535
_RAW_CHANNELS = 4
_RAW_DTYPE = np.dtype("<u2")
_POSE_LAST_ROW_TOLERANCE = 1e-9
_POSE_ROTATION_TOLERANCE = 1e-6
_NUMERIC_KINDS = "iuf"
_PLY_HEADER_LIMIT = 1 << 16
_PLY_FORMATS = {"ascii": "=", "binary_little_endian": "<", "binary_big_endian": ">"}
_PLY_TYPES = {
    name: np.dtype(code)
    for names, code in [
        (("char", "int8"), "i1"),
        (("uchar", "uint8"), "u1"),
        (("short", "int16"), "i2"),
        (("ushort", "uint16"), "u2"),
        (("int", "int32"), "i4"),
        (("uint", "uint32"), "u4"),
        (("float", "float32"), "f4"),
        (("double", "float64"), "f8"),
    ]
    for name in names
}
_PLY_ELEMENT = "vertex"
_PLY_XYZ = ("x", "y", "z")
_PLY_INTENSITY = "intensity"
_LOW_LEVEL_ERRORS = (
    ValueError,
    TypeError,
    EOFError,
    OSError,
    zipfile.BadZipFile,
    zipfile.LargeZipFile,
    plyfile.PlyParseError,
)


@dataclass(frozen=True, eq=False)
class View:
    """One camera view, converted to metres and validated.

    Attributes
    ----------
    path : Path
        The view file it was read from.
    xyz : (height, width, 3) ndarray of float64, metres
        Points in the camera frame; NaN on invalid pixels.
    intensity : (height, width) ndarray of float32
        Camera intensity; 0 on invalid pixels.
    valid : (height, width) ndarray of bool
        Pixels with a usable return.
    pose : (4, 4) ndarray of float64 or None
        Camera-to-world transform with its translation in metres; None if the
        view carries no pose.
    """

    path: Path
    xyz: np.ndarray
    intensity: np.ndarray
    valid: np.ndarray
    pose: np.ndarray | None


class _Form(NamedTuple):
    """How one view file form is checked and read.

    Attributes
    ----------
    inspect : callable (path, width, height) -> (4, 4) ndarray or None
        Cheap structural check; returns the pose stored inside the file (file
        units) or None.
    load : callable (path, width, height, abcy16) -> (xyz, intensity)
        Pixel data: xyz (height, width, 3) in file units, NaN where the form
        itself marks a pixel invalid; intensity (height, width).
    units : str or None
        Unit of xyz fixed by the form, or None when it is the camera's.
    """

    inspect: Callable[[Path, int, int], np.ndarray | None]
    load: Callable[[Path, int, int, dict], tuple[np.ndarray, np.ndarray]]
    units: str | None


def pose_sidecar_path(path: str | Path) -> Path:
    """Return the sidecar pose file of a view file: ``<stem>.pose.txt`` beside it."""
    path = Path(path)
    return path.with_name(path.stem + POSE_SUFFIX)


def valid_pixels(xyz: np.ndarray) -> np.ndarray:
    """Pixels with a usable return.

    Parameters
    ----------
    xyz : (..., 3) ndarray
        Points in the camera frame, any unit.

    Returns
    -------
    (...) ndarray of bool
        True where all three coordinates are finite and z > 0 (so all-zero
        points are invalid).
    """
    return np.isfinite(xyz).all(axis=-1) & (xyz[..., 2] > 0)


def read_view(
    path: str | Path,
    *,
    width: int,
    height: int,
    units: str = "m",
    abcy16: dict | None = None,
) -> View:
    """Read and validate one view file.

    Parameters
    ----------
    path : str or Path
        A ``.npz``, ``.ply`` or ``.raw`` view file.
    width, height : int
        Sensor size in pixels; the file must hold exactly this grid.
    units : {"m", "mm"}
        Unit of xyz (and pose translation) in npz and ply files; raw files are
        always mm.
    abcy16 : dict, optional
        ``{"scale": float, "offset": (3,) floats}`` of raw files, mm;
        default :data:`ABCY16_DEFAULT`.

    Returns
    -------
    View
        xyz in metres, NaN on invalid pixels; intensity 0 there.

    Raises
    ------
    ViewFileError
        The file or its pose is unreadable or breaks the contract; the
        message names the file, the problem and what is expected.
    """
    path = Path(path)
    form, stored_pose = _inspect(path, width, height)
    with _as_view_error(path):
        xyz, intensity = form.load(path, width, height, ABCY16_DEFAULT if abcy16 is None else abcy16)
    metres_per_unit = _METRES_PER_UNIT[form.units or _checked_units(units)]
    xyz = np.asarray(xyz, dtype=np.float64) * metres_per_unit
    intensity = np.asarray(intensity, dtype=np.float32)
    valid = valid_pixels(xyz)
    if not valid.any():
        raise ViewFileError(f"{path}: no valid pixel (every pixel has xyz NaN or z <= 0); expected at least one")
    broken = valid & ~(np.isfinite(intensity) & (intensity >= 0))
    if broken.any():
        row, col = np.argwhere(broken)[0]
        raise ViewFileError(
            f"{path}: intensity is NaN, infinite or negative on {int(broken.sum())} of "
            f"{int(valid.sum())} valid pixels (first at row {row}, column {col}: "
            f"{intensity[row, col]}); expected finite values >= 0 (a broken conversion?)"
        )
    xyz[~valid] = np.nan
    intensity[~valid] = 0.0
    pose = None
    if stored_pose is not None:
        pose = np.array(stored_pose, dtype=np.float64)
        pose[:3, 3] *= metres_per_unit
    return View(path=path, xyz=xyz, intensity=intensity, valid=valid, pose=pose)


def check_view(
    path: str | Path,
    *,
    width: int,
    height: int,
    units: str = "m",
    abcy16: dict | None = None,
) -> None:
    """Check a view file's structure cheaply, without reading its pixel data.

    npz: member names, dtypes and shapes from the array headers (no pickle);
    ply: the header and, for binary files, the size; raw: the size. The pose
    (inside the npz or in the sidecar) is read and checked, and a pose given in
    both places is refused. Pixel validity is left to :func:`read_view`.

    Parameters
    ----------
    path, width, height, units, abcy16
        As for :func:`read_view`.

    Raises
    ------
    ViewFileError
        The file or its pose breaks the contract.
    """
    _checked_units(units)
    _inspect(Path(path), width, height)


def write_view(
    path: str | Path,
    xyz: np.ndarray,
    intensity: np.ndarray,
    *,
    units: str = "m",
    pose: np.ndarray | None = None,
    pose_sidecar: bool = False,
    binary: bool = True,
    abcy16: dict | None = None,
) -> None:
    """Write one view file atomically, in the form given by the suffix of ``path``.

    Parameters
    ----------
    path : str or Path
        Target ``.npz``, ``.ply`` or ``.raw`` file; replaced if it exists.
    xyz : (height, width, 3) array_like, metres
        Points in the camera frame; NaN (or zeros) on invalid pixels. Stored as
        float32 in ``units`` (npz, ply) or quantised to ABCY16 codes (raw).
    intensity : (height, width) array_like, numeric
        Kept as is in npz, float32 in ply, rounded and clipped to uint16 in raw.
    units : {"m", "mm"}
        Unit of xyz and pose translation inside npz and ply files.
    pose : (4, 4) array_like, optional
        Camera-to-world transform, translation in metres; written in the file's
        unit (``units``; mm for raw).
    pose_sidecar : bool
        npz only: write the pose to ``<stem>.pose.txt`` instead of into the
        npz. ply and raw poses always go to the sidecar.
    binary : bool
        ply only: ``binary_little_endian 1.0`` if True, else ``ascii 1.0``.
    abcy16 : dict, optional
        raw only: ``{"scale", "offset"}`` of the encoding, mm; default
        :data:`ABCY16_DEFAULT`.

    Raises
    ------
    ValueError
        Bad suffix, units, shapes or pose, or a valid point outside the range
        of the raw encoding. Nothing is written then.

    Notes
    -----
    Every file goes to a temporary name in the same folder and is renamed into
    place. A sidecar left from an earlier view of the same stem is removed when
    the new view carries no sidecar pose.
    """
    path = Path(path)
    if path.suffix not in VIEW_SUFFIXES:
        raise ValueError(f"{path}: suffix {path.suffix!r} is not a view form; expected one of {VIEW_SUFFIXES}")
    xyz = np.asarray(xyz, dtype=np.float64)
    intensity = np.asarray(intensity)
    if xyz.ndim != 3 or xyz.shape[2] != 3:
        raise ValueError(f"{path}: xyz has shape {xyz.shape}; expected (height, width, 3)")
    if intensity.shape != xyz.shape[:2] or intensity.dtype.kind not in _NUMERIC_KINDS:
        raise ValueError(
            f"{path}: intensity is {intensity.dtype} {intensity.shape}; expected a numeric "
            f"array of shape {xyz.shape[:2]}"
        )
    file_units = _RAW_UNITS if path.suffix == ".raw" else _checked_units(units)
    metres_per_unit = _METRES_PER_UNIT[file_units]
    file_pose = None
    if pose is not None:
        file_pose = np.array(pose, dtype=np.float64)
        problem = _pose_problem(file_pose)
        if problem:
            raise ValueError(f"{path}: malformed pose argument: {problem}")
        file_pose[:3, 3] /= metres_per_unit
    in_sidecar = file_pose is not None and (pose_sidecar or path.suffix != ".npz")
    xyz_file = xyz / metres_per_unit
    if path.suffix == ".npz":
        content = _encode_npz(xyz_file, intensity, None if in_sidecar else file_pose)
    elif path.suffix == ".ply":
        content = _encode_ply(xyz_file, intensity, binary=binary)
    else:
        content = _encode_raw(path, xyz_file, intensity, ABCY16_DEFAULT if abcy16 is None else abcy16)
    sidecar = pose_sidecar_path(path)
    if in_sidecar:
        write_atomically(sidecar, _encode_pose(file_pose))
    else:
        sidecar.unlink(missing_ok=True)
    write_atomically(path, content)


def list_views(folder: str | Path, *, exclude: Iterable[str | Path] = ()) -> list[Path]:
    """List the view files of a folder, in name order.

    Parameters
    ----------
    folder : str or Path
        Searched without recursion.
    exclude : iterable of str or Path
        Files that are never views (e.g. a truth file); compared after
        resolving symlinks.

    Returns
    -------
    list of Path
        ``folder / name`` of every regular ``*.npz``, ``*.ply`` and ``*.raw``
        file, sorted by name. Hidden files (a leading dot, as left by temporary
        writes and some file managers) are skipped.

    Raises
    ------
    ViewFileError
        The folder cannot be listed, or two view files share a stem (which
        would make a ``reference: <stem>`` ambiguous).
    """
    folder = Path(folder)
    excluded = {Path(item).resolve() for item in exclude}
    try:
        entries = sorted(folder.iterdir(), key=attrgetter("name"))
    except OSError as exc:
        raise ViewFileError(f"{folder}: cannot list the view files: {exc}") from exc
    views = [
        entry
        for entry in entries
        if entry.suffix in VIEW_SUFFIXES
        and not entry.name.startswith(".")
        and entry.is_file()
        and entry.resolve() not in excluded
    ]
    by_stem: dict[str, Path] = {}
    for view in views:
        if view.stem in by_stem:
            raise ViewFileError(
                f"{by_stem[view.stem]} and {view}: two view files with the stem {view.stem!r} in one "
                f"folder; expected one file per view (the stem names the view)"
            )
        by_stem[view.stem] = view
    return views


def _checked_units(units: str) -> str:
    if units not in _METRES_PER_UNIT:
        raise ValueError(f"units {units!r} is not supported; expected one of {sorted(_METRES_PER_UNIT)}")
    return units


@contextlib.contextmanager
def _as_view_error(path: Path) -> Iterator[None]:
    """Turn the errors of numpy, zipfile and plyfile into a ViewFileError naming ``path``."""
    try:
        yield
    except _LOW_LEVEL_ERRORS as exc:
        raise ViewFileError(
            f"{path}: unreadable ({type(exc).__name__}: {exc}); expected a valid {path.suffix} file"
        ) from exc


def _inspect(path: Path, width: int, height: int) -> tuple[_Form, np.ndarray | None]:
    """Return the form of a view file and its pose (file units), after the cheap checks."""
    form = _FORMS.get(path.suffix)
    if form is None:
        raise ViewFileError(f"{path}: suffix {path.suffix!r} is not a view form; expected one of {VIEW_SUFFIXES}")
    with _as_view_error(path):
        stored_pose = form.inspect(path, width, height)
    if stored_pose is not None:
        _check_pose(stored_pose, f"{path} (array 'pose')")
    sidecar = pose_sidecar_path(path)
    if not sidecar.exists():
        return form, stored_pose
    if stored_pose is not None:
        raise ViewFileError(
            f"{path}: pose given both inside the npz and in the sidecar {sidecar}; expected one of the two"
        )
    return form, _read_pose_sidecar(sidecar)


def _pose_problem(pose: np.ndarray) -> str | None:
    """Say what is wrong with a camera-to-world pose, or return None if it is a rigid transform."""
    if pose.shape != (4, 4):
        return f"shape {pose.shape}, expected (4, 4)"
    if not np.isfinite(pose).all():
        return "non-finite entries, expected finite numbers"
    if not np.allclose(pose[3], [0.0, 0.0, 0.0, 1.0], rtol=0.0, atol=_POSE_LAST_ROW_TOLERANCE):
        return f"last row {pose[3].tolist()}, expected [0, 0, 0, 1]"
    rotation = pose[:3, :3]
    deviation = np.abs(rotation @ rotation.T - np.eye(3)).max()
    if deviation > _POSE_ROTATION_TOLERANCE or np.linalg.det(rotation) <= 0:
        return (
            f"rotation part is not a rotation (R R^T deviates from I by {deviation:.3g}, "
            f"det {np.linalg.det(rotation):.6g}), expected orthonormal with det +1 "
            f"(tolerance {_POSE_ROTATION_TOLERANCE:g})"
        )
    return None


def _check_pose(pose: np.ndarray, source: str) -> None:
    problem = _pose_problem(np.asarray(pose, dtype=np.float64))
    if problem:
        raise ViewFileError(f"{source}: malformed pose: {problem}")


def _read_pose_sidecar(sidecar: Path) -> np.ndarray:
    try:
        words = sidecar.read_text(encoding="ascii").split()
        numbers = [float(word) for word in words]
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise ViewFileError(
            f"{sidecar}: unreadable pose sidecar ({exc}); expected 16 whitespace-separated numbers, row-major"
        ) from exc
    if len(numbers) != 16:
        raise ViewFileError(
            f"{sidecar}: pose sidecar holds {len(numbers)} numbers; expected 16 whitespace-separated "
            f"numbers (a 4x4 camera-to-world matrix, row-major)"
        )
    pose = np.array(numbers, dtype=np.float64).reshape(4, 4)
    _check_pose(pose, str(sidecar))
    return pose


def _encode_pose(pose: np.ndarray) -> bytes:
    return "".join(" ".join(f"{value:.17g}" for value in row) + "\n" for row in pose).encode("ascii")


# --- npz -------------------------------------------------------------------------------------


def _npy_header(archive: zipfile.ZipFile, member: str) -> tuple[tuple[int, ...], np.dtype]:
    """Shape and dtype of one ``.npy`` member, from its header alone."""
    with archive.open(member) as stream:
        version = np.lib.format.read_magic(stream)
        read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
        shape, _, dtype = read_header(stream)
        header_size = stream.tell()
    if dtype.hasobject:
        return shape, dtype
    expected = header_size + int(np.prod(shape)) * dtype.itemsize
    actual = archive.getinfo(member).file_size
    if actual != expected:
        raise ValueError(f"member {member} holds {actual} bytes but its header implies {expected}")
    return shape, dtype


def npz_headers(path: str | Path) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    """Shapes and dtypes of the arrays of an npz file, from their headers alone.

    Reads no array data and never unpickles.

    Parameters
    ----------
    path : str or Path
        An npz archive (as written by ``numpy.savez``).

    Returns
    -------
    dict
        Array name to ``(shape, dtype)``.

    Raises
    ------
    ViewFileError
        The archive or a header is unreadable, a member's size does not match
        its header, or an array holds Python objects (which would need pickle).
    """
    path = Path(path)
    with _as_view_error(path), zipfile.ZipFile(path) as archive:
        headers = {
            member.removesuffix(".npy"): _npy_header(archive, member)
            for member in archive.namelist()
            if member.endswith(".npy")
        }
    for name, (_, dtype) in headers.items():
        if dtype.hasobject:
            raise ViewFileError(
                f"{path}: array {name!r} is an object array, which would need unpickling (refused); "
                f"expected plain numeric or string arrays"
            )
    return headers


def _inspect_npz(path: Path, width: int, height: int) -> np.ndarray | None:
    headers = npz_headers(path)
    expected = [
        ("xyz", (height, width, 3), "f", "a float", True),
        ("intensity", (height, width), _NUMERIC_KINDS, "a numeric", True),
        ("pose", (4, 4), _NUMERIC_KINDS, "a numeric", False),
    ]
    for name, shape, kinds, kind_text, required in expected:
        if name not in headers:
            if required:
                raise ViewFileError(
                    f"{path}: no array {name!r} (arrays: {sorted(headers)}); expected {kind_text} "
                    f"array {name!r} of shape {shape}"
                )
            continue
        found_shape, dtype = headers[name]
        if found_shape != shape or dtype.kind not in kinds:
            raise ViewFileError(
                f"{path}: array {name!r} is {dtype} of shape {found_shape}; expected {kind_text} array of shape {shape}"
            )
    if "pose" not in headers:
        return None
    with np.load(path, allow_pickle=False) as arrays:
        return arrays["pose"]


def _load_npz(path: Path, width: int, height: int, abcy16: dict) -> tuple[np.ndarray, np.ndarray]:
    with np.load(path, allow_pickle=False) as arrays:
        return arrays["xyz"], arrays["intensity"]


def _encode_npz(xyz: np.ndarray, intensity: np.ndarray, pose: np.ndarray | None) -> bytes:
    arrays = {"xyz": xyz.astype(np.float32), "intensity": intensity}
    if pose is not None:
        arrays["pose"] = pose
    buffer = io.BytesIO()
    np.savez(buffer, allow_pickle=False, **arrays)
    return buffer.getvalue()


# --- ply -------------------------------------------------------------------------------------


class _PlyHeader(NamedTuple):
    """The parts of a PLY header that matter here.

    Attributes
    ----------
    byte_order : str
        ``=`` for ascii, ``<`` or ``>`` for binary.
    elements : list of (name, count, {property: dtype or None})
        In file order; None marks a list property.
    size : int
        Bytes of the header, up to and including the ``end_header`` line.
    """

    byte_order: str
    elements: list[tuple[str, int, dict[str, np.dtype | None]]]
    size: int


def _read_ply_header(path: Path) -> _PlyHeader:
    with open(path, "rb") as stream:
        head = stream.read(_PLY_HEADER_LIMIT)
    lines = head.split(b"\n")
    if lines[0].rstrip(b"\r") != b"ply":
        raise ViewFileError(f"{path}: does not start with the line 'ply'; expected a PLY file")
    byte_order = None
    elements: list[tuple[str, int, dict[str, np.dtype | None]]] = []
    size = len(lines[0]) + 1
    for number, raw_line in enumerate(lines[1:-1], start=2):
        size += len(raw_line) + 1
        words = raw_line.decode("ascii", errors="replace").split()
        keyword = words[0] if words else ""
        if keyword == "end_header":
            if byte_order is None:
                raise ViewFileError(f"{path}: PLY header has no 'format' line; expected 'format ascii 1.0'")
            return _PlyHeader(byte_order, elements, size)
        if keyword == "format" and len(words) == 3 and words[1] in _PLY_FORMATS and words[2] == "1.0":
            byte_order = _PLY_FORMATS[words[1]]
        elif keyword == "element" and len(words) == 3 and words[2].isdigit():
            elements.append((words[1], int(words[2]), {}))
        elif keyword == "property" and elements and len(words) == 3 and words[1] in _PLY_TYPES:
            elements[-1][2][words[2]] = _PLY_TYPES[words[1]]
        elif keyword == "property" and elements and len(words) == 5 and words[1] == "list":
            elements[-1][2][words[4]] = None
        elif keyword not in ("comment", "obj_info", ""):
            raise ViewFileError(
                f"{path}: PLY header line {number} {raw_line[:80]!r} is not understood; expected "
                f"'format ascii|binary_little_endian 1.0', 'element', 'property', 'comment' or 'end_header'"
            )
    raise ViewFileError(
        f"{path}: no 'end_header' line in the first {_PLY_HEADER_LIMIT} bytes; expected a complete PLY header"
    )


def _inspect_ply(path: Path, width: int, height: int) -> None:
    header = _read_ply_header(path)
    vertices = [element for element in header.elements if element[0] == _PLY_ELEMENT]
    if len(vertices) != 1:
        raise ViewFileError(
            f"{path}: {len(vertices)} '{_PLY_ELEMENT}' elements; expected exactly one "
            f"(elements: {[element[0] for element in header.elements]})"
        )
    _, count, properties = vertices[0]
    if count != width * height:
        raise ViewFileError(f"{path}: {count} vertices; expected width*height = {width}*{height} = {width * height}")
    for name in (*_PLY_XYZ, _PLY_INTENSITY):
        dtype = properties.get(name)
        kinds = "f" if name in _PLY_XYZ else _NUMERIC_KINDS
        if dtype is None or dtype.kind not in kinds:
            raise ViewFileError(
                f"{path}: vertex property {name!r} is {'missing or a list' if dtype is None else dtype}; "
                f"expected a scalar {'float or double' if kinds == 'f' else 'numeric'} property "
                f"(properties: {list(properties)})"
            )
    if header.byte_order == "=":
        return
    needed = header.size
    for _, element_count, element_properties in header.elements:
        if None in element_properties.values():
            break
        needed += element_count * sum(dtype.itemsize for dtype in element_properties.values())
    actual = path.stat().st_size
    if actual < needed:
        raise ViewFileError(f"{path}: truncated PLY: {actual} bytes; expected at least {needed}")


def _load_ply(path: Path, width: int, height: int, abcy16: dict) -> tuple[np.ndarray, np.ndarray]:
    vertex = plyfile.PlyData.read(path)[_PLY_ELEMENT]
    xyz = np.stack([np.asarray(vertex[name], dtype=np.float64) for name in _PLY_XYZ], axis=-1)
    intensity = np.array(vertex[_PLY_INTENSITY], dtype=np.float32)
    return xyz.reshape(height, width, 3), intensity.reshape(height, width)


def _encode_ply(xyz: np.ndarray, intensity: np.ndarray, *, binary: bool) -> bytes:
    fields = (*_PLY_XYZ, _PLY_INTENSITY)
    table = np.column_stack([xyz.reshape(-1, 3), intensity.reshape(-1)]).astype(np.float32)
    vertices = np.empty(table.shape[0], dtype=[(name, np.float32) for name in fields])
    for column, name in enumerate(fields):
        vertices[name] = table[:, column]
    data = plyfile.PlyData([plyfile.PlyElement.describe(vertices, _PLY_ELEMENT)], text=not binary, byte_order="<")
    buffer = io.BytesIO()
    if binary:
        data.write(buffer)
    else:
        buffer.write(f"{data.header}\n".encode("ascii"))
        np.savetxt(buffer, table, fmt="%.9g")
    return buffer.getvalue()


# --- raw (Coord3D_ABCY16) ----------------------------------------------------------------------


def _inspect_raw(path: Path, width: int, height: int) -> None:
    expected = width * height * _RAW_CHANNELS * _RAW_DTYPE.itemsize
    actual = path.stat().st_size
    if actual != expected:
        raise ViewFileError(
            f"{path}: {actual} bytes; expected width*height*8 = {expected} bytes "
            f"(Coord3D_ABCY16: four uint16 channels per pixel)"
        )


def _abcy16_scale_offset(abcy16: dict) -> tuple[float, np.ndarray]:
    return float(abcy16["scale"]), np.asarray(abcy16["offset"], dtype=np.float64)


def _load_raw(path: Path, width: int, height: int, abcy16: dict) -> tuple[np.ndarray, np.ndarray]:
    scale, offset = _abcy16_scale_offset(abcy16)
    channels = np.fromfile(path, dtype=_RAW_DTYPE).reshape(height, width, _RAW_CHANNELS)
    codes = channels[..., :3]
    xyz = codes * scale + offset
    xyz[(codes == _RAW_INVALID).any(axis=-1)] = np.nan
    return xyz, channels[..., 3]


def _encode_raw(path: Path, xyz: np.ndarray, intensity: np.ndarray, abcy16: dict) -> bytes:
    scale, offset = _abcy16_scale_offset(abcy16)
    valid = valid_pixels(xyz)
    channels = np.full((*xyz.shape[:2], _RAW_CHANNELS), _RAW_INVALID, dtype=_RAW_DTYPE)
    codes = np.rint((xyz[valid] - offset) / scale)
    if codes.size and (codes.min() < 0 or codes.max() >= _RAW_INVALID):
        raise ValueError(
            f"{path}: valid points span ABCY16 codes {codes.min():.0f}..{codes.max():.0f}; expected "
            f"0..{_RAW_INVALID - 1} (xyz in mm = code * {scale} + {offset.tolist()})"
        )
    channels[valid, :3] = codes
    level = np.nan_to_num(np.asarray(intensity, dtype=np.float64), nan=0.0)
    channels[..., 3] = np.clip(np.rint(level), 0, _RAW_INVALID)
    return channels.tobytes()


_FORMS = {
    ".npz": _Form(_inspect_npz, _load_npz, None),
    ".ply": _Form(_inspect_ply, _load_ply, None),
    ".raw": _Form(_inspect_raw, _load_raw, _RAW_UNITS),
}
