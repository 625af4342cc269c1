"""Read a store surffin wrote straight from its files into memory, as xarray would load it.

xarray loads a zarr store through zarr-python, whose per-array machinery (an event-loop thread hop,
metadata objects and a codec pipeline per array) costs several times the reading of the files for
stores as small as an item's. The stores :func:`surffin.io.store.write_store` writes use a small
part of zarr v3: a group with inline consolidated metadata and no subgroups; arrays on a regular
chunk grid with ``/``-separated default chunk keys, typed float32, float64, int8 to int64, uint8,
bool or string, encoded by the codecs bytes (little endian), vlen-utf8 and zstd; chunks equal to
the fill value not written. :func:`read_store` reads that part by hand (numcodecs decodes the
chunks) and builds the Dataset as xarray's zarr backend and CF decoding do: the variables in the
consolidated metadata's order, split into coordinates and data variables by their dimensions and
``coordinates`` attributes, default indexes on the dimension coordinates, ``_FillValue`` and
``coordinates`` taken out of the attributes, strings as numpy ``StringDType``. Anything outside
that part (another codec or data type, big endian, sharding, a subgroup, an attribute CF decoding
would act on, no consolidated metadata) it declines, and the caller reads the store with xarray.
"""

from __future__ import annotations

import base64
import itertools
import json
import math
import os
import struct
from pathlib import Path

import numpy as np
import xarray as xr
from numcodecs import VLenUTF8, Zstd

__all__ = ["read_store", "store_sizes"]

_DTYPES = {
    name: np.dtype(name) for name in ("float32", "float64", "int8", "int16", "int32", "int64", "uint8", "bool")
} | {"string": np.dtypes.StringDType()}
_ARRAY_KEYS = {
    "zarr_format",
    "node_type",
    "shape",
    "data_type",
    "chunk_grid",
    "chunk_key_encoding",
    "fill_value",
    "codecs",
    "attributes",
    "dimension_names",
    "storage_transformers",
}
#: Attributes xarray's CF decoding acts on (masking, scaling, times, booleans, encoded strings).
_CF_ACTED_ON = {"missing_value", "scale_factor", "add_offset", "_Unsigned", "dtype", "calendar", "_Encoding"}
_SPECIAL_FLOATS = {"NaN": np.nan, "Infinity": np.inf, "-Infinity": -np.inf}
_ZSTD = Zstd()
_VLEN_UTF8 = VLenUTF8()


class _Unsupported(Exception):
    """The store uses something outside the part of zarr v3 this module reads."""


def _require(condition: bool) -> None:
    if not condition:
        raise _Unsupported


def _fill_value(value, dtype: np.dtype):
    """Return the array's fill value as a scalar of ``dtype``."""
    if dtype.kind == "T":
        _require(isinstance(value, str))
        return value
    _require(not isinstance(value, bool) or dtype.kind == "b")
    if dtype.kind == "f" and isinstance(value, str):
        _require(value in _SPECIAL_FLOATS)
        value = _SPECIAL_FLOATS[value]
    _require(isinstance(value, bool) if dtype.kind == "b" else isinstance(value, int | float))
    return np.array(value, dtype=dtype)[()]


def _chunk_reader(codecs, dtype: np.dtype):
    """Return a function that fills a chunk (a C-contiguous array) from its file, reading it once."""
    _require(isinstance(codecs, list) and len(codecs) in (1, 2))
    serializer, *compressors = codecs
    for codec in compressors:
        _require(codec.get("name") == "zstd" and set(codec.get("configuration", {})) <= {"level", "checksum"})
    if dtype.kind == "T":
        _require(serializer.get("name") == "vlen-utf8" and not serializer.get("configuration"))
    else:
        endian = serializer.get("configuration", {}).get("endian")
        _require(serializer.get("name") == "bytes" and (endian == "little" or endian is None and dtype.itemsize == 1))

    def read(file: Path, chunk: np.ndarray) -> None:
        flat = chunk.reshape(-1)
        if dtype.kind == "T":
            raw = file.read_bytes()
            strings = _VLEN_UTF8.decode(_ZSTD.decode(raw) if compressors else raw)
            _require(strings.size == flat.size)
            flat[:] = strings
        elif compressors:
            values = np.frombuffer(_ZSTD.decode(file.read_bytes()), dtype=dtype)
            _require(values.size == flat.size)
            flat[:] = values
        else:
            with open(file, "rb") as stream:
                _require(stream.readinto(memoryview(flat).cast("B")) == flat.nbytes and not stream.read(1))

    return read


def _read_array(folder: Path, meta: dict) -> np.ndarray:
    """Read an array's chunks into one new array; a chunk without a file holds the fill value."""
    _require(set(meta) <= _ARRAY_KEYS and meta.get("node_type") == "array" and meta.get("zarr_format") == 3)
    _require(not meta.get("storage_transformers"))
    dtype = _DTYPES[meta["data_type"]]
    shape = tuple(meta["shape"])
    grid, keys = meta["chunk_grid"], meta["chunk_key_encoding"]
    _require(grid.get("name") == "regular" and keys.get("name") == "default")
    _require(keys.get("configuration", {}).get("separator", "/") == "/")
    chunks = tuple(grid["configuration"]["chunk_shape"])
    _require(len(chunks) == len(shape) and all(size > 0 for size in chunks))
    fill = _fill_value(meta["fill_value"], dtype)
    read = _chunk_reader(meta["codecs"], dtype)
    # Strings are gathered as Python objects and turned into StringDType once. An array in one chunk
    # is read straight into its place; the chunks of another through a buffer, cut at the edges.
    out = np.empty(shape, dtype=object if dtype.kind == "T" else dtype)
    whole = chunks == shape
    buffer = out if whole else np.empty(chunks, dtype=out.dtype)
    counts = [range(math.ceil(size / chunk)) for size, chunk in zip(shape, chunks)]
    for index in itertools.product(*counts):
        region = tuple(slice(i * chunk, min((i + 1) * chunk, size)) for i, chunk, size in zip(index, chunks, shape))
        try:
            read(folder.joinpath("c", *map(str, index)), buffer)
        except FileNotFoundError:
            out[region] = fill
            continue
        if not whole:
            out[region] = buffer[tuple(slice(0, r.stop - r.start) for r in region)]
    return out.astype(dtype) if dtype.kind == "T" else out


def _variable_attrs(meta: dict, dtype: np.dtype) -> dict:
    """Return an array's attributes as xarray's CF decoding leaves them (``coordinates`` still in)."""
    attrs = dict(meta.get("attributes", {}))
    _require(not attrs.keys() & _CF_ACTED_ON)
    units, coordinates = attrs.get("units"), attrs.get("coordinates", "")
    _require(not (isinstance(units, str) and "since" in units) and isinstance(coordinates, str))
    if "_FillValue" in attrs:
        # xarray writes a float's fill value as a base64 little-endian double; NaN masks nothing, any other value would.
        fill = attrs.pop("_FillValue")
        _require(dtype.kind == "f" and isinstance(fill, str))
        _require(math.isnan(struct.unpack("<d", base64.standard_b64decode(fill))[0]))
    return attrs


def _dataset(variables: dict[str, xr.Variable], attrs: dict) -> xr.Dataset:
    """Assemble the Dataset xarray's store backend makes of these decoded variables."""
    coord_names = set()
    for variable in variables.values():
        names = variable.attrs.pop("coordinates", None)
        if names is not None:
            coord_names.update(name for name in names.split() if name in variables)
    if isinstance(attrs.get("coordinates"), str):
        coord_names.update(attrs.pop("coordinates").split())
    coords = {name: var for name, var in variables.items() if name in coord_names or var.dims == (name,)}
    data_vars = {name: var for name, var in variables.items() if name not in coords}
    # xarray makes the Dataset without indexes, then assigns the dimension coordinates with their
    # default indexes; making them at once gives the same Dataset in half the time.
    return xr.Dataset(data_vars, coords=xr.Coordinates(coords), attrs=attrs)


def _dims(meta: dict) -> tuple:
    """Return an array's dimension names (none stored: none, as a 0-d array's)."""
    dims = meta.get("dimension_names") or ()
    _require(isinstance(dims, list | tuple))
    return tuple(dims)


def _group(root: Path) -> dict:
    """Return the root document of the store at ``root``, its consolidated array documents checked."""
    try:
        group = json.loads((root / "zarr.json").read_bytes())
    except (OSError, ValueError) as exc:
        raise _Unsupported from exc
    _require(isinstance(group, dict) and group.get("zarr_format") == 3 and group.get("node_type") == "group")
    consolidated = group.get("consolidated_metadata") or {}
    _require(consolidated.get("kind") == "inline" and isinstance(consolidated.get("metadata"), dict))
    members = consolidated["metadata"]
    for name, meta in members.items():
        _require("/" not in name and isinstance(meta, dict) and meta.get("data_type") in _DTYPES)
        dims = _dims(meta)
        _require(all(isinstance(dim, str) for dim in dims) and len(dims) == len(meta.get("shape", ())))
    return group


def store_sizes(path: str | os.PathLike) -> dict[str, int] | None:
    """Return the sizes of a store's dimensions, read from its metadata alone.

    Parameters
    ----------
    path : path-like
        The store's folder.

    Returns
    -------
    dict of str to int or None
        Each dimension's size; None if :func:`read_store` would not read the store.
    """
    try:
        group = _group(Path(path))
    except _Unsupported:
        return None
    members = group["consolidated_metadata"]["metadata"].values()
    return {dim: size for meta in members for dim, size in zip(_dims(meta), meta["shape"])}


def read_store(path: str | os.PathLike) -> xr.Dataset | None:
    """Load a store :func:`~surffin.io.store.write_store` wrote into memory, without zarr-python.

    Parameters
    ----------
    path : path-like
        The store's folder.

    Returns
    -------
    Dataset or None
        The store as ``xr.open_zarr(path, consolidated=True, chunks=None).load()`` gives it: the same
        variables in the same order, coordinates, indexes, dtypes, values and attributes, its arrays
        numpy arrays of its own (writeable); its ``.encoding`` and its variables' are left empty.
        None if there is no store at ``path`` or it uses anything this module does not read; then
        read it with xarray.
    """
    root = Path(path)
    try:
        group = _group(root)
        variables = {}
        for name, meta in group["consolidated_metadata"]["metadata"].items():
            attrs = _variable_attrs(meta, _DTYPES[meta["data_type"]])
            variables[name] = xr.Variable(_dims(meta), _read_array(root / name, meta), attrs)
        attrs = {key: value for key, value in group.get("attributes", {}).items() if not key.lower().startswith("_nc")}
        return _dataset(variables, attrs)
    except (_Unsupported, KeyError, TypeError, AttributeError, ValueError):  # damaged too: xarray says how
        return None
