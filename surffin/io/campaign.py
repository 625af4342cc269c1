"""Campaign: ``campaign.yaml`` and the view folders it names, validated up front.

:func:`read_campaign` checks the whole campaign before any work starts: the
YAML (no duplicate, unknown or misspelt keys, right types), the geometry (crop
within the sensor, rois clipped to the crop), the folders (inside the campaign
directory, at least two views each, unambiguous stems), the truth files and,
cheaply, every view file. Each error is a :class:`~surffin.errors.CampaignError`
naming ``campaign.yaml``, the key, the bad value and what is expected.

The structure of ``campaign.yaml`` is described once, as data: a converter per
key (``_KEY`` tables below) checked by one generic mapping checker. The
acquisition settings named in ``camera.match_settings`` are compared over every
view of the calibration and of the items.
"""

from __future__ import annotations

import contextlib
import dataclasses
import difflib
import json
import math
import re
import reprlib
import zipfile
from collections.abc import Callable, Collection, Iterator, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import partial
from pathlib import Path, PurePosixPath, PureWindowsPath
from typing import Any, NoReturn

import numpy as np
import yaml

from surffin.errors import CampaignError, ViewFileError
from surffin.grid import Roi
from surffin.io.viewfile import (
    PLY_INTENSITY,
    View,
    abcy16_encoding,
    check_view,
    check_view_pixels,
    describe_groups,
    list_views,
    npz_headers,
    pose_problem,
    read_settings,
    read_view,
    setting_values,
)

__all__ = [
    "CAMPAIGN_FILE",
    "MIN_VIEWS",
    "NAME_PATTERN",
    "Camera",
    "Item",
    "Reference",
    "Calibration",
    "Campaign",
    "read_campaign",
    "check_pixels",
    "read_truth",
]

CAMPAIGN_FILE = "campaign.yaml"
MIN_VIEWS = 2
NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*")
#: Broken view files a failed :func:`check_pixels` lists (then how many more).
SHOWN_BROKEN = 20
#: View files :func:`check_pixels` reads at once: their reads and checks release the GIL.
PIXEL_READERS = 2

_UNITS = ("m", "mm")
_DISTORTION_SIZES = (4, 5, 8)
_TOP_LEVEL = "(top level)"
_MERGE_TAG = "tag:yaml.org,2002:merge"
_SHOW = reprlib.Repr()
_SHOW.maxstring = _SHOW.maxother = 60


@dataclass(frozen=True)
class Camera:
    """The depth camera, as ``campaign.yaml`` describes it.

    Attributes
    ----------
    width, height : int
        Sensor columns and rows.
    units : {"m", "mm"}
        Unit of xyz (and pose translation) in npz and ply view files.
    intrinsics : dict or None
        ``{"fx", "fy", "cx", "cy"}`` pinhole parameters, pixels, and
        ``"distortion"`` (a tuple of 4, 5 or 8 OpenCV coefficients) when given.
    abcy16 : dict
        ``{"signed": bool, "scale": float or (3,) floats, "offset": (3,) floats}``,
        mm, of raw view files (:func:`~surffin.io.viewfile.abcy16_encoding`).
    ply_intensity : str
        Name of the PLY intensity property.
    saturation : float or None
        Intensity at or above which a pixel is saturated.
    hand_eye : (4, 4) tuple of tuples or None
        Flange-to-camera transform, its translation in the view files' unit;
        the views' poses are then the flange's (world-from-flange).
    match_settings : tuple of str
        Acquisition settings that every view must share.
    """

    width: int
    height: int
    units: str
    intrinsics: dict | None
    abcy16: dict
    ply_intensity: str = PLY_INTENSITY
    saturation: float | None = None
    hand_eye: tuple[tuple[float, ...], ...] | None = None
    match_settings: tuple[str, ...] = ()

    @property
    def sensor(self) -> Roi:
        """The whole sensor as a roi."""
        return Roi((0, self.height), (0, self.width))

    @property
    def distortion(self) -> tuple[float, ...] | None:
        """OpenCV distortion coefficients ``(k1, k2, p1, p2[, k3[, k4, k5, k6]])``, or None."""
        return None if self.intrinsics is None else self.intrinsics.get("distortion")

    @property
    def view_kwargs(self) -> dict:
        """Keyword arguments of :func:`~surffin.io.viewfile.read_view` and ``check_view`` for this camera."""
        return {
            "width": self.width,
            "height": self.height,
            "units": self.units,
            "abcy16": self.abcy16,
            "ply_intensity": self.ply_intensity,
            "saturation": self.saturation,
            "hand_eye": None if self.hand_eye is None else np.array(self.hand_eye),
        }

    @property
    def settings(self) -> dict:
        """Everything ``campaign.yaml`` says about the camera, as plain JSON values (for store attrs and params)."""
        return json.loads(json.dumps(dataclasses.asdict(self)))


@dataclass(frozen=True)
class Item:
    """A specimen (known class, training) or a scene (to classify).

    Attributes
    ----------
    name : str
        Unique among specimens and scenes.
    kind : {"specimen", "scene"}
    views : tuple of Path
        The item's view files, in name order.
    reference : str
        Stem of the reference view, whose pixel grid the item is registered on.
    cls : str or None
        Class name (specimens only).
    roi : Roi or None
        Specimen pixels in the reference view, clipped to the crop.
    roughness_mm : float or None
        Reference roughness measurement, mm.
    truth : Path or None
        Ground-truth label file (scenes only).
    """

    name: str
    kind: str
    views: tuple[Path, ...]
    reference: str
    cls: str | None = None
    roi: Roi | None = None
    roughness_mm: float | None = None
    truth: Path | None = None

    @property
    def view_stems(self) -> tuple[str, ...]:
        """The view names: file stems, in view order."""
        return tuple(path.stem for path in self.views)

    @property
    def reference_view(self) -> Path:
        """The reference view file."""
        return self.views[self.view_stems.index(self.reference)]


@dataclass(frozen=True)
class Reference:
    """Views of the reference panel of known reflectance.

    Attributes
    ----------
    views : tuple of Path
    reflectance : float
        The panel's reflectance, in (0, 1].
    roi : Roi
        Panel pixels in every view, clipped to the crop.
    """

    views: tuple[Path, ...]
    reflectance: float
    roi: Roi


@dataclass(frozen=True)
class Calibration:
    """The radiometric calibration set.

    Attributes
    ----------
    wall : tuple of Path
        Views of a flat diffuse wall at many poses.
    reference : Reference
    """

    wall: tuple[Path, ...]
    reference: Reference


@dataclass(frozen=True)
class Campaign:
    """A validated campaign directory.

    Attributes
    ----------
    root : Path
        The campaign directory, resolved.
    path : Path
        Its ``campaign.yaml``.
    name : str
    camera : Camera
    crop : Roi
        Usable sensor region (default: the whole sensor).
    calibration : Calibration or None
        None when the campaign has no ``calibration:`` section.
    specimens, scenes : dict of str to Item
        In the order of ``campaign.yaml``.
    """

    root: Path
    path: Path
    name: str
    camera: Camera
    crop: Roi
    calibration: Calibration | None
    specimens: dict[str, Item]
    scenes: dict[str, Item]

    @property
    def items(self) -> dict[str, Item]:
        """Specimens, then scenes."""
        return {**self.specimens, **self.scenes}

    @property
    def classes(self) -> list[str]:
        """The specimens' class names, sorted."""
        return sorted({item.cls for item in self.specimens.values()})

    @property
    def view_files(self) -> list[Path]:
        """Every view file: the items', then the calibration set's (wall, then reference)."""
        calibration = () if self.calibration is None else (*self.calibration.wall, *self.calibration.reference.views)
        return [*(view for item in self.items.values() for view in item.views), *calibration]

    def item(self, name: str) -> Item:
        """Return the specimen or scene ``name``.

        Raises
        ------
        CampaignError
            The campaign has no item ``name``; the message names those it has.
        """
        items = self.items
        if name not in items:
            raise _no_item(self.path, name, items)
        return items[name]

    def read_view(self, path: str | Path) -> View:
        """Read one view file with this campaign's camera (size, units, ABCY16 encoding)."""
        return read_view(path, **self.camera.view_kwargs)


def _no_item(yaml_path: Path, name: str, names: Collection[str]) -> CampaignError:
    """Return the error of asking a campaign of the items ``names`` for the item ``name``."""
    return CampaignError(f"{yaml_path}: no item named {name!r}; the campaign has: {', '.join(names) or 'none'}")


def read_campaign(
    path: str | Path,
    *,
    require_calibration: bool = True,
    check_views: bool = True,
    items: Collection[str] | None = None,
) -> Campaign:
    """Read and validate a campaign.

    Parameters
    ----------
    path : str or Path
        The campaign directory, or its ``campaign.yaml``.
    require_calibration : bool
        False when an existing calibration store is used; the
        ``calibration:`` section is then optional (still checked if present).
    check_views : bool
        Check the structure of every view file and its sidecars (cheap:
        headers and sizes), and that the settings of ``camera.match_settings``
        agree over the views.
    items : collection of str, optional
        Build only these specimens and scenes, as a job that reads one item
        needs: the other items' folders, view files and truth files are not
        read (``campaign.yaml`` is still checked whole), and ``check_views``
        covers the calibration set's views and these items' only.

    Returns
    -------
    Campaign

    Raises
    ------
    CampaignError
        Anything in the campaign breaks the contract; the message names
        ``campaign.yaml``, the key (e.g. ``specimens.S1.roi.y``), the bad value
        and what is expected; or a name of ``items`` is no item of the
        campaign (the message names those it has).
    """
    yaml_path = _campaign_file(Path(path))
    try:
        entries = _CAMPAIGN(_load_yaml(yaml_path), "")
        builder = _Builder.for_campaign(yaml_path, entries, check_views, items)
        return builder.campaign(entries, require_calibration, items)
    except _Invalid as exc:
        raise CampaignError(f"{yaml_path}: {exc.key}: {exc.message}") from exc.__cause__


def check_pixels(campaign: Campaign, views, known: Mapping | None = None) -> dict:
    """Read view files' pixels for the contract's pixel rules, which their headers cannot tell.

    Intensity NaN, infinite or negative on a pixel whose xyz is valid, and a view without a valid
    pixel, are refused (:func:`~surffin.io.viewfile.check_view_pixels`). :data:`PIXEL_READERS`
    files are read at once, in threads; the broken ones are named in the order of ``views``.

    Parameters
    ----------
    campaign : Campaign
        Its camera decodes the files.
    views : iterable of path
        The view files, their structure checked (:func:`~surffin.io.viewfile.check_view`, as
        :func:`read_campaign` does for the campaign's views): it is not checked again here.
    known : mapping, optional
        A record this function returned before: the files it lists with their present size and
        modification time, read with the same camera settings, are not read again.

    Returns
    -------
    dict
        The record: ``camera`` (its settings) and ``views`` (path -> [size, modification time in ns]).

    Raises
    ------
    ViewFileError
        Naming every broken file and its problem (at most :data:`SHOWN_BROKEN`, then how many more).
    """
    camera = campaign.camera.settings
    recorded = known["views"] if known and known.get("camera") == camera else {}
    stamps = {}
    for path in dict.fromkeys(str(view) for view in views):
        stat = Path(path).stat()
        stamps[path] = [stat.st_size, stat.st_mtime_ns]
    unread = [path for path, stamp in stamps.items() if recorded.get(path) != stamp]
    with ThreadPoolExecutor(PIXEL_READERS) as pool:
        problems = dict(zip(unread, pool.map(partial(_pixel_problem, campaign.camera), unread)))
    broken = [problem for problem in problems.values() if problem is not None]
    checked = {path: stamp for path, stamp in stamps.items() if problems.get(path) is None}
    if broken:
        more = f"\n... and {len(broken) - SHOWN_BROKEN} more" if len(broken) > SHOWN_BROKEN else ""
        raise ViewFileError(
            f"{len(broken)} of {len(checked) + len(broken)} view files break the campaign contract:\n"
            + "\n".join(broken[:SHOWN_BROKEN])
            + more
        )
    return {"camera": camera, "views": checked}


def _pixel_problem(camera: Camera, path: str) -> str | None:
    """Say what breaks the pixel rules in a view file (its :class:`ViewFileError`), or return None."""
    try:
        check_view_pixels(
            path, width=camera.width, height=camera.height, abcy16=camera.abcy16, ply_intensity=camera.ply_intensity
        )
    except ViewFileError as error:
        return str(error)
    return None


def read_truth(path: str | Path, *, width: int, height: int) -> tuple[np.ndarray, list[str]]:
    """Read a ground-truth label file.

    Parameters
    ----------
    path : str or Path
        npz with ``label`` and ``classes``, loaded without pickle.
    width, height : int
        Sensor size; ``label`` is on the sensor grid of the scene's reference view.

    Returns
    -------
    label : (height, width) ndarray of int64
        Class index 0..K-1, or -1 where not scored.
    classes : list of str
        The K class names, in label order.

    Raises
    ------
    CampaignError
        The file is unreadable or inconsistent.
    """
    path = Path(path)
    expected = (
        f"expected an npz with 'label' (integer, shape {(height, width)}, values -1..K-1) and "
        f"'classes' (K distinct strings)"
    )
    try:
        missing = sorted({"label", "classes"} - set(npz_headers(path)))
    except ViewFileError as exc:
        raise CampaignError(f"{path}: unreadable truth file ({exc.__cause__ or exc}); {expected}") from exc
    if missing:
        raise CampaignError(f"{path}: truth file lacks {missing}; {expected}")
    try:
        with np.load(path, allow_pickle=False) as arrays:
            label, classes = arrays["label"], arrays["classes"]
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise CampaignError(f"{path}: unreadable truth file ({exc}); {expected}") from exc
    if label.dtype.kind not in "iu" or label.shape != (height, width):
        raise CampaignError(f"{path}: 'label' is {label.dtype} of shape {label.shape}; {expected}")
    if classes.dtype.kind not in "US" or classes.ndim != 1 or classes.size == 0:
        raise CampaignError(f"{path}: 'classes' is {classes.dtype} of shape {classes.shape}; {expected}")
    names = [str(name, "utf-8") if isinstance(name, bytes) else str(name) for name in classes.tolist()]
    if len(set(names)) != len(names):
        raise CampaignError(f"{path}: 'classes' repeats a name: {names}; {expected}")
    low, high = int(label.min()), int(label.max())
    if low < -1 or high >= len(names):
        raise CampaignError(f"{path}: 'label' spans {low}..{high} with {len(names)} classes; {expected}")
    return label.astype(np.int64), names


# --- errors and YAML -------------------------------------------------------------------------


class _Invalid(Exception):
    """A problem at one key of ``campaign.yaml``; :func:`read_campaign` adds the file name."""

    def __init__(self, key: str, message: str) -> None:
        super().__init__(f"{key}: {message}")
        self.key = key or _TOP_LEVEL
        self.message = message


def _fail(key: str, value: Any, expected: str) -> NoReturn:
    raise _Invalid(key, f"got {_SHOW.repr(value)}; expected {expected}")


@contextlib.contextmanager
def _at_key(key: str) -> Iterator[None]:
    """Report an error about a file named at ``key`` (a view or truth file) as a problem of that key."""
    try:
        yield
    except (CampaignError, ViewFileError) as exc:
        raise _Invalid(key, str(exc)) from exc


class _StrictLoader(getattr(yaml, "CSafeLoader", yaml.SafeLoader)):
    """``yaml.SafeLoader`` that refuses a key repeated within one mapping.

    Parsed by libyaml where PyYAML has it (its wheels do): every job reads campaign.yaml, and
    the pure-Python parser takes 19 ms for a campaign of 49 items, libyaml 3.
    """

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        first_lines: dict[Any, int] = {}
        for key_node, _ in node.value:
            if key_node.tag == _MERGE_TAG:
                continue
            key = self.construct_object(key_node, deep=True)
            try:
                first = first_lines.get(key)
            except TypeError:
                continue  # an unhashable key: the base class reports it
            if first is not None:
                raise _Invalid(
                    f"line {key_node.start_mark.line + 1}",
                    f"duplicate key {key!r} (first on line {first}); expected each key once in a mapping",
                )
            first_lines[key] = key_node.start_mark.line + 1
        return super().construct_mapping(node, deep=deep)


def _campaign_file(path: Path) -> Path:
    yaml_path = (path / CAMPAIGN_FILE if path.is_dir() else path).resolve()
    if not yaml_path.is_file():
        raise CampaignError(f"{yaml_path}: no such file; expected a campaign directory holding {CAMPAIGN_FILE}")
    return yaml_path


def _load_yaml(yaml_path: Path) -> Any:
    try:
        return yaml.load(yaml_path.read_text(encoding="utf-8"), Loader=_StrictLoader)  # noqa: S506 (a SafeLoader)
    except (OSError, UnicodeDecodeError) as exc:
        raise CampaignError(f"{yaml_path}: unreadable ({exc}); expected a UTF-8 YAML file") from exc
    except yaml.YAMLError as exc:
        raise CampaignError(f"{yaml_path}: not valid YAML: {exc}") from exc


# --- the schema: one converter per key, one generic mapping checker ----------------------------

_Convert = Callable[[Any, str], Any]


@dataclass(frozen=True)
class _Key:
    """One key of a mapping in ``campaign.yaml``.

    Attributes
    ----------
    convert : callable (value, key path) -> converted value
        Raises ``_Invalid`` naming the key path when the value is wrong.
    required : bool
        A missing (or null) required key is an error.
    default : Any
        YAML value used, and converted, when the key is missing; None leaves
        the value None.
    """

    convert: _Convert
    required: bool = False
    default: Any = None


def _child(key: str, name: Any) -> str:
    return f"{key}.{name}" if key else str(name)


def _mapping(value: Any, key: str) -> Mapping:
    if not isinstance(value, Mapping):
        _fail(key, value, "a mapping of keys to values")
    return value


def _record(schema: dict[str, _Key], build: Callable[..., Any] = dict) -> _Convert:
    """Make a converter of a mapping with the keys of ``schema``; unknown keys are errors."""

    def convert(value: Any, key: str) -> Any:
        mapping = _mapping(value, key)
        for name in mapping:
            if name not in schema:
                close = difflib.get_close_matches(str(name), list(schema), n=1)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                raise _Invalid(_child(key, name), f"unknown key {name!r}{hint}; expected one of: {', '.join(schema)}")
        fields = {}
        for name, spec in schema.items():
            value = mapping.get(name, spec.default)
            if value is None and spec.required:
                raise _Invalid(_child(key, name), f"missing; it is required in {key or _TOP_LEVEL}")
            fields[name] = None if value is None else spec.convert(value, _child(key, name))
        return build(**fields)

    return convert


def _named(convert_entry: _Convert) -> _Convert:
    """Make a converter of a mapping from item names to entries."""

    def convert(value: Any, key: str) -> dict[str, Any]:
        return {
            _name(name, _child(key, name)): convert_entry(entry, _child(key, name))
            for name, entry in _mapping(value, key).items()
        }

    return convert


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value: Any) -> bool:
    return _is_int(value) or (isinstance(value, float) and math.isfinite(value))


def _number(accept: Callable[[float], bool], expected: str, *, integer: bool = False) -> _Convert:
    """Make a converter of a finite number (an int if ``integer``, bool never) that ``accept`` allows."""

    def convert(value: Any, key: str) -> int | float:
        if not ((_is_int(value) if integer else _is_number(value)) and accept(value)):
            _fail(key, value, expected)
        return int(value) if integer else float(value)

    return convert


def _is_positive(value: float) -> bool:
    return value > 0


def _is_any(value: float) -> bool:
    return True


def _is_reflectance(value: float) -> bool:
    return 0 < value <= 1


def _text(value: Any, key: str) -> str:
    if not isinstance(value, str) or not value.strip():
        _fail(key, value, "a non-empty string (quote it in YAML if it looks like a number)")
    return value


def _name(value: Any, key: str) -> str:
    if not isinstance(value, str) or not NAME_PATTERN.fullmatch(value):
        _fail(key, value, f"a name matching {NAME_PATTERN.pattern} (quote it in YAML if it looks like a number)")
    return value


def _units(value: Any, key: str) -> str:
    if value not in _UNITS:
        _fail(key, value, f"one of {', '.join(_UNITS)}")
    return value


def _relative_path(value: Any, key: str) -> str:
    relative = isinstance(value, str) and value.strip() and not value.startswith("~")
    if not relative or PurePosixPath(value).is_absolute() or PureWindowsPath(value).is_absolute():
        _fail(key, value, "a path relative to the campaign directory (absolute paths are not allowed)")
    return value


def _range(value: Any, key: str) -> tuple[int, int]:
    if not (
        isinstance(value, list)
        and len(value) == 2
        and all(_is_int(bound) for bound in value)
        and 0 <= value[0] < value[1]
    ):
        _fail(key, value, "a half-open pixel range [start, stop] of integers with 0 <= start < stop")
    return value[0], value[1]


def _offset(value: Any, key: str) -> tuple[float, float, float]:
    if not (isinstance(value, list) and len(value) == 3 and all(_is_number(part) for part in value)):
        _fail(key, value, "three finite numbers [x, y, z], mm")
    return tuple(float(part) for part in value)


def _boolean(value: Any, key: str) -> bool:
    if not isinstance(value, bool):
        _fail(key, value, "true or false")
    return value


def _scale(value: Any, key: str) -> float | tuple[float, float, float]:
    if _is_number(value) and value > 0:
        return float(value)
    if not (isinstance(value, list) and len(value) == 3 and all(_is_number(part) and part > 0 for part in value)):
        _fail(key, value, "a number > 0 (mm per code) or three, one per axis [sA, sB, sC]")
    return tuple(float(part) for part in value)


def _property_name(value: Any, key: str) -> str:
    if not isinstance(value, str) or not re.fullmatch(r"\S+", value):
        _fail(key, value, "a PLY property name (one word, e.g. intensity or scalar_Intensity)")
    return value


def _distortion(value: Any, key: str) -> tuple[float, ...]:
    sizes = ", ".join(map(str, _DISTORTION_SIZES))
    if not (isinstance(value, list) and len(value) in _DISTORTION_SIZES and all(map(_is_number, value))):
        _fail(key, value, f"a list of {sizes} finite numbers: OpenCV's [k1, k2, p1, p2, k3, k4, k5, k6] or its start")
    return tuple(float(part) for part in value)


def _intrinsics(*, distortion: tuple[float, ...] | None, **pinhole: float) -> dict:
    return pinhole if distortion is None else {**pinhole, "distortion": distortion}


def _rigid(value: Any, key: str) -> tuple[tuple[float, ...], ...]:
    expected = "a rigid 4x4 transform (flange-to-camera), four rows of four numbers"
    if not (
        isinstance(value, list)
        and len(value) == 4
        and all(isinstance(row, list) and len(row) == 4 and all(map(_is_number, row)) for row in value)
    ):
        _fail(key, value, expected)
    problem = pose_problem(np.array(value, dtype=np.float64))
    if problem:
        _fail(key, value, f"{expected}: {problem}")
    return tuple(tuple(float(part) for part in row) for row in value)


def _setting_names(value: Any, key: str) -> tuple[str, ...]:
    if not (isinstance(value, list) and all(isinstance(name, str) and name for name in value)):
        _fail(key, value, "a list of setting names (keys of the views' <stem>.meta.json)")
    if len(set(value)) != len(value):
        _fail(key, value, "each setting name once")
    return tuple(value)


_positive_int = _number(_is_positive, "a positive integer", integer=True)
_positive = _number(_is_positive, "a number > 0")
_finite = _number(_is_any, "a finite number")

_ROI = _record({"y": _Key(_range, required=True), "x": _Key(_range, required=True)}, build=Roi)
_CAMERA = _record(
    {
        "width": _Key(_positive_int, required=True),
        "height": _Key(_positive_int, required=True),
        "units": _Key(_units, required=True),
        "intrinsics": _Key(
            _record(
                {
                    "fx": _Key(_positive, required=True),
                    "fy": _Key(_positive, required=True),
                    "cx": _Key(_finite, required=True),
                    "cy": _Key(_finite, required=True),
                    "distortion": _Key(_distortion),
                },
                build=_intrinsics,
            )
        ),
        "abcy16": _Key(
            _record({"signed": _Key(_boolean), "scale": _Key(_scale), "offset": _Key(_offset)}, build=abcy16_encoding),
            default={},
        ),
        "ply_intensity": _Key(_property_name, default=PLY_INTENSITY),
        "saturation": _Key(_positive),
        "hand_eye": _Key(_rigid),
        "match_settings": _Key(_setting_names, default=[]),
    },
    build=Camera,
)
_CALIBRATION = _record(
    {
        "wall": _Key(_relative_path, required=True),
        "reference": _Key(
            _record(
                {
                    "views": _Key(_relative_path, required=True),
                    "reflectance": _Key(_number(_is_reflectance, "a reflectance in (0, 1]"), required=True),
                    "roi": _Key(_ROI, required=True),
                }
            ),
            required=True,
        ),
    }
)
_SPECIMEN = _record(
    {
        "class": _Key(_name, required=True),
        "views": _Key(_relative_path, required=True),
        "roi": _Key(_ROI),
        "roughness_mm": _Key(_positive),
        "reference": _Key(_text),
    }
)
_SCENE = _record(
    {
        "views": _Key(_relative_path, required=True),
        "truth": _Key(_relative_path),
        "reference": _Key(_text),
    }
)
_CAMPAIGN = _record(
    {
        "name": _Key(_text),
        "camera": _Key(_CAMERA, required=True),
        "crop": _Key(_ROI),
        "calibration": _Key(_CALIBRATION),
        "specimens": _Key(_named(_SPECIMEN), default={}),
        "scenes": _Key(_named(_SCENE), default={}),
    }
)


# --- from checked entries to a Campaign: paths, views, geometry ---------------------------------


def _inside(root: Path, relative: str, key: str, *, folder: bool) -> Path:
    """``relative`` resolved (symlinks too) inside ``root``, as an existing folder or file."""
    target = (root / relative).resolve()
    if not target.is_relative_to(root):
        _fail(key, relative, f"a path that stays inside the campaign directory {root} (it leads to {target})")
    if not (target.is_dir() if folder else target.is_file()):
        _fail(key, relative, f"an existing {'folder' if folder else 'file'} inside {root}")
    return target


def _checked_truth(root: Path, relative: str, key: str, camera: Camera) -> Path:
    """Return the truth file of a scene, read once to check it."""
    path = _inside(root, relative, key, folder=False)
    with _at_key(key):
        read_truth(path, width=camera.width, height=camera.height)
    return path


@dataclass(frozen=True)
class _Builder:
    """Checks what needs the file system and the camera, and builds the dataclasses.

    Attributes
    ----------
    yaml_path : Path
    camera : Camera
    crop : Roi
        Checked to lie within the sensor.
    truths : dict of str to Path
        Scene name to its checked truth file; these files are never views.
    check_views : bool
    """

    yaml_path: Path
    camera: Camera
    crop: Roi
    truths: dict[str, Path]
    check_views: bool

    @classmethod
    def for_campaign(
        cls, yaml_path: Path, entries: dict, check_views: bool, items: Collection[str] | None = None
    ) -> _Builder:
        """Check the crop and the truth files (of ``items``' scenes when given: the others are found, not read)."""
        camera = entries["camera"]
        crop = entries["crop"] or camera.sensor
        for axis, size, what in (("y", camera.height, "rows"), ("x", camera.width, "columns")):
            bounds = getattr(crop, axis)
            if bounds[1] > size:
                _fail(f"crop.{axis}", list(bounds), f"a range within the sensor's {size} {what} (not clipped)")
        truths = {}
        for name, scene in entries["scenes"].items():
            if scene["truth"] is None:
                continue
            key = f"scenes.{name}.truth"
            if items is None or name in items:
                truths[name] = _checked_truth(yaml_path.parent, scene["truth"], key, camera)
            else:  # still never a view of the items built
                truths[name] = _inside(yaml_path.parent, scene["truth"], key, folder=False)
        return cls(yaml_path, camera, crop, truths, check_views)

    @property
    def root(self) -> Path:
        return self.yaml_path.parent

    def campaign(self, entries: dict, require_calibration: bool, items: Collection[str] | None = None) -> Campaign:
        """Build the campaign, of the items ``items`` only when given."""
        specimens, scenes = entries["specimens"], entries["scenes"]
        if not specimens and not scenes:
            raise _Invalid("specimens", "no specimens and no scenes; expected at least one item")
        for name in scenes:
            if name in specimens:
                raise _Invalid(
                    f"scenes.{name}", "the name is also a specimen's; specimens and scenes share one namespace"
                )
        calibration = entries["calibration"]
        if calibration is None and require_calibration:
            raise _Invalid(
                "calibration", "missing; expected a calibration section (wall, reference) or a calibration store"
            )
        if items is not None:
            for name in items:
                if name not in specimens and name not in scenes:
                    raise _no_item(self.yaml_path, name, [*specimens, *scenes])
            specimens = {name: entry for name, entry in specimens.items() if name in items}
            scenes = {name: entry for name, entry in scenes.items() if name in items}
        campaign = Campaign(
            root=self.root,
            path=self.yaml_path,
            name=entries["name"] or self.root.name,
            camera=self.camera,
            crop=self.crop,
            calibration=None if calibration is None else self.calibration(calibration),
            specimens={name: self.item(name, "specimen", entry) for name, entry in specimens.items()},
            scenes={name: self.item(name, "scene", entry) for name, entry in scenes.items()},
        )
        if self.check_views:
            self.check_settings(campaign)
        return campaign

    def check_settings(self, campaign: Campaign) -> None:
        """Check that the settings of ``camera.match_settings`` are equal in every view of the campaign."""
        calibration = campaign.calibration
        views = [] if calibration is None else [*calibration.wall, *calibration.reference.views]
        views += [view for item in campaign.items.values() for view in item.views]
        key = "camera.match_settings"
        settings = {}
        for view in views if self.camera.match_settings else ():
            with _at_key(key):
                settings[str(view.relative_to(self.root))] = read_settings(view)
        for name in self.camera.match_settings:
            groups = setting_values(settings, name)
            if len(groups) > 1:
                raise _Invalid(
                    key,
                    f"setting {name!r} differs between views ({describe_groups(groups)}); expected one value in "
                    f"every view of the calibration and of the items, given by its <stem>.meta.json: acquire them "
                    f"with the same settings, or remove {name!r} from camera.match_settings",
                )

    def calibration(self, entry: dict) -> Calibration:
        reference = entry["reference"]
        return Calibration(
            wall=self.views(entry["wall"], "calibration.wall"),
            reference=Reference(
                views=self.views(reference["views"], "calibration.reference.views"),
                reflectance=reference["reflectance"],
                roi=self.roi(reference["roi"], "calibration.reference.roi"),
            ),
        )

    def item(self, name: str, kind: str, entry: dict) -> Item:
        key = f"{kind}s.{name}"
        views = self.views(entry["views"], f"{key}.views")
        stems = [view.stem for view in views]
        reference = entry["reference"] or stems[0]
        if reference not in stems:
            _fail(f"{key}.reference", reference, f"the stem of one of the item's views: {', '.join(stems)}")
        roi = entry.get("roi")
        return Item(
            name=name,
            kind=kind,
            views=views,
            reference=reference,
            cls=entry.get("class"),
            roi=None if roi is None else self.roi(roi, f"{key}.roi"),
            roughness_mm=entry.get("roughness_mm"),
            truth=self.truths.get(name),
        )

    def views(self, relative: str, key: str) -> tuple[Path, ...]:
        """List the view files of a folder, at least :data:`MIN_VIEWS`, each checked if asked."""
        folder = _inside(self.root, relative, key, folder=True)
        with _at_key(key):
            views = list_views(folder, exclude=self.truths.values())
        if len(views) < MIN_VIEWS:
            _fail(
                key,
                relative,
                f"a folder with at least {MIN_VIEWS} view files (*.npz, *.ply, *.raw); {folder} holds "
                f"{[view.name for view in views]}",
            )
        for view in views if self.check_views else ():
            with _at_key(key):
                check_view(view, **self.camera.view_kwargs)
        return tuple(views)

    def roi(self, roi: Roi, key: str) -> Roi:
        """``roi`` clipped to the crop."""
        try:
            return roi.clip(self.crop)
        except ValueError:
            crop = self.crop
            _fail(
                key,
                {"y": list(roi.y), "x": list(roi.x)},
                f"a roi overlapping the crop {{y: {list(crop.y)}, x: {list(crop.x)}}}",
            )
