"""surffin.io.zarrread reads the stores surffin writes exactly as xarray and zarr-python load them."""

import math
import warnings

import numpy as np
import pytest
import xarray as xr
import zarr

from surffin.errors import StoreError
from surffin.io.store import StoreCache, load_store, open_store, own_files, provenance, same_dataset, write_store
from surffin.io.zarrread import read_store, store_sizes


def typed(value):
    """A value's structure with every type spelled out (NaN comparable), to compare attributes exactly."""
    if isinstance(value, dict):
        return ("dict", [(key, typed(item)) for key, item in value.items()])
    if isinstance(value, list | tuple):
        return (type(value).__name__, [typed(item) for item in value])
    if isinstance(value, np.ndarray):
        return ("ndarray", str(value.dtype), typed(value.tolist()))
    if isinstance(value, float) and math.isnan(value):
        return ("float", "nan")
    return (type(value).__name__, value)


def assert_same(mine: xr.Dataset, reference: xr.Dataset) -> None:
    xr.testing.assert_identical(mine, reference)
    assert list(mine.variables) == list(reference.variables)
    assert list(mine.coords) == list(reference.coords)
    assert list(mine.data_vars) == list(reference.data_vars)
    assert typed(mine.attrs) == typed(reference.attrs)
    for name, variable in reference.variables.items():
        other = mine.variables[name]
        assert type(other) is type(variable) and other.dtype == variable.dtype, name
        assert typed(other.attrs) == typed(variable.attrs), name
        if variable.dtype.kind in "fiub":  # bit for bit, NaN payloads included
            assert other.values.tobytes() == variable.values.tobytes(), name
        else:
            assert other.values.tolist() == variable.values.tolist(), name
    assert list(mine.xindexes) == list(reference.xindexes)
    for name, index in reference.xindexes.items():
        assert type(mine.xindexes[name]) is type(index)
        assert mine.xindexes[name].coord_dtype == index.coord_dtype, name
        assert mine.indexes[name].dtype == reference.indexes[name].dtype, name


#: The tests of read_store against xarray, where they read the same Datasets (else load_store uses xarray).
same_reads = pytest.mark.skipif(not own_files(), reason="this xarray and zarr read otherwise than zarrread")


def assert_reads_as_xarray(path) -> None:
    """read_store against xarray straight, load_store against open_store's (attributes decoded)."""
    mine = read_store(path)
    assert mine is not None
    assert_same(mine, xr.open_zarr(path, consolidated=True, chunks=None).load())
    assert_same(load_store(path), open_store(path, chunks=None).load())


def every_kind(ny=7, nx=9, nview=3) -> xr.Dataset:
    rng = np.random.default_rng(0)
    shape = (nview, ny, nx)
    reflectance = rng.random(shape).astype("f4")
    reflectance[0, :2, :3] = np.nan
    dense = rng.random((ny, nx))
    dense[3:6, 0:4] = np.nan  # a whole chunk of NaN (with chunks 3 x 4): not written
    names = np.array(["a", "", "é", "日本語", "plain", "ß", "x y"], dtype=object)
    variables = {
        "reflectance": (("view", "y", "x"), reflectance, {"units": "1", "long_name": "reflectance"}),
        "dense": (("y", "x"), dense, {"window": [3, 5], "scale": 0.5}),
        "all_nan": (("view", "y", "x"), np.full(shape, np.nan, "f4")),
        "i1": (("y", "x"), rng.integers(-100, 100, (ny, nx)).astype("i1")),
        "i2": (("y", "x"), rng.integers(-9, 9, (ny, nx)).astype("i2"), {"flag_values": [0, 1, 2]}),
        "i4": (("y", "x"), rng.integers(-(2**30), 2**30, (ny, nx)).astype("i4")),
        "i8": (("y", "x"), rng.integers(-(2**62), 2**62, (ny, nx)).astype("i8")),
        "u1": (("y", "x"), rng.integers(0, 255, (ny, nx)).astype("u1")),
        "all_zero": (("y", "x"), np.zeros((ny, nx), "i2")),
        "mask": (("view", "y", "x"), rng.random(shape) > 0.5),
        "all_false": (("view", "y", "x"), np.zeros(shape, bool)),
        "names": (("y",), names),
        "scalar": ((), 2.5, {"note": "0-d"}),
        "count": ((), np.int64(7)),
        "word": ((), "é"),
    }
    coords = {
        "view": [f"v{i:02d}" for i in range(nview)],
        "y": np.arange(10, 10 + ny),
        "x": np.arange(nx),
        "label": ("x", np.array([f"c{i}" for i in range(nx)], dtype=object)),  # a non-dimension coordinate
        "weight": ("view", np.linspace(0.5, 1.0, nview)),
    }
    attrs = provenance("test", {"window": 15, "nested": {"a": [1, 2], "b": None, "c": True}}, {"in.npz": {"size": 3}})
    ds = xr.Dataset(variables, coords=coords, attrs=attrs | {"flags": [True, False], "names": ["a", "b"]})
    ds["reflectance"].attrs["history"] = {"steps": ["a", "b"], "ok": False}
    return ds


@same_reads
@pytest.mark.parametrize("chunks", [None, {"y": 3, "x": 4}], ids=["one chunk", "edge chunks"])
def test_every_kind_of_variable_reads_as_xarray_loads_it(tmp_path, chunks):
    path = write_store(every_kind(), tmp_path / "s.zarr", chunks=chunks)
    # zarr writes no chunk that holds only the fill value: the reader fills those in
    assert not (path / "all_nan" / "c").exists() and not (path / "all_false" / "c").exists()
    if chunks is not None:
        assert not (path / "dense" / "c" / "1" / "0").exists() and (path / "dense" / "c" / "2" / "2").is_file()
        assert (path / "names" / "c" / "2").is_file()  # strings over three chunks, the last one partial
    assert_reads_as_xarray(path)
    ds = read_store(path)
    assert all(variable.values.flags.writeable for name, variable in ds.variables.items() if name not in ds.indexes)
    assert ds["label"].dims == ("x",) and "label" in ds.coords and "coordinates" not in ds["reflectance"].attrs
    assert store_sizes(path) == dict(xr.open_zarr(path, chunks=None).sizes)


@same_reads
def test_zstd_on_floats_reads_as_xarray_loads_it(tmp_path):
    # what to_zarr writes by default (write_store leaves floats uncompressed): the same codec as integers'
    path = tmp_path / "s.zarr"
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Consolidated metadata", category=UserWarning)
        every_kind().drop_vars(["names", "label", "view", "word"]).to_zarr(path, zarr_format=3, consolidated=True)
    assert_reads_as_xarray(path)


def plain_store(path, encoding=None, attrs=None, **to_zarr):
    ds = xr.Dataset(
        {"v": (("y", "x"), np.arange(12.0).reshape(3, 4), attrs or {}), "n": (("y",), np.arange(3))},
        coords={"y": np.arange(3), "x": np.arange(4)},
        attrs=provenance("test"),
    )
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Consolidated metadata", category=UserWarning)
        ds.to_zarr(path, encoding={"v": encoding or {}}, **({"zarr_format": 3, "consolidated": True} | to_zarr))
    return path


@pytest.mark.parametrize(
    "store",
    [
        {"encoding": {"compressors": [zarr.codecs.GzipCodec()]}},
        {"encoding": {"compressors": None, "serializer": zarr.codecs.BytesCodec(endian="big")}},
        {"encoding": {"compressors": None, "chunks": (1, 2), "shards": (3, 4)}},
        {"attrs": {"units": "days since 2000-01-01"}},  # xarray decodes it to dates
        {"attrs": {"scale_factor": 2.0}},
        {"attrs": {"_FillValue": 1.0}},  # xarray masks the ones
    ],
    ids=["gzip", "big endian", "sharding", "times", "scaled", "masked"],
)
def test_anything_else_is_declined_and_loaded_through_xarray(tmp_path, store):
    path = plain_store(tmp_path / "s.zarr", **store)
    assert read_store(path) is None
    xr.testing.assert_identical(load_store(path), open_store(path, chunks=None).load())


def test_load_store_fails_as_open_store_does(tmp_path):
    unconsolidated = plain_store(tmp_path / "u.zarr", consolidated=False)
    assert read_store(unconsolidated) is None
    with pytest.raises(StoreError, match="cannot open as a zarr store"):
        load_store(unconsolidated)
    version_2 = plain_store(tmp_path / "v2.zarr", zarr_format=2)
    for missing in (tmp_path / "missing.zarr", version_2):
        assert read_store(missing) is None and store_sizes(missing) is None
        with pytest.raises(StoreError, match="no zarr store here"):
            load_store(missing)
    path = write_store(every_kind(), tmp_path / "s.zarr")
    with pytest.raises(StoreError, match="expected a store made by stage 'aoi'"):
        load_store(path, stage="aoi")
    assert load_store(path, stage="test").attrs["surffin_parameters"]["nested"] == {"a": [1, 2], "b": None, "c": True}


def test_a_damaged_chunk_fails_as_through_xarray(tmp_path):
    path = write_store(every_kind(), tmp_path / "s.zarr")
    chunk = path / "dense" / "c" / "0" / "0"
    chunk.write_bytes(chunk.read_bytes()[:-8])
    assert read_store(path) is None
    with pytest.raises(Exception) as through_xarray:
        open_store(path, chunks=None).load()
    with pytest.raises(through_xarray.type):
        load_store(path)


def test_store_cache_keeps_what_load_store_reads(tmp_path):
    path = write_store(every_kind(), tmp_path / "s.zarr", chunks={"y": 3, "x": 4})
    kept = StoreCache(max_bytes=10**7).keep(path)
    assert_same(kept, open_store(path, chunks=None).load())
    assert not kept["reflectance"].values.flags.writeable


@same_reads
@pytest.mark.slow
def test_every_store_of_a_run_reads_as_xarray_loads_it(tiny_run):
    stores = sorted(path for path in (tiny_run / "processed").rglob("*.zarr") if not path.name.startswith("."))
    assert len(stores) > 10
    for path in stores:
        assert_reads_as_xarray(path)


def test_same_dataset_tells_what_identical_does_not():
    ds = xr.Dataset({"a": ("x", np.arange(3.0), {"w": 1}), "b": ("x", np.arange(3))}, coords={"x": [1, 2, 3]})
    assert same_dataset(ds, ds.copy(deep=True))
    others = {
        "order": ds[["b", "a"]],
        "dtype": ds.assign(b=ds["b"].astype("int32")),
        "attribute type": ds.assign(a=ds["a"].assign_attrs(w=1.0)),
        "NaN payload": ds.assign(a=("x", np.array([1.0, 2.0, np.nan]))).copy(deep=True),
    }
    nan = others["NaN payload"].copy(deep=True)
    nan["a"].values.view(np.uint64)[2] ^= 1  # another NaN, which Dataset.identical takes as equal
    assert others["order"].identical(ds) and nan.identical(others["NaN payload"])
    assert not any(same_dataset(other, ds) for key, other in others.items() if key != "NaN payload")
    assert not same_dataset(nan, others["NaN payload"])
