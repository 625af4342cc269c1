"""surffin.io.zarrwrite against xarray's and zarr-python's own writer: the same files, byte for byte."""

import json
import warnings

import numpy as np
import pytest
import xarray as xr
import zarr
from packaging.version import Version

import surffin.io.store
from surffin.io.store import encode_attrs, load_store, open_store, own_files, write_store
from surffin.io.zarrwrite import encode_store, probe


def stores_encoding(ds: xr.Dataset, chunking: dict) -> dict[str, dict]:
    """The stores' encoding: floats uncompressed, the rest with zarr's default, chunks per ``chunking``."""
    encoding = {}
    for name, variable in ds.variables.items():
        encoding[name] = {"compressors": None} if variable.dtype.kind == "f" else {}
        if name not in ds.indexes:
            sizes = [min(chunking.get(dim, size), size) for dim, size in variable.sizes.items()]
            encoding[name]["chunks"] = tuple(sizes)
    return encoding


def reference(ds: xr.Dataset, encoding: dict) -> dict[str, bytes]:
    """The files ``to_zarr`` writes of ``ds`` with ``encoding``."""
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
    """The writer's probe with attributes write_store stores as JSON text, and a fixed-width index."""
    ds = probe().assign_attrs(nested={"a": [1, 2], "b": None}, flag=True)
    return ds.assign_coords(view=["v00", "v01"], lonely=("axis", np.array(["a", "b", "c"])))


#: The tests comparing the two writers' files, where they write the same files (else write_store uses to_zarr).
same_files = pytest.mark.skipif(not own_files(), reason="this xarray and zarr write other files than zarrwrite")


@same_files
@pytest.mark.parametrize("chunking", [{}, {"y": 3, "x": 4}, {"view": 1, "y": 7, "x": 5}])
def test_files_as_to_zarr_writes_them(chunking):
    ds = prepared(every_kind())
    encoding = stores_encoding(ds, chunking)
    ours = encode_store(ds, encoding)
    assert ours == reference(ds, encoding)
    # not vacuous: attributes xarray adds, a chunk of NaN and a variable of fill values left out
    assert b'"coordinates": "pose"' in ours["reflectance/zarr.json"] and b'"coordinates": "lonely"' in ours["zarr.json"]
    assert b'"_FillValue"' in ours["fit/zarr.json"] and not any(key.startswith(("empty/c", "never/c")) for key in ours)


@same_files
def test_strings_as_numpy_strings():
    """Stores read back hold numpy's variable-width strings; a stage may pass them on."""
    ds = prepared(every_kind())
    ds = ds.assign(names=ds["names"].astype(np.dtypes.StringDType()))
    encoding = stores_encoding(ds, {})
    assert encode_store(ds, encoding) == reference(ds, encoding)


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
    ds = change(prepared(every_kind()))
    assert encode_store(ds, stores_encoding(ds, {})) is None


def test_another_encoding_is_left_to_to_zarr():
    ds = prepared(every_kind())
    encoding = stores_encoding(ds, {})
    assert encode_store(ds, encoding) is not None
    for name, other in (("fit", {}), ("status", {"compressors": None}), ("count", {"filters": None})):
        assert encode_store(ds, encoding | {name: other}) is None, name


def test_store_written_with_a_fallback_variable_reads_back(tmp_path):
    ds = every_kind().assign(half=(("y", "x"), np.ones((7, 9), np.float16)))
    path = write_store(ds, tmp_path / "s.zarr", chunks={"y": 3, "x": 4})
    back = open_store(path).load()
    # the index of fixed-width strings written as variable-length ones, which zarr v3 specifies
    assert json.loads((path / "view" / "zarr.json").read_text())["data_type"] == "string"
    assert back["half"].dtype == np.float16 and back.attrs["nested"] == {"a": [1, 2], "b": None}
    np.testing.assert_array_equal(back["reflectance"].values, ds["reflectance"].values)


@same_files
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
        ds = prepared(opened.load())
        assert reference(ds, stores_encoding(ds, chunking)) == files, store


def test_own_files_are_used_only_where_they_agree(tmp_path, monkeypatch):
    """A writer that disagrees with to_zarr on the probe is not used, nor is the reader: zarr-python serves."""
    checked = surffin.io.store.own_files.__wrapped__
    assert checked() == own_files()
    monkeypatch.setattr(surffin.io.store, "encode_store", lambda ds, encoding: {"zarr.json": b"{}"})
    assert not checked()
    monkeypatch.setattr(surffin.io.store, "own_files", lambda: False)

    def refuse(*args):
        raise AssertionError("not to be used")

    monkeypatch.setattr(surffin.io.store, "encode_store", refuse)
    monkeypatch.setattr(surffin.io.store, "read_store", refuse)
    ds = every_kind()
    path = write_store(ds, tmp_path / "s.zarr", chunks={"y": 3, "x": 4})
    xr.testing.assert_identical(load_store(path), open_store(path, chunks=None).load())
    np.testing.assert_array_equal(load_store(path)["reflectance"].values, ds["reflectance"].values)


@pytest.mark.skipif(
    Version(zarr.__version__) < Version("3.1.6") or Version(xr.__version__) < Version("2026.9"),
    reason="older than the versions zarrwrite and zarrread were written against",
)
def test_own_files_agree_with_the_versions_they_were_written_for():
    assert own_files()
