"""Stage entry points: campaign or stores in, one complete store out.

Each function here is what one workflow rule runs (through a two-line script in
``workflow/scripts/``); they are plain Python and usable without snakemake.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from collections.abc import Iterator, Mapping
from pathlib import Path

from surffin.campaign import read_campaign
from surffin.ingest import ingest_item
from surffin.store import write_store

__all__ = ["run_ingest", "logging_to"]

log = logging.getLogger("surffin")


@contextlib.contextmanager
def logging_to(path: str | os.PathLike | None) -> Iterator[logging.Logger]:
    """Send surffin's log records to ``path`` (and stderr) for the duration of a stage."""
    handlers: list[logging.Handler] = [logging.StreamHandler()]
    if path is not None:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        handlers.append(logging.FileHandler(path, mode="w"))
    formatter = logging.Formatter("%(asctime)s %(levelname)s %(message)s")
    for handler in handlers:
        handler.setFormatter(formatter)
        log.addHandler(handler)
    previous = log.level
    log.setLevel(logging.INFO)
    try:
        yield log
    except Exception:
        log.exception("stage failed")
        raise
    finally:
        log.setLevel(previous)
        for handler in handlers:
            log.removeHandler(handler)
            handler.close()


def run_ingest(
    campaign: str | os.PathLike,
    item: str,
    store: str | os.PathLike,
    *,
    chunks: Mapping[str, int] | None = None,
    log_path: str | os.PathLike | None = None,
) -> Path:
    """Read an item's view files and write its ingest store.

    Parameters
    ----------
    campaign : path-like
        The campaign directory.
    item : str
        Specimen or scene name.
    store : path-like
        Output store (``ingest/<item>.zarr``).
    chunks : mapping, optional
        Chunk sizes over ``y`` and ``x``.
    log_path : path-like, optional
        Log file of the stage.
    """
    with logging_to(log_path):
        start = time.perf_counter()
        camp = read_campaign(campaign, require_calibration=False)
        ds = ingest_item(camp, item)
        log.info("ingest %s: %d views, cube %s", item, ds.sizes["view"], dict(ds.sizes))
        path = write_store(ds, store, chunks=chunks)
        log.info("wrote %s in %.2f s", path, time.perf_counter() - start)
        return path
