"""Job plumbing: a job's log file and its dask scheduler, safe for jobs run side by side in threads.

The workflow runs its jobs in snakemake's own threads (``force-use-threads`` in
``profiles/default``), so two jobs share one process. A job's log file takes
the records of the thread that runs the job only, and the dask configuration,
which is process-wide, is set by the first job that needs it and restored by
the last one to leave, instead of each job setting and restoring it under the
other's feet.
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
from collections.abc import Iterator
from pathlib import Path

import dask
from dask.callbacks import Callback

__all__ = ["logging_to", "dask_scheduler"]

log = logging.getLogger("surffin")


class _ThisThread(logging.Filter):
    """Pass the records of the thread that made the filter."""

    def __init__(self) -> None:
        super().__init__()
        self._thread = threading.get_ident()

    def filter(self, record: logging.LogRecord) -> bool:
        return record.thread == self._thread


@contextlib.contextmanager
def logging_to(path: str | os.PathLike | None) -> Iterator[logging.Logger]:
    """Send this thread's surffin log records to ``path`` (and stderr) for the duration of a job."""
    handlers: list[logging.Handler] = [logging.StreamHandler()]
    if path is not None:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        handlers.append(logging.FileHandler(path, mode="w"))
    formatter = logging.Formatter("%(asctime)s %(levelname)s %(message)s")
    this_thread = _ThisThread()
    for handler in handlers:
        handler.setFormatter(formatter)
        handler.addFilter(this_thread)
        log.addHandler(handler)
    log.setLevel(logging.INFO)
    try:
        yield log
    except Exception:
        log.exception("job failed")
        raise
    finally:
        for handler in handlers:
            log.removeHandler(handler)
            handler.close()


class _LogProgress(Callback):
    """Log the share of dask tasks done, in steps of 10 %, of the computations started by one thread."""

    def __init__(self) -> None:
        super().__init__()
        self._thread = threading.get_ident()
        self._total = 0

    def _start_state(self, dsk, state):
        if threading.get_ident() == self._thread:
            self._total = max(1, sum(len(state[key]) for key in ("ready", "waiting", "running", "finished")))
            self._next = 0.1

    def _posttask(self, key, result, dsk, state, worker_id):
        if threading.get_ident() != self._thread or not self._total:
            return
        done = len(state["finished"]) / self._total
        if done >= self._next:
            log.info("progress: %d %% of %d tasks", int(100 * done), self._total)
            self._next = (int(done * 10) + 1) / 10


class _Shared:
    """A process-wide context entered by the first job that asks for it and left by the last one.

    Jobs asking for another setting while one is in use wait until it is free.
    """

    def __init__(self) -> None:
        self._condition = threading.Condition()
        self._key = None
        self._users = 0
        self._stack: contextlib.ExitStack | None = None

    @contextlib.contextmanager
    def use(self, key, enter) -> Iterator[None]:
        with self._condition:
            self._condition.wait_for(lambda: self._users == 0 or self._key == key)
            if self._users == 0:
                self._stack = contextlib.ExitStack()
                try:
                    enter(self._stack)
                except BaseException:
                    self._stack = None
                    raise
                self._key = key
            self._users += 1
        try:
            yield
        finally:
            with self._condition:
                self._users -= 1
                if self._users == 0:
                    stack, self._stack, self._key = self._stack, None, None
                    stack.close()
                    self._condition.notify_all()


_SCHEDULER = _Shared()


def _enter_scheduler(scheduler: str, threads: int, stack: contextlib.ExitStack) -> None:
    if "://" in scheduler:
        from distributed import Client

        stack.enter_context(Client(scheduler))
        return
    from dask.base import named_schedulers

    if scheduler not in named_schedulers:
        raise ValueError(
            f"unknown dask scheduler {scheduler!r}: expected threads, processes, synchronous or the "
            "address of a dask.distributed scheduler (e.g. tcp://10.0.0.1:8786)"
        )
    # The scheduler's function, not its name, and rechunks by tasks: given a name, or left
    # to choose a rechunk method, dask imports dask.distributed (0.4 s, in every job) to
    # look for a client first. Its other method, p2p, needs that client.
    local = {"scheduler": named_schedulers[scheduler], "num_workers": threads, "array.rechunk.method": "tasks"}
    stack.enter_context(dask.config.set(local))


@contextlib.contextmanager
def dask_scheduler(scheduler: str | None, threads: int = 1) -> Iterator[None]:
    """Run dask computations on ``scheduler`` inside the block, with progress in the log.

    Parameters
    ----------
    scheduler : {"threads", "processes", "synchronous"} or address, optional
        A ``tcp://...`` (or other) address connects to a running
        ``dask.distributed`` scheduler; None keeps dask's default.
    threads : int
        Workers of the local ``threads`` / ``processes`` schedulers.
    """
    if scheduler is None:
        yield
        return
    with _SCHEDULER.use((scheduler, threads), lambda stack: _enter_scheduler(scheduler, threads, stack)):
        with _LogProgress():
            yield
