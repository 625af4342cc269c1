"""View files: one organized point cloud and intensity image per camera view.

A view holds the full sensor grid (height x width), row-major from the top-left
pixel, in the camera frame with OpenCV axes (x right, y down, z forward). A
pixel is invalid when its xyz has a NaN or its z is <= 0. Three forms are read
(and written), chosen by the file suffix:

``.npz``
    ``xyz`` float (height, width, 3), ``intensity`` numeric, optional ``pose``
    (4, 4); loaded without pickle.
``.ply``
    ascii or binary (either byte order), LF, CRLF or CR line ends; one ``vertex``
    element of exactly width*height vertices, float ``x``, ``y``, ``z`` and a
    numeric intensity property (:data:`PLY_INTENSITY_FALLBACKS`).
``.raw``
    The Helios ``Coord3D_ABCY16`` buffer (A, B, C uint16, invalid 65535) or its
    signed form ``Coord3D_ABCY16s`` (int16, invalid -32768), then uint16 Y;
    mm = ``code * scale + offset`` (:func:`abcy16_encoding`).

Sidecars beside ``<stem>.<form>``: a pose (camera-to-world, or world-from-flange
with a hand-eye transform) as ``<stem>.pose.txt`` (16 numbers, row-major) or
``<stem>.pose.json`` (translation and unit quaternion), at most one per view
counting an npz's ``pose``; acquisition settings as ``<stem>.meta.json``.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import struct
import zipfile
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from operator import attrgetter
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import plyfile

from surffin.errors import ViewFileError
from surffin.io.files import write_atomically

__all__ = [
    "ABCY16_DEFAULT",
    "ABCY16_SIGNED_OFFSET",
    "PLY_INTENSITY",
    "PLY_INTENSITY_FALLBACKS",
    "VIEW_SUFFIXES",
    "POSE_SUFFIX",
    "POSE_JSON_SUFFIX",
    "META_SUFFIX",
    "View",
    "abcy16_encoding",
    "read_view",
    "write_view",
    "list_views",
    "check_view",
    "check_view_pixels",
    "read_settings",
    "setting_values",
    "describe_groups",
    "pose_problem",
    "pose_sidecar_path",
    "sidecar_path",
    "view_sidecars",
    "valid_pixels",
    "npz_headers",
]

ABCY16_DEFAULT = {"signed": False, "scale": 0.25, "offset": (-8192.0, -8192.0, 0.0)}
ABCY16_SIGNED_OFFSET = (0.0, 0.0, 0.0)
PLY_INTENSITY = "intensity"
PLY_INTENSITY_FALLBACKS = ("scalar_Intensity", "intensities")
"""Names of the PLY intensity property that CloudCompare and Open3D write, taken when the named one is absent."""
VIEW_SUFFIXES = (".npz", ".ply", ".raw")
POSE_SUFFIX = ".pose.txt"
POSE_JSON_SUFFIX = ".pose.json"
META_SUFFIX = ".meta.json"

_METRES_PER_UNIT = {"m": 1.0, "mm": 1e-3}
_RAW_UNITS = "mm"
_RAW_CHANNELS = 4
_RAW_DTYPE = np.dtype("<u2")
_RAW_SIGNED_DTYPE = np.dtype("<i2")
_RAW_INVALID = {False: 65535, True: -32768}
_RAW_CODES = {False: (0, 65534), True: (-32767, 32767)}
# Codes of the other form, read as this one, sit in the outer half of the 16-bit range (0 <-> 32768
# swapped): with the usual scale and offset, x and y beyond +-4096 mm, near +-8192 mm, where no
# Helios pixel (69 x 51 deg, 8.3 m range) can be; C = 32768 is the signed form's invalid marker.
_RAW_UNSIGNED_CENTRE = 32768
_RAW_SIGN_OUTER = 16384
_RAW_SIGN_SHARE = 0.5
_RAW_SIGN_SAMPLE_ROWS = 32
_POSE_LAST_ROW_TOLERANCE = 1e-9
_POSE_ROTATION_TOLERANCE = 1e-6
_QUATERNION_NORM_TOLERANCE = 1e-3
_NUMERIC_KINDS = "iuf"
_LOCAL_HEADER = struct.Struct("<4s22xHH")  # a zip member's local header: signature, name and extra field lengths
_PLY_HEADER_LIMIT = 1 << 16
_PLY_NEWLINES = (b"\r\n", b"\n", b"\r")
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
_PLY_ALL_PIXELS = (
    "save the PLY again with all pixels (in ArenaView or the Arena SDK, turn filterPoints off when saving "
    "it), or save the raw Coord3D_ABCY16 buffer (.raw)"
)
_POSE_JSON = '{"translation": [x, y, z], "quaternion": [w, x, y, z]}'
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
        Camera-to-world transform with its translation in metres (the hand-eye
        transform applied); None if the view carries no pose.
    saturated : (height, width) ndarray of bool or None
        Valid pixels whose intensity is at or above the camera's saturation;
        None when no saturation is given.
    settings : mapping of str to number or str
        Acquisition settings from the ``<stem>.meta.json`` sidecar; empty without one.
    """

    path: Path
    xyz: np.ndarray
    intensity: np.ndarray
    valid: np.ndarray
    pose: np.ndarray | None
    saturated: np.ndarray | None = None
    settings: Mapping[str, Any] = field(default_factory=dict)

    @property
    def radiometric(self) -> np.ndarray:
        """(height, width) bool: valid pixels whose intensity is not saturated, the ones radiometry may use."""
        return self.valid if self.saturated is None else self.valid & ~self.saturated


class _Decoding(NamedTuple):
    """How the pixel data of a view file are decoded.

    Attributes
    ----------
    abcy16 : dict
        Complete ABCY16 encoding of raw files (:func:`abcy16_encoding`).
    ply_intensity : str
        Preferred name of the PLY intensity property.
    """

    abcy16: dict
    ply_intensity: str


class _Form(NamedTuple):
    """How one view file form is checked and read.

    Attributes
    ----------
    inspect : callable (path, width, height, decoding) -> (4, 4) ndarray or None
        Cheap structural check; returns the pose stored inside the file (file
        units) or None.
    load : callable (path, width, height, decoding) -> (xyz, intensity)
        Pixel data: xyz (height, width, 3) in file units, NaN where the form
        itself marks a pixel invalid; intensity (height, width).
    units : str or None
        Unit of xyz fixed by the form, or None when it is the camera's.
    """

    inspect: Callable[[Path, int, int, _Decoding], np.ndarray | None]
    load: Callable[[Path, int, int, _Decoding], tuple[np.ndarray, np.ndarray]]
    units: str | None


def sidecar_path(path: str | Path, suffix: str) -> Path:
    """Return the sidecar ``<stem><suffix>`` beside a view file (``suffix``: e.g. :data:`META_SUFFIX`)."""
    path = Path(path)
    return path.with_name(path.stem + suffix)


def view_sidecars(path: str | Path) -> list[Path]:
    """Return the sidecars (pose, settings) that exist beside a view file."""
    candidates = (sidecar_path(path, suffix) for suffix in (POSE_SUFFIX, POSE_JSON_SUFFIX, META_SUFFIX))
    return [candidate for candidate in candidates if candidate.is_file()]


def pose_sidecar_path(path: str | Path) -> Path:
    """Return the sidecar pose file of a view file that :func:`write_view` writes: ``<stem>.pose.txt``."""
    return sidecar_path(path, POSE_SUFFIX)


def abcy16_encoding(signed: bool | None = None, scale=None, offset=None) -> dict:
    """Complete an ABCY16 encoding with the camera's usual values.

    Parameters
    ----------
    signed : bool, optional
        ``Coord3D_ABCY16s`` (int16 A, B, C) if True; default False.
    scale : float or (3,) floats, optional
        mm per code, one for all axes or per axis ``[sA, sB, sC]``; default 0.25.
    offset : (3,) floats, optional
        mm; default ``(-8192, -8192, 0)``, or :data:`ABCY16_SIGNED_OFFSET` when signed.

    Returns
    -------
    dict
        ``{"signed": bool, "scale": float or tuple, "offset": tuple}``.
    """
    signed = bool(signed)
    if offset is None:
        offset = ABCY16_SIGNED_OFFSET if signed else ABCY16_DEFAULT["offset"]
    if scale is None:
        scale = ABCY16_DEFAULT["scale"]
    scale = float(scale) if np.ndim(scale) == 0 else tuple(float(value) for value in scale)
    return {"signed": signed, "scale": scale, "offset": tuple(float(value) for value in offset)}


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
    x, y, z = np.moveaxis(xyz, -1, 0)  # per coordinate: 3x faster than a reduction over the last axis
    valid = np.isfinite(x)
    valid &= np.isfinite(y)
    valid &= z > 0
    valid &= z < np.inf
    return valid


def read_view(
    path: str | Path,
    *,
    width: int,
    height: int,
    units: str = "m",
    abcy16: Mapping | None = None,
    ply_intensity: str = PLY_INTENSITY,
    saturation: float | None = None,
    hand_eye: np.ndarray | None = None,
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
    abcy16 : mapping, optional
        The keywords of :func:`abcy16_encoding` for raw files; missing ones
        take their defaults.
    ply_intensity : str
        Name of the PLY intensity property; when a file lacks it, the names
        of :data:`PLY_INTENSITY_FALLBACKS` are taken.
    saturation : float, optional
        Intensity at or above which a valid pixel is saturated.
    hand_eye : (4, 4) array_like, optional
        Flange-to-camera transform (translation in the file's unit): the
        stored pose is then world-from-flange, and the view's pose is
        ``pose @ hand_eye``.

    Returns
    -------
    View
        xyz in metres, NaN on invalid pixels; intensity 0 there.

    Raises
    ------
    ViewFileError
        The file or a sidecar is unreadable or breaks the contract; the
        message names the file, the problem and what is expected.
    """
    path = Path(path)
    decoding = _decoding(abcy16, ply_intensity)
    form, stored_pose, settings = _inspect(path, width, height, decoding)
    xyz, intensity = _load(path, form, width, height, decoding)
    valid = _pixel_rules(path, xyz, intensity)
    metres_per_unit = _METRES_PER_UNIT[form.units or _checked_units(units)]
    xyz = np.multiply(xyz, metres_per_unit, dtype=np.float64, order="C")  # one pass: cast and scale
    intensity = np.asarray(intensity, dtype=np.float32, order="C")
    saturated = None if saturation is None else valid & (intensity >= saturation)
    invalid = np.flatnonzero(~valid)  # C order, as xyz and intensity: set through flat views, 2x faster than a mask
    xyz.reshape(-1, 3)[invalid] = np.nan
    intensity.reshape(-1)[invalid] = 0.0
    pose = None
    if stored_pose is not None:
        pose = np.array(stored_pose, dtype=np.float64)
        if hand_eye is not None:
            pose = pose @ _checked_transform(hand_eye, "hand_eye")
        pose[:3, 3] *= metres_per_unit
    return View(path, xyz, intensity, valid, pose, saturated, settings)


def _load(path: Path, form: _Form, width: int, height: int, decoding: _Decoding) -> tuple[np.ndarray, np.ndarray]:
    """Load a view's xyz (the file's unit) and intensity."""
    with _as_view_error(path):
        return form.load(path, width, height, decoding)


def _pixel_rules(path: Path, xyz: np.ndarray, intensity: np.ndarray) -> np.ndarray:
    """Apply the contract's pixel rules to a view's xyz and intensity; return the valid mask."""
    valid = valid_pixels(xyz)  # the unit's positive scale changes no pixel's validity
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
    return valid


def _pixel_rules_hold(xyz: np.ndarray, intensity: np.ndarray) -> bool:
    """Tell cheaply, when it can, that :func:`_pixel_rules` finds nothing; False when it cannot tell.

    Every intensity finite and >= 0 (two reductions) breaks no rule whatever the valid pixels are,
    and one valid pixel in the middle row shows that the view has one.
    """
    sound = (
        isinstance(intensity, np.ndarray)
        and isinstance(xyz, np.ndarray)
        and intensity.dtype.kind in _NUMERIC_KINDS
        and intensity.size > 0
        and intensity.shape == xyz.shape[:-1]
        and intensity.min() >= 0
        and intensity.max() < np.inf  # NaN fails the test of the minimum
    )
    return bool(sound and valid_pixels(xyz[xyz.shape[0] // 2]).any())


def check_view(
    path: str | Path,
    *,
    width: int,
    height: int,
    units: str = "m",
    abcy16: Mapping | None = None,
    ply_intensity: str = PLY_INTENSITY,
    saturation: float | None = None,
    hand_eye: np.ndarray | None = None,
) -> None:
    """Check a view file's structure cheaply; :func:`check_view_pixels` checks its pixel rules.

    npz: member names, dtypes and shapes from the array headers (no pickle);
    ply: the header and, for binary files, the size; raw: the size and, on a
    sample of rows, that the codes look like the configured signedness. The
    sidecars (pose, settings) are read and checked, and a view with more than
    one pose is refused.

    Parameters
    ----------
    path, width, height, units, abcy16, ply_intensity, saturation, hand_eye
        As for :func:`read_view` (``saturation`` is not needed here).

    Raises
    ------
    ViewFileError
        The file or a sidecar breaks the contract.
    """
    _checked_units(units)
    if hand_eye is not None:
        _checked_transform(hand_eye, "hand_eye")
    _inspect(Path(path), width, height, _decoding(abcy16, ply_intensity))


def check_view_pixels(
    path: str | Path,
    *,
    width: int,
    height: int,
    abcy16: Mapping | None = None,
    ply_intensity: str = PLY_INTENSITY,
) -> None:
    """Check the pixel rules of a view file whose structure :func:`check_view` passed.

    Loads the pixel data for the rules :func:`read_view` applies (intensity on
    valid pixels, at least one valid pixel), at a fraction of its cost:
    when every intensity is finite and >= 0 and the middle row has a valid
    pixel, the valid pixels are not computed. An npz whose arrays are stored
    uncompressed (``numpy.savez``) is tested first on its bytes mapped in place
    (:func:`_mapped_npz`): the intensity and the middle row of xyz, without
    reading the rest of xyz or the members' checksums (a damaged member is
    refused when :func:`read_view` reads it); when that test cannot tell, the
    file is loaded as :func:`read_view` loads it. The structure is not checked
    again. File reads, zlib and numpy release the GIL: files checked in
    threads at once take the cores there are.

    Parameters
    ----------
    path, width, height, abcy16, ply_intensity
        As for :func:`read_view`.

    Raises
    ------
    ViewFileError
        The pixels break the contract, or the file is unreadable.
    """
    path = Path(path)
    mapped = _mapped_npz(path) if path.suffix == ".npz" else None
    if mapped is not None and _pixel_rules_hold(*mapped):
        return
    xyz, intensity = _load(path, _FORMS[path.suffix], width, height, _decoding(abcy16, ply_intensity))
    if not _pixel_rules_hold(xyz, intensity):
        _pixel_rules(path, xyz, intensity)


def read_settings(path: str | Path) -> dict[str, int | float | str]:
    """Read the acquisition settings of a view: its ``<stem>.meta.json`` sidecar.

    Parameters
    ----------
    path : str or Path
        The view file.

    Returns
    -------
    dict
        Setting name to a number or a string; empty when there is no sidecar.

    Raises
    ------
    ViewFileError
        The sidecar is unreadable, not one JSON object, or holds a value that
        is neither a finite number nor a string.
    """
    sidecar = sidecar_path(path, META_SUFFIX)
    if not sidecar.exists():
        return {}
    expected = 'expected one JSON object of setting names to numbers or strings, e.g. {"exposure_us": 250}'
    document = _read_json(sidecar, "settings sidecar", expected)
    if not isinstance(document, dict):
        raise ViewFileError(f"{sidecar}: settings sidecar holds {type(document).__name__}; {expected}")
    for name, value in document.items():
        if not (isinstance(value, str) or _is_json_number(value)):
            raise ViewFileError(f"{sidecar}: setting {name!r} is {value!r}; {expected}")
    return document


def setting_values(settings: Mapping[str, Mapping], name: str) -> dict[str, list[str]]:
    """Group views by their value of one acquisition setting.

    Parameters
    ----------
    settings : mapping
        View (a name) -> its settings (:func:`read_settings`).
    name : str
        The setting.

    Returns
    -------
    dict of str to list of str
        The value's ``repr`` (``"missing"`` for views without it) -> the views holding it, in order.
    """
    groups: dict[str, list[str]] = {}
    for view, values in settings.items():
        groups.setdefault(repr(values[name]) if name in values else "missing", []).append(view)
    return groups


def describe_groups(groups: Mapping[str, Sequence[str]], shown: int = 3) -> str:
    """Say which views hold which value of :func:`setting_values`: ``"250 in 2 view(s): a, b; 400 in 1 view(s): c"``.

    At most ``shown`` views are named per value.
    """
    return "; ".join(
        f"{value} in {len(views)} view(s): {', '.join(views[:shown])}{', ...' if len(views) > shown else ''}"
        for value, views in groups.items()
    )


def write_view(
    path: str | Path,
    xyz: np.ndarray,
    intensity: np.ndarray,
    *,
    units: str = "m",
    pose: np.ndarray | None = None,
    pose_sidecar: bool = False,
    binary: bool = True,
    abcy16: Mapping | None = None,
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
    abcy16 : mapping, optional
        raw only: the keywords of :func:`abcy16_encoding` (e.g. ``{"signed":
        True}`` writes ``Coord3D_ABCY16s``); missing ones take their defaults.

    Raises
    ------
    ValueError
        Bad suffix, units, shapes or pose, or a valid point outside the range
        of the raw encoding. Nothing is written then.

    Notes
    -----
    Every file goes to a temporary name in the same folder and is renamed into
    place. Pose sidecars left from an earlier view of the same stem
    (``.pose.txt``, ``.pose.json``) are removed unless this view's pose goes there.
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
        problem = pose_problem(file_pose)
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
        content = _encode_raw(path, xyz_file, intensity, abcy16_encoding(**(abcy16 or {})))
    sidecar_path(path, POSE_JSON_SUFFIX).unlink(missing_ok=True)
    if in_sidecar:
        write_atomically(pose_sidecar_path(path), _encode_pose(file_pose))
    else:
        pose_sidecar_path(path).unlink(missing_ok=True)
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


def pose_problem(pose: np.ndarray) -> str | None:
    """Say what keeps a 4x4 matrix from being a rigid transform (a pose), or return None if it is one.

    Parameters
    ----------
    pose : array_like
        Expected (4, 4): a rotation (orthonormal, det +1), a translation and
        the last row ``[0, 0, 0, 1]``.

    Returns
    -------
    str or None
        What is wrong and what is expected, for an error message.
    """
    pose = np.asarray(pose, dtype=np.float64)
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


def _checked_units(units: str) -> str:
    if units not in _METRES_PER_UNIT:
        raise ValueError(f"units {units!r} is not supported; expected one of {sorted(_METRES_PER_UNIT)}")
    return units


def _checked_transform(matrix: np.ndarray, name: str) -> np.ndarray:
    problem = pose_problem(matrix)
    if problem:
        raise ValueError(f"{name} is not a rigid transform: {problem}")
    return np.asarray(matrix, dtype=np.float64)


def _decoding(abcy16: Mapping | None, ply_intensity: str) -> _Decoding:
    return _Decoding(abcy16_encoding(**(abcy16 or {})), ply_intensity)


def _is_json_number(value: Any) -> bool:
    """Tell whether a value of :func:`_read_json` is a number (always finite there), not a bool."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)


@contextlib.contextmanager
def _as_view_error(path: Path) -> Iterator[None]:
    """Turn the errors of numpy, zipfile and plyfile into a ViewFileError naming ``path``."""
    try:
        yield
    except _LOW_LEVEL_ERRORS as exc:
        raise ViewFileError(
            f"{path}: unreadable ({type(exc).__name__}: {exc}); expected a valid {path.suffix} file"
        ) from exc


def _inspect(path: Path, width: int, height: int, decoding: _Decoding) -> tuple[_Form, np.ndarray | None, dict]:
    """Return the form of a view file, its pose (file units) and its settings, after the cheap checks."""
    form = _FORMS.get(path.suffix)
    if form is None:
        raise ViewFileError(f"{path}: suffix {path.suffix!r} is not a view form; expected one of {VIEW_SUFFIXES}")
    with _as_view_error(path):
        stored_pose = form.inspect(path, width, height, decoding)
    poses = {}
    if stored_pose is not None:
        poses["the npz's array 'pose'"] = _checked_pose(stored_pose, f"{path} (array 'pose')")
    for suffix, read in ((POSE_SUFFIX, _read_pose_txt), (POSE_JSON_SUFFIX, _read_pose_json)):
        sidecar = sidecar_path(path, suffix)
        if sidecar.exists():
            poses[str(sidecar)] = read(sidecar)
    if len(poses) > 1:
        raise ViewFileError(
            f"{path}: {len(poses)} poses given: {' and '.join(poses)}; expected at most one pose per view "
            f"(remove all but one)"
        )
    return form, next(iter(poses.values()), None), read_settings(path)


def _checked_pose(pose: np.ndarray, source: str) -> np.ndarray:
    problem = pose_problem(pose)
    if problem:
        raise ViewFileError(f"{source}: malformed pose: {problem}")
    return np.asarray(pose, dtype=np.float64)


def _read_pose_txt(sidecar: Path) -> np.ndarray:
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
    return _checked_pose(np.array(numbers, dtype=np.float64).reshape(4, 4), str(sidecar))


def _read_pose_json(sidecar: Path) -> np.ndarray:
    expected = f"expected {_POSE_JSON} (translation in the view file's unit)"
    document = _read_json(sidecar, "pose sidecar", expected)
    if not isinstance(document, dict) or sorted(document) != ["quaternion", "translation"]:
        raise ViewFileError(f"{sidecar}: pose sidecar holds {str(document)[:80]}; {expected}")
    for name, size in (("translation", 3), ("quaternion", 4)):
        value = document[name]
        if not (isinstance(value, list) and len(value) == size and all(map(_is_json_number, value))):
            raise ViewFileError(f"{sidecar}: {name!r} is {value!r}; expected {size} finite numbers: {expected}")
    quaternion = np.array(document["quaternion"], dtype=np.float64)
    norm = float(np.linalg.norm(quaternion))
    if abs(norm - 1.0) > _QUATERNION_NORM_TOLERANCE:
        raise ViewFileError(
            f"{sidecar}: 'quaternion' {document['quaternion']} has norm {norm:.6g}; expected a unit quaternion "
            f"[w, x, y, z] (norm within {_QUATERNION_NORM_TOLERANCE:g} of 1)"
        )
    pose = np.eye(4)
    pose[:3, :3] = _rotation_matrix(quaternion / norm)
    pose[:3, 3] = document["translation"]
    return pose


def _rotation_matrix(quaternion: np.ndarray) -> np.ndarray:
    """Return the rotation (3, 3) of a unit quaternion ``[w, x, y, z]`` (Hamilton convention)."""
    w, x, y, z = quaternion
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict:
    names = [name for name, _ in pairs]
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise ValueError(f"repeated key(s) {repeated}")
    return dict(pairs)


def _finite(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"{text} is not a finite number")
    return value


def _read_json(sidecar: Path, what: str, expected: str) -> Any:
    try:
        return json.loads(
            sidecar.read_text(encoding="utf-8"),
            object_pairs_hook=_unique_keys,
            parse_float=_finite,
            parse_constant=_finite,
        )
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise ViewFileError(f"{sidecar}: unreadable {what} ({exc}); {expected}") from exc


def _encode_pose(pose: np.ndarray) -> bytes:
    return "".join(" ".join(f"{value:.17g}" for value in row) + "\n" for row in pose).encode("ascii")


# --- npz -------------------------------------------------------------------------------------


def _read_npy_header(stream) -> tuple[tuple[int, ...], bool, np.dtype]:
    """Read an ``.npy`` header from ``stream``, left at the array's first byte: shape, Fortran order, dtype."""
    version = np.lib.format.read_magic(stream)
    read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
    return read_header(stream)


def _npy_header(archive: zipfile.ZipFile, member: str) -> tuple[tuple[int, ...], np.dtype]:
    """Shape and dtype of one ``.npy`` member, from its header alone."""
    with archive.open(member) as stream:
        shape, _, dtype = _read_npy_header(stream)
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


def _mapped_npz(path: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """Map an npz's ``xyz`` and ``intensity`` in place, read-only; None unless both are stored uncompressed.

    A stored member's ``.npy`` bytes follow its local file header (30 bytes, then its name and extra
    field, whose lengths are the header's last two 16-bit fields: the zip format's APPNOTE 4.3.7).
    Nothing is read but the headers; None also when the file does not hold what its directory says.
    """
    try:
        with open(path, "rb") as stream, zipfile.ZipFile(stream) as archive:  # the directory read, then the stream ours
            arrays = []
            for name in ("xyz.npy", "intensity.npy"):
                member = archive.getinfo(name)
                if member.compress_type != zipfile.ZIP_STORED:
                    return None
                stream.seek(member.header_offset)
                header = stream.read(_LOCAL_HEADER.size)
                signature, name_length, extra_length = _LOCAL_HEADER.unpack(header)
                if signature != b"PK\x03\x04":
                    return None
                stream.seek(name_length + extra_length, io.SEEK_CUR)
                shape, fortran, dtype = _read_npy_header(stream)
                if dtype.hasobject:
                    return None
                arrays.append(np.memmap(stream, dtype, "r", stream.tell(), shape, order="F" if fortran else "C"))
    except (OSError, ValueError, KeyError, zipfile.BadZipFile, struct.error):
        return None
    return arrays[0], arrays[1]


def _inspect_npz(path: Path, width: int, height: int, decoding: _Decoding) -> np.ndarray | None:
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


def _load_npz(path: Path, width: int, height: int, decoding: _Decoding) -> tuple[np.ndarray, np.ndarray]:
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
    newline = next((ending for ending in _PLY_NEWLINES if head.startswith(b"ply" + ending)), None)
    if newline is None:
        raise ViewFileError(f"{path}: does not start with the line 'ply'; expected a PLY file")
    lines = head.split(newline)
    byte_order = None
    elements: list[tuple[str, int, dict[str, np.dtype | None]]] = []
    size = len(lines[0]) + len(newline)
    for number, raw_line in enumerate(lines[1:-1], start=2):
        size += len(raw_line) + len(newline)
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


def _ply_intensity_name(properties: Iterable[str], preferred: str) -> str | None:
    """Return the intensity property of a vertex element: ``preferred``, else the first known name present."""
    present = set(properties)
    return next((name for name in (preferred, *PLY_INTENSITY_FALLBACKS) if name in present), None)


def _inspect_ply(path: Path, width: int, height: int, decoding: _Decoding) -> None:
    header = _read_ply_header(path)
    vertices = [element for element in header.elements if element[0] == _PLY_ELEMENT]
    if len(vertices) != 1:
        raise ViewFileError(
            f"{path}: {len(vertices)} '{_PLY_ELEMENT}' elements; expected exactly one "
            f"(elements: {[element[0] for element in header.elements]})"
        )
    _, count, properties = vertices[0]
    expected = f"width*height = {width}*{height} = {width * height}"
    if count < width * height:
        raise ViewFileError(
            f"{path}: {count} vertices, fewer than {expected}: the file keeps only some pixels (an Arena SDK "
            f"export with filterPoints on drops the invalid ones), so the sensor grid is lost; {_PLY_ALL_PIXELS}"
        )
    if count != width * height:
        raise ViewFileError(f"{path}: {count} vertices; expected {expected}")
    intensity = _ply_intensity_name(properties, decoding.ply_intensity)
    if intensity is None:
        names = ", ".join(dict.fromkeys((decoding.ply_intensity, *PLY_INTENSITY_FALLBACKS)))
        raise ViewFileError(
            f"{path}: no vertex property of the intensity ({names}); expected a scalar numeric property, named "
            f"by camera.ply_intensity in campaign.yaml (properties: {list(properties)})"
        )
    for name in (*_PLY_XYZ, intensity):
        dtype = properties.get(name)
        kinds = "f" if name in _PLY_XYZ else _NUMERIC_KINDS
        if dtype is None or dtype.kind not in kinds:
            found = ("a list" if name in properties else "missing") if dtype is None else dtype
            raise ViewFileError(
                f"{path}: vertex property {name!r} is {found}; expected a scalar "
                f"{'float or double' if kinds == 'f' else 'numeric'} property (properties: {list(properties)})"
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


def _load_ply(path: Path, width: int, height: int, decoding: _Decoding) -> tuple[np.ndarray, np.ndarray]:
    vertex = plyfile.PlyData.read(path)[_PLY_ELEMENT]
    intensity_name = _ply_intensity_name((prop.name for prop in vertex.properties), decoding.ply_intensity)
    xyz = np.stack([np.asarray(vertex[name], dtype=np.float64) for name in _PLY_XYZ], axis=-1)
    intensity = np.array(vertex[intensity_name], dtype=np.float32)
    return xyz.reshape(height, width, 3), intensity.reshape(height, width)


def _encode_ply(xyz: np.ndarray, intensity: np.ndarray, *, binary: bool) -> bytes:
    fields = (*_PLY_XYZ, PLY_INTENSITY)
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


# --- raw (Coord3D_ABCY16, Coord3D_ABCY16s) ---------------------------------------------------------


def _inspect_raw(path: Path, width: int, height: int, decoding: _Decoding) -> None:
    pixel_bytes = _RAW_CHANNELS * _RAW_DTYPE.itemsize
    expected = width * height * pixel_bytes
    actual = path.stat().st_size
    if actual != expected:
        raise ViewFileError(
            f"{path}: {actual} bytes; expected width*height*8 = {expected} bytes "
            f"(Coord3D_ABCY16: four 16-bit channels per pixel)"
        )
    rows = np.unique(np.linspace(0, height - 1, min(height, _RAW_SIGN_SAMPLE_ROWS)).astype(int))
    with open(path, "rb") as stream:
        sample = []
        for row in rows:
            stream.seek(int(row) * width * pixel_bytes)
            sample.append(np.frombuffer(stream.read(width * pixel_bytes), dtype=_RAW_DTYPE))
    _decode_raw(path, np.stack(sample).reshape(len(rows), width, _RAW_CHANNELS), decoding.abcy16)


def _load_raw(path: Path, width: int, height: int, decoding: _Decoding) -> tuple[np.ndarray, np.ndarray]:
    channels = np.fromfile(path, dtype=_RAW_DTYPE).reshape(height, width, _RAW_CHANNELS)
    return _decode_raw(path, channels, decoding.abcy16), channels[..., 3]


def _decode_raw(path: Path, channels: np.ndarray, abcy16: dict) -> np.ndarray:
    """Decode uint16 channels (..., 4) to xyz (..., 3) mm, NaN where invalid; refuse data of the other signedness."""
    signed = abcy16["signed"]
    codes = channels[..., :3].view(_RAW_SIGNED_DTYPE) if signed else channels[..., :3]
    xyz = codes * np.asarray(abcy16["scale"], dtype=np.float64) + np.asarray(abcy16["offset"], dtype=np.float64)
    xyz[(codes == _RAW_INVALID[signed]).any(axis=-1)] = np.nan
    valid = valid_pixels(xyz)
    centred = codes.astype(np.int32) - (0 if signed else _RAW_UNSIGNED_CENTRE)
    outer = (np.abs(centred[..., :2]) >= _RAW_SIGN_OUTER).any(axis=-1)
    if not signed:
        outer |= codes[..., 2] == _RAW_UNSIGNED_CENTRE
    odd = int((valid & outer).sum())
    if odd > _RAW_SIGN_SHARE * valid.sum():
        form, other = ("Coord3D_ABCY16s", "Coord3D_ABCY16") if signed else ("Coord3D_ABCY16", "Coord3D_ABCY16s")
        usual = list(ABCY16_DEFAULT["offset"] if signed else ABCY16_SIGNED_OFFSET)
        raise ViewFileError(
            f"{path}: looks like {other} data, not {form} (camera.abcy16.signed: {str(signed).lower()}): {odd} of "
            f"{int(valid.sum())} valid pixels have x or y codes in the outer half of the 16-bit range (near "
            f"+-8192 mm with the usual scale and offset) or the other form's invalid marker; expected "
            f"{form}: set camera.abcy16.signed: {str(not signed).lower()} (usual offset {usual}) if the camera "
            f"saved {other}"
        )
    return xyz


def _encode_raw(path: Path, xyz: np.ndarray, intensity: np.ndarray, abcy16: dict) -> bytes:
    signed = abcy16["signed"]
    scale, offset = (np.asarray(abcy16[key], dtype=np.float64) for key in ("scale", "offset"))
    low, high = _RAW_CODES[signed]
    valid = valid_pixels(xyz)
    codes = np.rint((xyz[valid] - offset) / scale)
    if codes.size and (codes.min() < low or codes.max() > high):
        raise ValueError(
            f"{path}: valid points span ABCY16 codes {codes.min():.0f}..{codes.max():.0f}; expected "
            f"{low}..{high} (xyz in mm = code * {abcy16['scale']} + {list(abcy16['offset'])})"
        )
    coordinates = np.full((*xyz.shape[:2], 3), _RAW_INVALID[signed], dtype=_RAW_SIGNED_DTYPE if signed else _RAW_DTYPE)
    coordinates[valid] = codes
    channels = np.empty((*xyz.shape[:2], _RAW_CHANNELS), dtype=_RAW_DTYPE)
    channels[..., :3] = coordinates.view(_RAW_DTYPE)
    level = np.nan_to_num(np.asarray(intensity, dtype=np.float64), nan=0.0)
    channels[..., 3] = np.clip(np.rint(level), 0, np.iinfo(_RAW_DTYPE).max)
    return channels.tobytes()


_FORMS = {
    ".npz": _Form(_inspect_npz, _load_npz, None),
    ".ply": _Form(_inspect_ply, _load_ply, None),
    ".raw": _Form(_inspect_raw, _load_raw, _RAW_UNITS),
}
