"""One item's chain from view files to features stores, per chunk size of the stores.

Run by hand: ``python benchmarks/bench_chunks.py [--campaign DIR] [--chunks 256 512]
[--repeat 5] [--threads 1]``. Without ``--campaign`` it renders the ``paper`` preset into a
temporary folder. The calibration is fitted once; then each specimen's and the scene's chain
runs as the workflow's jobs run it (:func:`run_chain`: the five stores written and read back)
with each chunk size in turn, the sizes alternating so that the machine's load (it is shared)
falls on all of them alike. One warm-up round is not counted. Prints the median seconds of a
chain per chunk size and its ratio to the first size.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import statistics
import tempfile
import time
from collections.abc import Iterator, Mapping
from pathlib import Path

from _paper import paper_campaign  # benchmarks/_paper.py: this folder is on sys.path when run as a script

from surffin.method.stages import ITEM_CHAIN
from surffin.pipeline import parameters
from surffin.pipeline.run import run_calibration, run_ingest, run_stage

#: The workflow's configuration (config/config.yaml).
CONFIG = parameters.read_config()


def quiet_logs() -> None:
    """Keep surffin's warnings only: each job's log (of ``run_stage`` ...) also goes to stderr."""
    logging.getLogger("surffin").addFilter(lambda record: record.levelno >= logging.WARNING)


@contextlib.contextmanager
def calibrated_campaign(path: Path | None) -> Iterator[tuple]:
    """Yield the campaign at ``path`` (default: the ``paper`` preset rendered), a temporary folder and its calibration.

    The calibration store is fitted into the folder with the config's parameters, as the workflow fits it.
    """
    with paper_campaign(path) as (camp, _), tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        yield (
            camp,
            out,
            run_calibration(camp.path, out / "calibration.zarr", params=parameters.calibration_parameters(CONFIG)),
        )


def chain_parameters(config: Mapping, item) -> dict:
    """Return the keyword parameters of the chain's stages, as the workflow's rules give them."""
    return {
        **parameters.aoi_parameters(config),
        **parameters.feature_parameters(config),
        **parameters.registration_parameters(config),
        "roi": None if item.roi is None else item.roi.as_mapping(),
    }


def run_chain(
    camp,
    name: str,
    folder: str | os.PathLike,
    calibration: str | os.PathLike,
    *,
    config: Mapping = CONFIG,
    chunks: Mapping[str, int] | None = None,
    scheduler: str | None = None,
    threads: int = 1,
) -> tuple[dict[str, Path], dict[str, float]]:
    """Run an item's chain as the workflow's jobs do, store to store; returns its stores and each stage's seconds.

    :func:`~surffin.pipeline.run.run_ingest` writes ``<folder>/ingest/<name>.zarr``, then
    :func:`~surffin.pipeline.run.run_stage` runs each step of
    :data:`~surffin.method.stages.ITEM_CHAIN` into ``<folder>/<step.output>/<name>.zarr``,
    reading the stores it takes (``step.inputs``; ``calibration`` is the calibration store) with
    the config's values of its parameters (``step.keywords``). ``chunks`` and ``scheduler``
    default to the config's.
    """
    params = chain_parameters(config, camp.items[name])
    chunks, scheduler = chunks or config["chunks"], scheduler or config["scheduler"]
    stores = {"calibration": calibration, "ingest": Path(folder, "ingest", f"{name}.zarr")}
    start = time.perf_counter()
    run_ingest(camp.path, name, stores["ingest"], chunks=chunks)
    seconds = {"ingest": time.perf_counter() - start}
    for step in ITEM_CHAIN:
        stores[step.output] = Path(folder, step.output, f"{name}.zarr")
        start = time.perf_counter()
        run_stage(
            step.function,
            stores[step.output],
            stores={key: stores[key] for key in step.inputs},
            params={key: params[key] for key in step.keywords if key in params},
            chunks=chunks,
            scheduler=scheduler,
            threads=threads,
        )
        seconds[step.name] = time.perf_counter() - start
    return {key: path for key, path in stores.items() if key != "calibration"}, seconds


def main():
    """Run the item chains with each chunk size and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--campaign", type=Path, help="a rendered paper campaign")
    parser.add_argument("--chunks", type=int, nargs="+", default=[256, 512], help="y and x chunk sizes to compare")
    parser.add_argument("--repeat", type=int, default=5, help="counted rounds")
    parser.add_argument("--threads", type=int, default=1, help="dask threads (the workflow's per-item jobs: 1)")
    args = parser.parse_args()
    quiet_logs()
    with calibrated_campaign(args.campaign) as (camp, out, calibration):
        times = {size: [] for size in args.chunks}
        for round_ in range(args.repeat + 1):
            for size in args.chunks:
                chunks = {"y": size, "x": size}
                for name in camp.items:
                    start = time.perf_counter()
                    run_chain(camp, name, out / str(size), calibration, chunks=chunks, threads=args.threads)
                    if round_:
                        times[size].append(time.perf_counter() - start)
        crop = camp.crop
        print(
            f"item chain (run_ingest, run_stage per stage) over {len(camp.items)} items "
            f"({crop.shape[0]} x {crop.shape[1]} crop), threads {args.threads}, {args.repeat} rounds"
        )
        print(f"{'chunks':>8s}{'median s':>10s}{'ratio':>8s}")
        reference = statistics.median(times[args.chunks[0]])
        for size, values in times.items():
            median = statistics.median(values)
            print(f"{size:>8d}{median:10.3f}{median / reference:8.2f}")


if __name__ == "__main__":
    main()
