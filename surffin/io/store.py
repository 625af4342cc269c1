"""Processed zarr stores: written complete or not at all, readable with plain xarray.

A store is written into a hidden temporary sibling (``.<name>.partial-<token>``)
and renamed onto its final path only once everything, consolidated metadata
included, is on disk. Anything at a store's final path is therefore complete;
leftovers of a crashed or killed run carry names no reader mistakes for a store
and are removed by the next write of the same store.

Attributes netCDF cannot hold (nested dicts, lists of strings, booleans, None)
are stored as JSON strings and named in the attribute ``surffin_json_attrs``;
:func:`open_store` decodes them, so ``xr.open_zarr(store).to_netcdf(path)``
works for every store and surffin still reads the values it wrote. :func:`load_store` loads a
store whole, by :mod:`surffin.io.zarrread` (without zarr-python's overhead) where it can.
"""

from __future__ import annotations

import copy
import functools
import json
import numbers
import os
import shutil
import tempfile
import threading
import uuid
import warnings
from collections import OrderedDict
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import xarray as xr
import zarr

from surffin._version import __version__
from surffin.errors import StoreError
from surffin.io.zarrread import read_store
from surffin.io.zarrwrite import encode_store, probe
from surffin.paper import CITATION

__all__ = [
    "DEFAULT_CHUNKS",
    "JSON_ATTRS",
    "write_store",
    "open_store",
    "load_store",
    "own_files",
    "same_dataset",
    "StoreCache",
    "provenance",
    "clean_leftovers",
    "encode_attrs",
    "decode_attrs",
]

#: Default dask/zarr chunk sizes over the image dimensions (a camera frame in one or two chunks:
#: fewer, larger tasks cost less overhead: an item's chain ran 1.13x faster than with 256, measured
#: with benchmarks/bench_chunks.py); ``view`` is never split.
DEFAULT_CHUNKS = {"y": 512, "x": 512}

#: The attribute naming (as a JSON list) the attributes stored as JSON strings.
JSON_ATTRS = "surffin_json_attrs"
#: The CF conventions the stores follow.
CONVENTIONS = "CF-1.10"

_PARTIAL = ".partial-"
_RETIRED = ".retired-"


def provenance(
    stage: str, parameters: Mapping | None = None, inputs: Mapping | None = None, version: int | None = None
) -> dict:
    """Attributes recording what made a store.

    Parameters
    ----------
    stage : str
        Name of the stage that made the store (``"ingest"``, ``"aoi"``, ...).
    parameters : mapping, optional
        The processing parameters of that stage (JSON-serialisable values).
    inputs : mapping, optional
        Description of the inputs (file names, sizes, checksums, ...).
    version : int, optional
        The stage's code version (:data:`surffin.pipeline.table.STAGES`).

    Returns
    -------
    dict
        ``surffin_version``, ``surffin_stage``, ``surffin_parameters``, ``surffin_inputs``
        and, when given, ``surffin_code_version``; CF's ``Conventions``, ``title``,
        ``references`` (the method's paper) and ``history`` (what made it; no time stamp, so
        that the same inputs give identical stores: the files' times say when).
    """
    attrs = {
        "Conventions": CONVENTIONS,
        "title": f"surffin {stage} store",
        "references": CITATION,
        "history": f"surffin {__version__}, stage {stage}",
        "surffin_version": __version__,
        "surffin_stage": stage,
        "surffin_parameters": dict(parameters or {}),
        "surffin_inputs": dict(inputs or {}),
    }
    return attrs if version is None else attrs | {"surffin_code_version": version}


def _portable(value) -> bool:
    # What netCDF-3 and netCDF-4 both hold: a string, a real number or a non-empty 1-D numeric array.
    if isinstance(value, (bool, np.bool_)):
        return False
    if isinstance(value, (str, numbers.Real)):
        return True
    if isinstance(value, np.ndarray):
        return value.ndim == 1 and value.size > 0 and value.dtype.kind in "iuf"
    if isinstance(value, (list, tuple)):
        return len(value) > 0 and all(
            isinstance(v, numbers.Real) and not isinstance(v, (bool, np.bool_)) for v in value
        )
    return False


def _plain(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"attribute value {value!r} of type {type(value).__name__} is not JSON-serialisable")


def encode_attrs(attrs: Mapping) -> dict:
    """Attributes as netCDF holds them: each value it cannot hold as a JSON string, named in ``surffin_json_attrs``.

    Parameters
    ----------
    attrs : mapping
        Attributes of a Dataset or variable; values JSON-serialisable (numpy
        scalars and arrays included).

    Returns
    -------
    dict
        The attributes to write; :func:`decode_attrs` inverts it.
    """
    encoded = {key: value for key, value in attrs.items() if key != JSON_ATTRS}
    as_json = sorted(key for key, value in encoded.items() if not _portable(value))
    for key in as_json:
        encoded[key] = json.dumps(encoded[key], default=_plain)
    return encoded | {JSON_ATTRS: json.dumps(as_json)} if as_json else encoded


def decode_attrs(attrs: Mapping) -> dict:
    """Invert :func:`encode_attrs`: the attributes named in ``surffin_json_attrs`` parsed from JSON."""
    decoded = {key: value for key, value in attrs.items() if key != JSON_ATTRS}
    for key in json.loads(attrs.get(JSON_ATTRS, "[]")):
        decoded[key] = json.loads(decoded[key])
    return decoded


def _leftovers(path: Path) -> list[Path]:
    prefixes = (f".{path.name}{_PARTIAL}", f".{path.name}{_RETIRED}")
    if not path.parent.is_dir():
        return []
    return [p for p in path.parent.iterdir() if p.name.startswith(prefixes)]


def clean_leftovers(path: str | os.PathLike) -> list[Path]:
    """Remove what an interrupted write of the store at ``path`` left behind.

    Returns
    -------
    list of Path
        The removed temporary folders.
    """
    removed = _leftovers(Path(path))
    for leftover in removed:
        shutil.rmtree(leftover, ignore_errors=True)
    return removed


def _chunking(ds: xr.Dataset, chunks: Mapping[str, int]) -> dict[str, int]:
    wanted = {"view": -1, **{dim: size for dim, size in chunks.items() if dim != "view"}}
    return {dim: size for dim, size in wanted.items() if dim in ds.dims}


def _encoding(ds: xr.Dataset, chunking: Mapping[str, int] | None = None) -> dict[str, dict]:
    """Each variable's zarr encoding; with ``chunking``, its chunks too (those ``Dataset.chunk`` would give)."""
    # Noisy floats gain little from compression and write 2-4x slower with it
    # (NUMERICS.md); masks and labels compress well and keep zarr's default.
    encoding = {
        name: {"compressors": None} for name, var in ds.variables.items() if np.issubdtype(var.dtype, np.floating)
    }
    for name, var in ds.variables.items() if chunking is not None else ():
        if name not in ds.indexes:
            sizes = {dim: chunking.get(dim, -1) for dim in var.dims}
            chunks = tuple(var.sizes[dim] if size == -1 else min(size, var.sizes[dim]) for dim, size in sizes.items())
            encoding.setdefault(name, {})["chunks"] = chunks
    return encoding


def _strings_as_objects(ds: xr.Dataset) -> xr.Dataset:
    # Fixed-width unicode has no zarr v3 specification; variable-length strings do.
    # Strings are small labels: they are held in memory, never as dask arrays,
    # whose object dtype xarray would have to load to encode anyway.
    # Variables, not DataArrays: a DataArray would bring back its index coordinate as it was (fixed-width).
    fixed = {name: var.compute().astype(object) for name, var in ds.variables.items() if var.dtype.kind in "UO"}
    coords = {name: arr for name, arr in fixed.items() if name in ds.coords}
    data = {name: arr for name, arr in fixed.items() if name not in ds.coords}
    return ds.assign_coords(coords).assign(data)


def _write_files(encoded: Mapping[str, bytes], folder: Path) -> None:
    """Write the documents and chunks of a store encoded in memory (key -> bytes) as zarr's file store would."""
    for key, content in encoded.items():
        file = folder.joinpath(*key.split("/"))
        file.parent.mkdir(parents=True, exist_ok=True)
        file.write_bytes(content)


def _to_zarr(ds: xr.Dataset, target, encoding: Mapping, compute: bool):
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Consolidated metadata", category=UserWarning)
        return ds.to_zarr(target, mode="w-", zarr_format=3, consolidated=True, encoding=encoding, compute=compute)


def _spelled(value) -> str:
    """Return a value's ``repr`` with the type of every part, to compare attributes exactly."""
    if isinstance(value, dict):
        return "{" + ", ".join(f"{key!r}: {_spelled(item)}" for key, item in value.items()) + "}"
    if isinstance(value, list | tuple):
        return f"{type(value).__name__}(" + ", ".join(_spelled(item) for item in value) + ")"
    return f"{type(value).__name__}:{value!r}"


def same_dataset(a: xr.Dataset, b: xr.Dataset) -> bool:
    """Tell whether two Datasets in memory are the same, as two loads of one store must be.

    ``Dataset.identical``, and the variables, coordinates and indexes in the same order with the
    same dtypes, the numbers and booleans bit for bit, the attributes with the same types.
    """
    return (
        a.identical(b)
        and all(list(getattr(a, names)) == list(getattr(b, names)) for names in ("variables", "coords", "xindexes"))
        and _spelled(a.attrs) == _spelled(b.attrs)
        and all(
            type(var) is type(b.variables[name])
            and var.dtype == b.variables[name].dtype
            and _spelled(var.attrs) == _spelled(b.variables[name].attrs)
            and (var.dtype.kind not in "fiub" or var.values.tobytes() == b.variables[name].values.tobytes())
            for name, var in a.variables.items()
        )
        and all(a.xindexes[name].coord_dtype == index.coord_dtype for name, index in b.xindexes.items())
    )


@functools.cache
def own_files() -> bool:
    """Tell whether surffin's own writer and reader of store files agree with this xarray and zarr-python.

    :mod:`surffin.io.zarrwrite` and :mod:`surffin.io.zarrread` write and read the files as some
    versions of xarray and zarr-python do, not every one. Checked once per process on
    :func:`~surffin.io.zarrwrite.probe`: the files ``to_zarr`` writes of it, byte for byte, and the
    Dataset xarray loads of them. When either differs, every store is written and loaded by
    xarray and zarr-python.
    """
    ds = _prepared(probe())
    encoding = _encoding(ds, {"y": 3, "x": 4})
    memory: dict = {}
    _to_zarr(ds, zarr.storage.MemoryStore(memory), encoding, compute=True)
    files = {key: buffer.to_bytes() for key, buffer in memory.items()}
    if encode_store(ds, encoding) != files:
        return False
    with tempfile.TemporaryDirectory() as folder:
        _write_files(files, Path(folder))
        mine = read_store(folder)
        return mine is not None and same_dataset(mine, xr.open_zarr(folder, consolidated=True, chunks=None).load())


def _prepared(ds: xr.Dataset) -> xr.Dataset:
    """Return ``ds`` as the writers take it: its encoding dropped, strings as objects, attributes encoded."""
    ds = _strings_as_objects(ds.drop_encoding()).copy(deep=False)
    ds.attrs = encode_attrs(ds.attrs)
    for variable in ds.variables.values():
        variable.attrs = encode_attrs(variable.attrs)
    return ds


def write_store(
    ds: xr.Dataset, path: str | os.PathLike, *, chunks: Mapping[str, int] | None = None, scheduler=None
) -> Path:
    """Write ``ds`` as a zarr v3 store with consolidated metadata, atomically.

    Parameters
    ----------
    ds : Dataset
        numpy- or dask-backed; dask arrays are computed chunk by chunk while writing.
    path : path-like
        Final path of the store (conventionally ending in ``.zarr``).
    chunks : mapping of str to int, optional
        Chunk sizes per dimension (default :data:`DEFAULT_CHUNKS`); ``view`` is
        always kept whole so that per-pixel fits see all views of a pixel at once.
    scheduler : callable, optional
        The dask scheduler that writes a dask-backed ``ds``; default: the one
        configured. A Dataset in memory is written without dask.

    Returns
    -------
    Path
        The final path. An existing store there is replaced only after the new
        one is complete.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    clean_leftovers(path)
    chunking = _chunking(ds, DEFAULT_CHUNKS if chunks is None else chunks)
    # A Dataset in memory is written as it is, in the stores' chunks: through dask it would cost a
    # graph per write for nothing to compute.
    in_memory = all(var.chunks is None for var in ds.variables.values())
    ds = _prepared(ds if in_memory else ds.drop_encoding().chunk(chunking))
    partial = path.parent / f".{path.name}{_PARTIAL}{uuid.uuid4().hex[:12]}"
    # A Dataset in memory is encoded into memory at once and its files written in one go: by
    # zarrwrite.encode_store, the files to_zarr would write at a tenth of its CPU (where they are
    # the same: own_files), else by to_zarr into a memory store (into zarr's file store, a thread
    # hop per document and chunk, an item's stores took 1.15-1.65x as long, and a delayed write's
    # compute imported dask.distributed to look for a client). Dask arrays are written chunk by
    # chunk to the files: memory follows the chunks, any scheduler (a cluster's) can.
    try:
        if in_memory:
            encoding = _encoding(ds, chunking)
            encoded = encode_store(ds, encoding) if own_files() else None
            if encoded is None:
                memory: dict = {}
                _to_zarr(ds, zarr.storage.MemoryStore(memory), encoding, compute=True)
                encoded = {key: buffer.to_bytes() for key, buffer in memory.items()}
            _write_files(encoded, partial)
        else:
            _to_zarr(ds, partial, _encoding(ds), compute=False).compute(scheduler=scheduler)
        if path.exists():
            retired = path.parent / f".{path.name}{_RETIRED}{uuid.uuid4().hex[:12]}"
            os.replace(path, retired)
            os.replace(partial, path)
            shutil.rmtree(retired)
        else:
            os.replace(partial, path)
    finally:
        if partial.exists():
            shutil.rmtree(partial, ignore_errors=True)
    return path


def _check_exists(path: Path) -> None:
    if not (path / "zarr.json").is_file():
        raise StoreError(f"{path}: no zarr store here (missing {path / 'zarr.json'}); run the stage that makes it")


def _checked(ds: xr.Dataset, path: Path, stage: str | None) -> xr.Dataset:
    """Return ``ds`` with its attributes decoded, checking that ``stage`` (if given) made it."""
    ds.attrs = decode_attrs(ds.attrs)
    for variable in ds.variables.values():
        variable.attrs = decode_attrs(variable.attrs)
    made_by = ds.attrs.get("surffin_stage")
    if stage is not None and made_by != stage:
        raise StoreError(f"{path}: expected a store made by stage {stage!r}, found one made by {made_by!r}")
    return ds


def open_store(path: str | os.PathLike, *, stage: str | None = None, chunks="auto") -> xr.Dataset:
    """Open a processed store lazily, checking that it is one.

    Parameters
    ----------
    path : path-like
        The store's folder.
    stage : str, optional
        When given, the store must have been written by this stage.
    chunks : optional
        Passed to :func:`xarray.open_zarr`; the default keeps the stored chunks.

    Raises
    ------
    StoreError
        If nothing readable is there, or it was made by another stage.
    """
    path = Path(path)
    _check_exists(path)
    try:
        ds = xr.open_zarr(path, consolidated=True, chunks={} if chunks == "auto" else chunks)
    except Exception as exc:  # zarr and xarray raise many types on damaged stores
        raise StoreError(f"{path}: cannot open as a zarr store: {exc}") from exc
    return _checked(ds, path, stage)


def load_store(path: str | os.PathLike, *, stage: str | None = None) -> xr.Dataset:
    """Load a processed store into memory, checking that it is one, as ``open_store(path, chunks=None).load()``.

    The store is read by :func:`surffin.io.zarrread.read_store`, several times faster than through
    zarr-python, where that reader reads as xarray does (:func:`own_files`); a store it declines is
    loaded through xarray. Either way the Dataset is the same (its ``.encoding`` aside, which
    surffin does not use), its arrays numpy arrays of its own.

    Parameters
    ----------
    path : path-like
        The store's folder.
    stage : str, optional
        When given, the store must have been written by this stage.

    Raises
    ------
    StoreError
        If nothing readable is there, or it was made by another stage.
    """
    path = Path(path)
    _check_exists(path)
    ds = read_store(path) if own_files() else None
    return open_store(path, stage=stage, chunks=None).load() if ds is None else _checked(ds, path, stage)


def _identity(path: Path) -> tuple | None:
    """Return what changes when a store is written anew: its ``zarr.json``'s device, inode, size, time (or None)."""
    try:
        stat = (path / "zarr.json").stat()
    except OSError:
        return None
    return stat.st_dev, stat.st_ino, stat.st_size, stat.st_mtime_ns


def _copy(ds: xr.Dataset) -> xr.Dataset:
    """Return a new Dataset on the same arrays, with its own attributes (nested values included)."""
    copied = ds.copy(deep=False)
    copied.attrs = copy.deepcopy(ds.attrs)
    for variable in copied.variables.values():
        variable.attrs = copy.deepcopy(variable.attrs)
    return copied


class StoreCache:
    """Stores loaded into memory, kept while their files are unchanged, so that a process reads each once.

    A store is known by its path and its ``zarr.json``'s identity (device, inode, size, modification
    time): :func:`write_store` renames a new folder onto the path, so a store written anew is read
    anew. The kept arrays are read-only: a caller that would change an array in place gets an error,
    not another caller's data changed. The least recently used stores leave first once the kept
    arrays exceed ``max_bytes``; a store larger than that is returned and not kept.

    Parameters
    ----------
    max_bytes : int
        The most bytes of arrays kept.
    """

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = max_bytes
        self._kept: OrderedDict[tuple, xr.Dataset] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, path: str | os.PathLike) -> xr.Dataset | None:
        """Return the store at ``path`` as :meth:`keep` loaded it, if kept and unchanged since; else None."""
        key = (Path(path).resolve(), _identity(Path(path)))
        with self._lock:
            ds = self._kept.get(key)
            if ds is None:
                return None
            self._kept.move_to_end(key)
        return _copy(ds)

    def keep(self, path: str | os.PathLike) -> xr.Dataset:
        """Load the store at ``path`` by :func:`load_store` and keep it.

        Returns
        -------
        Dataset
            The loaded store; kept only if its files did not change while it was loaded.
        """
        path = Path(path).resolve()
        identity = _identity(path)
        ds = load_store(path)
        for variable in ds.variables.values():
            if isinstance(variable.data, np.ndarray):
                variable.data.flags.writeable = False
        if identity is not None and identity == _identity(path) and ds.nbytes <= self.max_bytes:
            with self._lock:
                self._kept[(path, identity)] = ds
                while sum(kept.nbytes for kept in self._kept.values()) > self.max_bytes:
                    self._kept.popitem(last=False)
        return _copy(ds)
