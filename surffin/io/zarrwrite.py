"""The files of a store, encoded from a Dataset in memory as ``Dataset.to_zarr`` writes them, at a fraction of its cost.

``to_zarr`` into a zarr v3 store costs ~30 ms of CPU a store, nearly all of it zarr-python's work per
array (metadata objects, an event-loop hop per call, the codec pipeline), against ~3 ms for the
bytes of the files; a run writes ~250 stores (``python benchmarks/bench_store.py``).
:func:`encode_store` makes the same files, byte for byte, for what surffin's stores hold: numeric
and boolean arrays in memory, variable-length strings, the floats uncompressed and the rest
compressed with zstd, regular chunks, consolidated metadata, xarray's ``_FillValue`` and
``coordinates`` attributes. For anything else it returns None and the caller writes with
``to_zarr``. Those are the files xarray 2026.9 and zarr 3.1.6 write; other versions may write
otherwise (xarray 2026.1 with zarr 3.1.2: booleans as int8), so :func:`surffin.io.store.write_store`
uses this writer only where it writes :func:`probe` as ``to_zarr`` does.
"""

from __future__ import annotations

import base64
import itertools
import json
import math
import struct
import unicodedata
from collections.abc import Mapping

import numpy as np
import xarray as xr
from numcodecs import VLenUTF8, Zstd

__all__ = ["encode_store", "probe"]

_ZSTD = {"name": "zstd", "configuration": {"level": 0, "checksum": False}}
_LITTLE = {"name": "bytes", "configuration": {"endian": "little"}}
#: zarr's chunks for an array given none (e.g. an index coordinate): the whole array up to this size.
_WHOLE_BYTES = 128 * 1024
_NUMERIC = "fiub"
_ZSTD_CODEC = Zstd(level=0, checksum=False)
_VLEN_UTF8 = VLenUTF8()


def _attribute(value):
    """Return an attribute value as xarray hands it to zarr: numpy arrays as lists, numpy scalars as Python's."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value


def _strings(data: np.ndarray) -> bool:
    if data.dtype.kind == "T":
        return True
    return data.dtype == object and all(isinstance(value, str) for value in data.reshape(-1))


def _kind(data: np.ndarray) -> tuple[str, object, object, list] | None:
    """Return an array's zarr data type, fill value (as stored and in JSON) and codecs; None if not written here.

    The codecs are those ``to_zarr`` gives without compressors for floats, and zarr's default
    compressor (zstd) for the rest: the stores' encoding.
    """
    if _strings(data):
        return "string", "", "", [{"name": "vlen-utf8", "configuration": {}}, _ZSTD]
    if data.dtype.kind not in _NUMERIC or data.dtype.byteorder == ">" or data.dtype.kind == "f" and data.itemsize < 4:
        return None
    if data.dtype.kind == "f":
        return data.dtype.name, np.nan, "NaN", [_LITTLE]
    fill = False if data.dtype.kind == "b" else 0
    return data.dtype.name, fill, fill, [{"name": "bytes"} if data.itemsize == 1 else _LITTLE, _ZSTD]


def _empty(chunk: np.ndarray, fill) -> bool:
    """Tell whether a chunk holds only the fill value (zarr writes no file for it)."""
    if chunk.dtype.kind == "f":
        return bool(np.isnan(chunk).all())
    return bool((chunk == fill).all())


def _chunk_bytes(chunk: np.ndarray) -> bytes:
    if chunk.dtype.kind in "OT":
        return _ZSTD_CODEC.encode(_VLEN_UTF8.encode(chunk.astype(object)))
    raw = chunk.astype(chunk.dtype.newbyteorder("<"), copy=False).tobytes()
    return raw if chunk.dtype.kind == "f" else _ZSTD_CODEC.encode(raw)


def _chunks(name: str, data: np.ndarray, shape: tuple[int, ...], fill) -> dict[str, bytes]:
    """Return the chunk files of an array: edge chunks padded with the fill value, chunks of fill value left out."""
    files = {}
    counts = [math.ceil(size / step) for size, step in zip(data.shape, shape)]
    for index in itertools.product(*(range(count) for count in counts)):
        part = data[tuple(slice(i * step, (i + 1) * step) for i, step in zip(index, shape))] if data.ndim else data
        if part.shape != shape:
            padded = np.full(shape, fill, dtype=data.dtype)
            padded[tuple(slice(0, size) for size in part.shape)] = part
            part = padded
        if not _empty(part, fill):
            files["/".join((name, "c", *map(str, index)))] = _chunk_bytes(np.ascontiguousarray(part))
    return files


def _coordinates(ds: xr.Dataset) -> tuple[dict[str, str], str | None]:
    """Return xarray's ``coordinates`` attributes: per variable, and the dataset's for those no variable names."""
    others = [name for name in ds.coords if name not in ds.dims]
    per_variable = {}
    for name, variable in ds.variables.items():
        named = sorted(
            str(coord)
            for coord in others
            if name not in others and name not in variable.dims and set(ds.variables[coord].dims) <= set(variable.dims)
        )
        if named:
            per_variable[name] = " ".join(named)
    written = {coord for text in per_variable.values() for coord in text.split()}
    orphans = sorted(str(coord) for coord in others if coord not in written)
    return per_variable, " ".join(orphans) or None


def encode_store(ds: xr.Dataset, encoding: Mapping[str, Mapping]) -> dict[str, bytes] | None:
    """Return the files of ``ds`` as a consolidated zarr v3 store (relative path -> bytes), as ``to_zarr`` writes them.

    Parameters
    ----------
    ds : Dataset
        In memory, its encoding dropped, its strings as object arrays and its attributes JSON-ready, as
        :func:`surffin.io.store.write_store` hands it to ``to_zarr``.
    encoding : mapping of str to mapping
        The ``to_zarr`` encoding of the variables: ``chunks`` (absent: whole), and ``compressors``
        None for floats, absent for the rest.

    Returns
    -------
    dict or None
        None when ``ds`` holds or ``encoding`` asks what this writer does not write (a dtype, a
        variable or attribute named ``coordinates`` or ``_FillValue``, a large array given no chunks,
        names equal but for case, another compressor or encoding key): write it with ``to_zarr``.
    """
    names = list(ds.variables)
    if any(not isinstance(name, str) or "/" in name or " " in name for name in names):
        return None
    folded = [unicodedata.normalize("NFKC", name).casefold() for name in names]
    if len(set(folded)) < len(names):  # zarr's order of the consolidated documents: by these keys
        return None
    per_variable, orphans = _coordinates(ds)
    root_attrs = {key: _attribute(value) for key, value in ds.attrs.items()}
    if orphans is not None:
        if "coordinates" in root_attrs:
            return None
        root_attrs["coordinates"] = orphans
    files, documents = {}, {}
    for name, variable in ds.variables.items():
        data = variable.values
        kind = _kind(data)
        wanted = dict(encoding.get(name, {}))
        chunked = "chunks" in wanted
        shape = tuple(wanted.pop("chunks", data.shape))
        # the stores' encoding: floats uncompressed, the rest with zarr's default compressor
        if kind is None or wanted != ({"compressors": None} if data.dtype.kind == "f" else {}):
            return None
        if len(shape) != data.ndim or not chunked and data.nbytes > _WHOLE_BYTES:
            return None
        if "_FillValue" in variable.attrs or "coordinates" in variable.attrs:
            return None
        data_type, fill, json_fill, codecs = kind
        attrs = {key: _attribute(value) for key, value in variable.attrs.items()}
        if name in per_variable:
            attrs["coordinates"] = per_variable[name]
        if data_type.startswith("float"):
            attrs["_FillValue"] = base64.standard_b64encode(struct.pack("<d", math.nan)).decode()
        documents[name] = {
            "shape": list(data.shape),
            "data_type": data_type,
            "chunk_grid": {"name": "regular", "configuration": {"chunk_shape": list(shape)}},
            "chunk_key_encoding": {"name": "default", "configuration": {"separator": "/"}},
            "fill_value": json_fill,
            "codecs": codecs,
            "attributes": attrs,
            "dimension_names": list(variable.dims),
            "zarr_format": 3,
            "node_type": "array",
            "storage_transformers": [],
        }
        if not variable.dims:  # zarr leaves out the names of no dimensions
            del documents[name]["dimension_names"]
        files |= _chunks(name, data, shape, fill)
    for name, document in documents.items():
        files[f"{name}/zarr.json"] = _json(document)
    ordered = [name for _, name in sorted(zip(folded, names))]
    root = {
        "attributes": root_attrs,
        "zarr_format": 3,
        "consolidated_metadata": {
            "kind": "inline",
            "must_understand": False,
            "metadata": {name: documents[name] for name in ordered},
        },
        "node_type": "group",
    }
    files["zarr.json"] = _json(root)
    return files


def _json(document: dict) -> bytes:
    return json.dumps(document, indent=2, allow_nan=True).encode()


def probe() -> xr.Dataset:
    """Return a small Dataset holding every kind of variable, value and attribute :func:`encode_store` writes.

    Numeric and boolean arrays of each dtype (with NaN, a chunk of NaN and arrays of fill values only),
    strings (empty, non-ASCII, a 0-d one), 0-d numbers, an index, a non-dimension coordinate and
    one no variable names, attributes of numpy scalars and arrays; written with chunks of 3 x 4 it
    has edge chunks. Its strings are object arrays and its attributes JSON-ready, as ``encode_store``
    takes them.
    """
    rng = np.random.default_rng(3)
    shape = (2, 7, 9)
    noisy = rng.normal(size=shape).astype(np.float32)
    noisy[0, :3, :4] = np.nan
    return xr.Dataset(
        {
            "reflectance": (("view", "y", "x"), noisy, {"units": "1", "window": np.int64(15), "nan": math.nan}),
            "fit": (("y", "x"), rng.normal(size=shape[1:]), {"scale": np.float32(0.5), "edges": np.arange(3.0)}),
            "empty": (("y", "x"), np.full(shape[1:], np.nan)),
            "valid": (("view", "y", "x"), rng.random(shape) > 0.3),
            "never": (("y", "x"), np.zeros(shape[1:], dtype=bool)),
            "status": (("y", "x"), rng.integers(-3, 3, shape[1:]).astype(np.int8)),
            "count": (("y", "x"), rng.integers(0, 200, shape[1:]).astype(np.uint8)),
            "label": (("y", "x"), rng.integers(-1, 4, shape[1:]).astype(np.int16)),
            "index": (("y", "x"), rng.integers(0, 1 << 20, shape[1:]).astype(np.int32)),
            "big": (("y", "x"), rng.integers(0, 1 << 40, shape[1:])),
            "scalar": ((), 2.5),
            "flag": ((), np.int64(3)),
            "note": ((), np.array("no views", dtype=object)),
            "names": ("view", np.array(["é-side", ""], dtype=object)),
        },
        coords={
            "view": np.array(["v00", "v01"], dtype=object),
            "y": np.arange(10, 17),
            "x": np.arange(20, 29),
            "pose": ("view", np.array([1.0, np.nan])),
            "lonely": ("axis", np.array(["a", "b", "c"], dtype=object)),
        },
        attrs={"ratio": 0.25, "name": "S1-01", "sizes": [1, 2]},
    )
