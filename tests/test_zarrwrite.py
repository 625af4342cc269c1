"""surffin.io.zarrwrite against xarray's and zarr-python's own writer: the same files, byte for byte."""

import json
import warnings

import numpy as np
import pytest
import xarray as xr
import zarr

from surffin.io.store import encode_attrs, open_store, write_store
from surffin.io.zarrwrite import encode_store


def reference(ds: xr.Dataset, chunking: dict) -> dict[str, bytes]:
    """The files ``to_zarr`` writes: floats uncompressed, the rest with zarr's default, chunks per ``chunking``."""
    encoding = {}
    for name, variable in ds.variables.items():
        encoding[name] = {"compressors": None} if variable.dtype.kind == "f" else {}
        if name not in ds.indexes:
            sizes = [min(chunking.get(dim, size), size) for dim, size in variable.sizes.items()]
            encoding[name]["chunks"] = tuple(sizes)
    memory = {}
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Consolidated metadata", category=UserWarning)
        ds.to_zarr(zarr.storage.MemoryStore(memory), mode="w-", zarr_format=3, consolidated=True, encoding=encoding)
    return {key: buffer.to_bytes() for key, buffer in memory.items()}


def prepared(ds: xr.Dataset) -> xr.Dataset:
    """``ds`` as write_store hands it to a writer: strings as objects, attributes encoded."""
    strings = {name: var.astype(object) for name, var in ds.variables.items() if var.dtype.kind in "UT"}
    ds = ds.assign_coords({k: v for k, v in strings.items() if k in ds.coords})
    ds = ds.assign({k: v for k, v in strings.items() if k not in ds.coords}).copy(deep=True)
    for variable in ds.variables.values():
        variable.attrs = encode_attrs(variable.attrs)
    ds.attrs = encode_attrs(ds.attrs)
    return ds


def every_kind() -> xr.Dataset:
    """A Dataset with every kind of variable, value and attribute surffin's stores hold."""
    rng = np.random.default_rng(3)
    shape = (2, 7, 9)
    noisy = rng.normal(size=shape).astype(np.float32)
    noisy[0, :3, :4] = np.nan  # a whole chunk of NaN: not written
    return xr.Dataset(
        {
            "reflectance": (("view", "y", "x"), noisy, {"units": "1", "window": np.int64(15)}),
            "fit": (("y", "x"), rng.normal(size=shape[1:]), {"scale": np.float32(0.5), "edges": np.arange(3.0)}),
            "empty": (("y", "x"), np.full(shape[1:], np.nan)),
            "valid": (("view", "y", "x"), rng.random(shape) > 0.3),
            "never": (("y", "x"), np.zeros(shape[1:], dtype=bool)),
            "status": (("y", "x"), rng.integers(-3, 3, shape[1:]).astype(np.int8)),
            "count": (("y", "x"), rng.integers(0, 200, shape[1:]).astype(np.uint8)),
            "label": (("y", "x"), rng.integers(-1, 4, shape[1:]).astype(np.int16)),
            "index": (("y", "x"), rng.integers(0, 1 << 20, shape[1:]).astype(np.int32)),
            "big": (("y", "x"), rng.integers(0, 1 << 40, shape[1:])),
            "scalar": ((), 2.5, {"nan": np.nan}),
            "flag": ((), np.int64(3)),
            "note": ((), np.array("no views", dtype=object)),
            "names": ("view", np.array(["é-side", ""], dtype=object)),
        },
        coords={
            "view": ["v00", "v01"],
            "y": np.arange(10, 17),
            "x": np.arange(20, 29),
            "pose": ("view", np.array([1.0, np.nan])),
            "lonely": ("axis", np.array(["a", "b", "c"])),
        },
        attrs={"nested": {"a": [1, 2], "b": None}, "flag": True, "ratio": 0.25, "name": "S1-01"},
    )


@pytest.mark.parametrize("chunking", [{}, {"y": 3, "x": 4}, {"view": 1, "y": 7, "x": 5}])
def test_files_as_to_zarr_writes_them(chunking):
    ds = prepared(every_kind())
    ours = encode_store(ds, chunking)
    assert ours == reference(ds, chunking)
    # not vacuous: attributes xarray adds, a chunk of NaN and a variable of fill values left out
    assert b'"coordinates": "pose"' in ours["reflectance/zarr.json"] and b'"coordinates": "lonely"' in ours["zarr.json"]
    assert b'"_FillValue"' in ours["fit/zarr.json"] and not any(key.startswith(("empty/c", "never/c")) for key in ours)


def test_strings_as_numpy_strings():
    """Stores read back hold numpy's variable-width strings; a stage may pass them on."""
    ds = prepared(every_kind())
    ds = ds.assign(names=ds["names"].astype(np.dtypes.StringDType()))
    assert encode_store(ds, {}) == reference(ds, {})


@pytest.mark.parametrize(
    "change",
    [
        lambda ds: ds.assign(half=(("y", "x"), np.ones((7, 9), np.float16))),
        lambda ds: ds.assign(big_endian=(("y", "x"), np.ones((7, 9), ">f8"))),
        lambda ds: ds.assign(when=("view", np.array(["2026-01-01", "2026-01-02"], "datetime64[ns]"))),
        lambda ds: ds.assign(mixed=("view", np.array(["a", 1], dtype=object))),
        lambda ds: ds.assign(fixed=("view", np.array(["a", "bc"]))),
        lambda ds: ds.assign(fill=(("y", "x"), np.ones((7, 9)), {"_FillValue": -1.0})),
        lambda ds: ds.assign_coords(long=np.arange(20_000)),
        lambda ds: ds.assign(Fit=ds["fit"]),
    ],
    ids=[
        "float16",
        "big-endian",
        "datetime",
        "mixed-objects",
        "fixed-width-strings",
        "own-fill-value",
        "large-index",
        "names-equal-but-for-case",
    ],
)
def test_anything_else_is_left_to_to_zarr(change):
    assert encode_store(change(prepared(every_kind())), {}) is None


def test_store_written_with_a_fallback_variable_reads_back(tmp_path):
    ds = every_kind().assign(half=(("y", "x"), np.ones((7, 9), np.float16)))
    path = write_store(ds, tmp_path / "s.zarr", chunks={"y": 3, "x": 4})
    back = open_store(path).load()
    # the index of fixed-width strings written as variable-length ones, which zarr v3 specifies
    assert json.loads((path / "view" / "zarr.json").read_text())["data_type"] == "string"
    assert back["half"].dtype == np.float16 and back.attrs["nested"] == {"a": [1, 2], "b": None}
    np.testing.assert_array_equal(back["reflectance"].values, ds["reflectance"].values)


@pytest.mark.slow
def test_every_store_of_a_run(tiny_run):
    """The stores of a whole run, written by encode_store, are the files to_zarr writes of them read back."""
    stores = sorted((tiny_run / "processed").rglob("*.zarr"))
    assert len(stores) > 20
    for store in stores:
        # all but the timestamp snakemake leaves in an output folder
        files = {str(p.relative_to(store)): p.read_bytes() for p in store.rglob("*") if p.is_file()}
        files.pop(".snakemake_timestamp", None)
        opened = open_store(store)
        chunking = {}
        for variable in opened.data_vars.values():
            chunking |= dict(zip(variable.dims, variable.encoding["chunks"]))
        assert reference(prepared(opened.load()), chunking) == files, store
