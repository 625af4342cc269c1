import json
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
import zarr
from hypothesis import given
from hypothesis import strategies as st

import surffin
from surffin.errors import StoreError
from surffin.io.store import (
    JSON_ATTRS,
    StoreCache,
    clean_leftovers,
    decode_attrs,
    encode_attrs,
    open_store,
    provenance,
    write_store,
)
from surffin.paper import DOI


def cube(nview=3, ny=7, nx=9, seed=0):
    rng = np.random.default_rng(seed)
    return xr.Dataset(
        {
            "a": (("view", "y", "x"), rng.random((nview, ny, nx)).astype("f4"), {"units": "1", "long_name": "a"}),
            "m": (("view", "y", "x"), rng.random((nview, ny, nx)) > 0.5),
        },
        coords={"view": [f"v{i:02d}" for i in range(nview)], "y": np.arange(10, 10 + ny), "x": np.arange(nx)},
        attrs=provenance("test", {"window": 15}, {"a.npz": {"size": 3}}),
    )


def test_round_trip_with_plain_xarray(tmp_path):
    ds = cube()
    path = write_store(ds, tmp_path / "s.zarr", chunks={"y": 4, "x": 5})
    back = xr.open_zarr(path)
    xr.testing.assert_equal(back.compute(), ds)
    xr.testing.assert_identical(open_store(path).compute(), ds)
    assert back.attrs["surffin_version"] == surffin.__version__
    # plain xarray sees the nested attrs as JSON text, named in surffin_json_attrs
    assert json.loads(back.attrs["surffin_parameters"]) == {"window": 15}
    assert json.loads(back.attrs[JSON_ATTRS]) == ["surffin_inputs", "surffin_parameters"]
    # chunks that do not divide the image, view never split
    assert back["a"].chunks == ((3,), (4, 3), (5, 4))
    meta = json.loads((path / "zarr.json").read_text())
    assert meta["zarr_format"] == 3 and "consolidated_metadata" in meta


def test_store_cache_keeps_a_store_until_it_is_written_anew(tmp_path):
    path = write_store(nested_attrs_store(), tmp_path / "s.zarr")
    other = write_store(cube(seed=1), tmp_path / "o.zarr")
    cache = StoreCache(max_bytes=10**6)
    assert cache.get(path) is None
    loaded = cache.keep(path)
    xr.testing.assert_identical(loaded, open_store(path).compute())
    kept = cache.get(tmp_path / "." / "s.zarr")  # the same store by another spelling of its path
    xr.testing.assert_identical(kept, loaded)
    assert kept["a"].data is loaded["a"].data  # not read again
    with pytest.raises(ValueError, match="read-only"):
        kept["a"].data[0, 0, 0] = 2.0
    # a caller's attributes, nested ones included, are its own
    kept.attrs["camera"]["width"] = 0
    kept["a"].attrs["unclassified"]["board"] = 0
    assert cache.get(path).attrs["camera"]["width"] == 9
    assert cache.get(path)["a"].attrs["unclassified"] == {"board": 3}
    # a store written anew at the path is read anew
    write_store(cube(seed=2), path)
    assert cache.get(path) is None
    xr.testing.assert_identical(cache.keep(path), cube(seed=2))
    assert cache.get(other) is None and cache.keep(other) is not None
    xr.testing.assert_identical(cache.get(other), cube(seed=1))


def test_store_cache_lets_the_least_recently_used_store_go_beyond_its_bytes(tmp_path):
    paths = [write_store(cube(seed=seed), tmp_path / f"{seed}.zarr") for seed in range(3)]
    size = StoreCache(max_bytes=0).keep(paths[0]).nbytes  # as the cache counts it (strings' dtype: numpy's)
    cache = StoreCache(max_bytes=2 * size)
    cache.keep(paths[0])
    cache.keep(paths[1])
    assert cache.get(paths[0]) is not None  # now the most recently used
    cache.keep(paths[2])
    assert cache.get(paths[1]) is None
    assert cache.get(paths[0]) is not None and cache.get(paths[2]) is not None
    small = StoreCache(max_bytes=size - 1)
    xr.testing.assert_identical(small.keep(paths[0]), cube(seed=0))
    assert small.get(paths[0]) is None


def nested_attrs_store():
    ds = cube()
    ds.attrs |= {"camera": {"width": 9, "intrinsics": {"fx": 7.5}}, "ok": True, "none": None, "names": ["a", "b"]}
    ds["a"].attrs |= {"flag_values": [0, 1], "unclassified": {"board": 3}}
    return ds


@pytest.mark.parametrize("engine", ["scipy", "netcdf4", "h5netcdf"])
def test_every_attr_survives_netcdf(tmp_path, engine):
    if engine != "scipy":
        pytest.importorskip({"netcdf4": "netCDF4", "h5netcdf": "h5netcdf"}[engine])
    ds = nested_attrs_store()
    path = write_store(ds, tmp_path / "s.zarr")
    xr.open_zarr(path).to_netcdf(tmp_path / "s.nc", engine=engine)
    back = xr.open_dataset(tmp_path / "s.nc", engine=engine)
    xr.testing.assert_equal(back.load(), ds)
    # surffin's decoding reads the netCDF attrs back as written
    assert decode_attrs(back.attrs)["camera"] == {"width": 9, "intrinsics": {"fx": 7.5}}
    assert decode_attrs(back["a"].attrs)["unclassified"] == {"board": 3}


def test_nested_attrs_round_trip_through_the_store(tmp_path):
    ds = nested_attrs_store()
    back = open_store(write_store(ds, tmp_path / "s.zarr"))
    assert back.attrs["ok"] is True and back.attrs["none"] is None and back.attrs["names"] == ["a", "b"]
    xr.testing.assert_identical(back.compute(), ds)


json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**40), 2**40) | st.floats(allow_nan=False) | st.text(),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=5), inner, max_size=4),
    max_leaves=12,
)


@given(st.dictionaries(st.text(min_size=1, max_size=8).filter(lambda k: k != JSON_ATTRS), json_values, max_size=6))
def test_encode_decode_inverse_and_only_netcdf_types_left(attrs):
    encoded = encode_attrs(attrs)
    assert decode_attrs(encoded) == {key: list(v) if isinstance(v, tuple) else v for key, v in attrs.items()}
    for value in encoded.values():
        if isinstance(value, list):
            assert value and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
        else:
            assert isinstance(value, (str, int, float)) and not isinstance(value, bool)


def test_provenance_carries_cf_globals():
    attrs = provenance("aoi", {"window": 15})
    assert attrs["Conventions"].startswith("CF-")
    assert DOI in attrs["references"]
    assert "surffin" in attrs["history"] and "stage aoi" in attrs["history"] and attrs["title"]


def test_strings_are_variable_length(tmp_path):
    path = write_store(cube(), tmp_path / "s.zarr")
    assert str(zarr.open_group(path)["view"].dtype) != "<U3"
    assert list(xr.open_zarr(path)["view"].values) == ["v00", "v01", "v02"]


def test_floats_uncompressed_masks_compressed(tmp_path):
    group = zarr.open_group(write_store(cube(), tmp_path / "s.zarr"))
    assert group["a"].compressors == ()
    assert group["m"].compressors != ()


def test_crash_leaves_previous_store_and_no_lookalike(tmp_path, monkeypatch):
    """Killed after some of a store's files are written."""
    path = write_store(cube(seed=1), tmp_path / "s.zarr")
    written = []
    write_bytes = Path.write_bytes

    def explode(self, *args, **kwargs):
        written.append(self)
        if len(written) == 3:
            raise RuntimeError("killed")
        return write_bytes(self, *args, **kwargs)

    monkeypatch.setattr(Path, "write_bytes", explode)
    with pytest.raises(RuntimeError):
        write_store(cube(seed=2), path)
    monkeypatch.undo()
    assert len(written) == 3
    xr.testing.assert_identical(open_store(path).load(), cube(seed=1))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.zarr"]


def test_crash_of_a_dask_backed_write_leaves_previous_store(tmp_path, monkeypatch):
    path = write_store(cube(seed=1), tmp_path / "s.zarr")

    def explode(self, *args, **kwargs):
        raise RuntimeError("killed")

    monkeypatch.setattr(xr.Dataset, "to_zarr", explode)
    with pytest.raises(RuntimeError):
        write_store(cube(seed=2).chunk(), path)
    monkeypatch.undo()
    xr.testing.assert_identical(open_store(path).load(), cube(seed=1))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.zarr"]


def test_leftovers_of_a_kill_are_removed_by_next_write(tmp_path):
    partial = tmp_path / ".s.zarr.partial-deadbeef"
    (partial / "a").mkdir(parents=True)
    unrelated = tmp_path / ".t.zarr.partial-deadbeef"
    unrelated.mkdir()
    write_store(cube(), tmp_path / "s.zarr")
    assert not partial.exists() and unrelated.exists()
    assert clean_leftovers(tmp_path / "t.zarr") == [unrelated]


def test_replacing_a_store(tmp_path):
    path = write_store(cube(seed=1), tmp_path / "s.zarr")
    write_store(cube(seed=2), path)
    xr.testing.assert_identical(open_store(path).load(), cube(seed=2))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.zarr"]


def test_open_store_errors(tmp_path):
    with pytest.raises(StoreError, match="no zarr store"):
        open_store(tmp_path / "missing.zarr")
    path = write_store(cube(), tmp_path / "s.zarr")
    assert open_store(path, stage="test").sizes["view"] == 3
    with pytest.raises(StoreError, match="stage 'aoi'"):
        open_store(path, stage="aoi")


def test_dask_input_is_written_lazily(tmp_path):
    ds = cube().chunk({"view": -1, "y": 2, "x": 3})
    path = write_store(ds, tmp_path / "s.zarr", chunks={"y": 2, "x": 3})
    xr.testing.assert_identical(open_store(path).load(), ds.load())


def test_memory_and_dask_writes_lay_out_the_same_files(tmp_path):
    # a Dataset in memory is encoded in memory and its files written by write_store; dask arrays go through
    # zarr's file store: both must leave the same files, byte for byte
    ds = cube(ny=11, nx=13)
    in_memory = write_store(ds, tmp_path / "memory.zarr", chunks={"y": 4, "x": 5})
    lazy = write_store(ds.chunk({"view": -1, "y": 4, "x": 5}), tmp_path / "dask.zarr", chunks={"y": 4, "x": 5})

    def files(root):
        return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}

    written = files(in_memory)
    assert "a/c/0/1/2" in written and len(written) == len(files(lazy))
    assert written == files(lazy)


def test_crash_while_writing_files_leaves_previous_store(tmp_path, monkeypatch):
    path = write_store(cube(seed=1), tmp_path / "s.zarr")
    calls = []

    def fail_third(self, data):
        calls.append(self)
        if len(calls) == 3:
            raise OSError("disk full")
        return original(self, data)

    original = type(path).write_bytes
    monkeypatch.setattr(type(path), "write_bytes", fail_third)
    with pytest.raises(OSError, match="disk full"):
        write_store(cube(seed=2), path)
    monkeypatch.undo()
    xr.testing.assert_identical(open_store(path).load(), cube(seed=1))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.zarr"]
