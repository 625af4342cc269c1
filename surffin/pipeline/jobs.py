"""Job plumbing: where a job runs, its log file and its dask scheduler.

The workflow runs its jobs in snakemake's own threads (``force-use-threads`` in
``profiles/default``), and each job's work in a pool of worker processes kept
for the run (:func:`in_worker`): no process start-up per job, and jobs in
parallel despite the interpreter lock the threads share. A job's log file
takes the records of the thread that runs the job only, and the dask
configuration, which is process-wide, is set by the first job that needs it
and restored by the last one to leave, so that jobs run side by side in
threads of one process (a notebook, a test) do not disturb each other.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import os
import re
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Any

import dask
from dask.callbacks import Callback

__all__ = ["logging_to", "job_seconds", "dask_scheduler", "in_worker", "start_workers"]

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
    """Send this thread's surffin log records to ``path`` (and stderr) for the duration of a job.

    A job that ends without an exception logs its wall time last (:func:`job_seconds` reads it).
    """
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
    start = time.perf_counter()
    try:
        yield log
    except Exception:
        log.exception("job failed")
        raise
    else:
        log.info("job done in %.2f s", time.perf_counter() - start)
    finally:
        for handler in handlers:
            log.removeHandler(handler)
            handler.close()


#: The line :func:`logging_to` ends a job's log with.
_DONE = re.compile(r" INFO job done in ([0-9.]+) s$", re.M)


def job_seconds(path: str | os.PathLike) -> float | None:
    """Return the wall time of the job that wrote log file ``path``; None when it holds no finished job (or is missing).

    The workflow's jobs time themselves in their logs (:func:`logging_to`): snakemake's
    ``benchmark:`` measures the whole snakemake process and its workers when jobs run in
    its threads, and its sampling of their memory took 12-15 s of system CPU in a
    48-specimen campaign of ~175 core-s (``benchmarks/bench_campaign.py``).
    """
    try:
        done = _DONE.findall(Path(path).read_text())
    except FileNotFoundError:
        return None
    return float(done[-1]) if done else None


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
        try:
            from distributed import Client
        except ImportError:
            raise ValueError(
                f"dask scheduler {scheduler!r} needs dask.distributed: pip install 'surffin[distributed]'"
            ) from None
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


#: Modules the worker processes import once, when their server starts (scipy.optimize: the camera model's
#: fit imports it when called, so that snakemake's own process, which only names the stages, does not).
_PRELOAD = ["surffin.pipeline.run", "surffin.pipeline.analyses", "scipy.optimize"]


class _Workers:
    """The worker processes of :func:`in_worker`: one pool of one process each, started as jobs need them.

    A job goes to an idle worker that last ran a job of the same ``affinity`` key, else to the idle
    started worker used longest ago, else to a new one: an item's stages, run one after another,
    tend to share a process, which keeps the stores it loaded for the next stage
    (:class:`surffin.io.store.StoreCache`).
    """

    def __init__(self, size: int) -> None:
        self._pools: list[ProcessPoolExecutor | None] = [None] * size
        self._keys: list[Any] = [None] * size
        self._used = [0] * size
        self._busy = [False] * size
        self._jobs = 0
        self._free = threading.Condition()

    def _take(self, key: Any) -> int:
        with self._free:
            self._free.wait_for(lambda: not all(self._busy))
            idle = [i for i, busy in enumerate(self._busy) if not busy]
            started = [i for i in idle if self._pools[i] is not None]
            same = [i for i in started if key is not None and self._keys[i] == key]
            index = (same or sorted(started, key=self._used.__getitem__) or idle)[0]
            self._busy[index] = True
            self._jobs += 1
            self._used[index] = self._jobs
            self._keys[index] = self._keys[index] if key is None else key
            if self._pools[index] is None:
                self._pools[index] = _new_pool()
            return index

    def _give_back(self, index: int) -> None:
        with self._free:
            self._busy[index] = False
            self._free.notify()

    def run(self, key: Any, function: Callable, args: tuple, kwargs: dict) -> Any:
        """Run ``function(*args, **kwargs)`` in a worker chosen for ``key``; a crashed worker is replaced."""
        index = self._take(key)
        try:
            try:
                future = self._pools[index].submit(function, *args, **kwargs)
            except BrokenProcessPool:
                self._pools[index] = _new_pool()
                future = self._pools[index].submit(function, *args, **kwargs)
            return future.result()
        finally:
            self._give_back(index)


def _new_pool() -> ProcessPoolExecutor:
    # forkserver: the workers are forked from a clean single-threaded server that has
    # imported surffin, not from this multi-threaded process.
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(_PRELOAD)
    return ProcessPoolExecutor(max_workers=1, mp_context=context, initializer=_one_thread)


_WORKERS: list[_Workers] = []
_WORKERS_LOCK = threading.Lock()


def _workers() -> _Workers:
    """Return the process's workers, at most one per core, made on first use."""
    with _WORKERS_LOCK:
        if not _WORKERS:
            _WORKERS.append(_Workers(os.cpu_count() or 1))
        return _WORKERS[0]


def start_workers() -> threading.Thread:
    """Start the pool's first worker in the background and return the thread that starts it.

    The worker processes' server imports surffin (~2 s) before the first worker forks: started while
    snakemake builds its DAG, on the core that leaves idle, it is ready for the first job instead of
    delaying it. A failure to start is left to the first job's :func:`in_worker`, which reports it.
    """

    def start() -> None:
        with contextlib.suppress(Exception):
            _workers().run(None, os.getpid, (), {})

    thread = threading.Thread(target=start, name="surffin-workers", daemon=True)
    thread.start()
    return thread


def _one_thread() -> None:
    """Keep a worker's OpenCV calls on its own thread: the pool already runs one worker per core.

    OpenCV's own threads (one per core by default) would only contend with the other workers' jobs
    (docs/performance.md, campaign rate).
    """
    import cv2

    cv2.setNumThreads(1)


def _plain(value: Any) -> Any:
    """Return ``value`` with str subclasses (snakemake's file names) as str and mappings as dicts."""
    if isinstance(value, str):
        return str(value)
    if isinstance(value, Mapping):
        return {_plain(key): _plain(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(item) for item in value]
    return value


def in_worker(function: Callable, /, *args: Any, affinity: str | None = None, **kwargs: Any) -> Any:
    """Run ``function(*args, **kwargs)`` in a worker process and return what it returns.

    The workflow's jobs run in snakemake's threads, which share one interpreter
    lock: in threads, two jobs took as long as the same two one after the other.
    Each job's work therefore runs in a pool of worker processes, started once
    per run with surffin imported (``forkserver``), so that jobs run in parallel
    without a process start-up each. A worker's crash fails the job it was
    running, and the worker is replaced for the next ones.

    Parameters
    ----------
    function : callable
        A module-level function (it is sent to the worker by name).
    *args, **kwargs
        Its arguments: plain values, paths, mappings and sequences of them.
    affinity : str, optional
        A key (an item's name) of jobs that read each other's stores: they go to the worker
        that ran the last of them when it is idle (:class:`_Workers`).
    """
    args, kwargs = _plain(args), _plain(kwargs)
    return _workers().run(affinity, function, tuple(args), kwargs)
