"""Loading stores whole: ``load_store`` (``surffin.io.zarrread``) against xarray through zarr-python.

Run by hand: ``python benchmarks/bench_read.py STORE [STORE ...] [--repeat 15]``, e.g. stores of a run's
``processed`` folder. Each store is loaded by :func:`~surffin.io.store.load_store` and, as the reference,
by ``open_store(path, chunks=None).load()`` (what every job did before), the two alternating so that
the machine's load (it is shared) falls on both alike; one warm-up round is not counted. Prints per
store its size in memory, the median milliseconds of each, the ratio reference / ``load_store`` and
whether the two Datasets are the same (:func:`~surffin.io.store.same_dataset`: the variables,
coordinates and indexes in the same order with the same dtypes, values bit for bit, attributes' types).
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

import xarray as xr

from surffin.io.store import load_store, open_store, same_dataset


def reference(path: Path) -> xr.Dataset:
    """Load a store as surffin did before ``load_store``: through xarray and zarr-python."""
    return open_store(path, chunks=None).load()


def main():
    """Load each store both ways and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("stores", nargs="+", type=Path, help="the stores to load")
    parser.add_argument("--repeat", type=int, default=15, help="counted rounds")
    args = parser.parse_args()
    times = {path: ([], []) for path in args.stores}
    for round_ in range(args.repeat + 1):
        for path, (new, old) in times.items():
            for load, spent in ((load_store, new), (reference, old)):
                start = time.perf_counter()
                load(path)
                if round_:
                    spent.append(time.perf_counter() - start)
    print(f"stores loaded whole, median ms over {args.repeat} rounds")
    names = {path: os.path.join(path.parent.name, path.name) for path in args.stores}
    width = max(len(name) for name in names.values()) + 2
    print(f"{'store':>{width}s}{'MB':>7s}{'load_store':>12s}{'xarray':>9s}{'ratio':>8s}{'identical':>11s}")
    for path, (new, old) in times.items():
        ds = load_store(path)
        new, old = statistics.median(new) * 1e3, statistics.median(old) * 1e3
        same = "yes" if same_dataset(ds, reference(path)) else "NO"
        print(f"{names[path]:>{width}s}{ds.nbytes / 1e6:7.1f}{new:12.2f}{old:9.2f}{old / new:8.2f}{same:>11s}")


if __name__ == "__main__":
    main()
