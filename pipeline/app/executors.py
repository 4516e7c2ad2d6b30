"""Executors: run one function over many items, locally or on a Dask cluster.

One small interface, :class:`Executor`: ``map(fn, items)`` yields ``(item, result)`` as items
finish (in completion order), where ``result`` is what ``fn`` returned or the exception that
prevented it (a crashed worker, a lost connection). ``fn`` must be a module-level function and
items and results small picklable values (paths and frozen option dataclasses in, small JSON-able
dicts out): nothing large travels, and nothing read from disk is ever unpickled.

Trust: a Dask scheduler runs whatever its clients send and its clients run whatever results it
sends back (pickle over the network). Join only a scheduler you trust like a shell on the
machines it runs on.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import logging
import multiprocessing as mp
import os
from collections.abc import Callable, Iterable, Iterator
from typing import Any, Protocol, TypeVar

import numpy  # noqa: F401 - loads the BLAS library, which threadpoolctl can only limit once loaded
from threadpoolctl import threadpool_limits

from pipeline.core.errors import UsageError

T = TypeVar("T")
R = TypeVar("R")


class Executor(Protocol):
    """Run ``fn`` over ``items``; yield ``(item, result or exception)`` as each finishes."""

    workers: int

    def map(
        self, fn: Callable[[T], R], items: Iterable[T]
    ) -> Iterator[tuple[T, R | BaseException]]:
        """Yield ``(item, fn(item))`` or ``(item, exception)`` in completion order."""
        ...

    def close(self) -> None:
        """Release workers."""
        ...

    def describe(self) -> str:
        """One line saying where the work runs."""
        ...


class SerialExecutor:
    """Runs everything in this process (for debugging and tiny inputs)."""

    workers = 1

    def map(
        self, fn: Callable[[T], R], items: Iterable[T]
    ) -> Iterator[tuple[T, R | BaseException]]:
        """See :class:`Executor`."""
        for it in items:
            try:
                res: Any = fn(it)
            except Exception as exc:  # noqa: BLE001 - reported per item
                res = exc
            yield it, res

    def close(self) -> None:
        """Nothing to release."""

    def describe(self) -> str:
        """See :class:`Executor`."""
        return "in this process"


def limit_blas_threads(n: int) -> None:
    """Let the BLAS of this worker process use at most ``n`` threads.

    Each of ``jobs`` workers gets ``cpu_count // jobs`` threads: with every worker's BLAS
    spawning a thread per core the cores are oversubscribed (40 ten-minute recordings on 2
    cores, 2 workers: 80.6 s with the default, 70.8 s with one thread each). Dask's nanny
    does the same for its workers (``distributed.nanny.pre-spawn-environ``).
    """
    threadpool_limits(limits=n, user_api="blas")


def _mp_context() -> mp.context.BaseContext:
    """Pick forkserver where available (no inherited threads or locks), else spawn."""
    methods = mp.get_all_start_methods()
    return mp.get_context("forkserver" if "forkserver" in methods else "spawn")


class LocalExecutor:
    """A local process pool (``concurrent.futures``, forkserver or spawn start).

    Parameters
    ----------
    jobs : int
        Worker processes (>= 1).

    Notes
    -----
    If a worker dies (killed, out of memory), the pool breaks and every unfinished item
    fails; those items are retried once in a fresh pool, so one crashing recording costs
    only itself.

    """

    def __init__(self, jobs: int = 1):
        if jobs < 1:
            raise UsageError(f"--jobs must be at least 1, got {jobs}")
        self.workers = int(jobs)
        self._pool: cf.ProcessPoolExecutor | None = None

    def _new_pool(self) -> cf.ProcessPoolExecutor:
        threads = max(1, (os.cpu_count() or 1) // self.workers)
        return cf.ProcessPoolExecutor(max_workers=self.workers, mp_context=_mp_context(),
                                      initializer=limit_blas_threads, initargs=(threads,))

    def map(
        self, fn: Callable[[T], R], items: Iterable[T]
    ) -> Iterator[tuple[T, R | BaseException]]:
        """See :class:`Executor`."""
        pending = list(items)
        for attempt in range(2):
            if not pending:
                return
            if self._pool is None:
                self._pool = self._new_pool()
            futs = {self._pool.submit(fn, it): it for it in pending}
            broken: list[T] = []
            for f in cf.as_completed(futs):
                it = futs[f]
                try:
                    yield it, f.result()
                except cf.process.BrokenProcessPool as exc:
                    if attempt == 0:
                        broken.append(it)
                    else:
                        yield it, exc
                except Exception as exc:  # noqa: BLE001 - reported per item
                    yield it, exc
            if broken:
                self._pool.shutdown(wait=False, cancel_futures=True)
                self._pool = None
                # Retry one at a time so a crashing item cannot take the others down again.
                for it in broken:
                    yield it, self._retry_one(fn, it)
                return
            pending = []

    def _retry_one(self, fn: Callable[[T], R], it: T) -> R | BaseException:
        pool = self._new_pool()
        try:
            return pool.submit(fn, it).result()
        except Exception as exc:  # noqa: BLE001
            return exc
        finally:
            pool.shutdown(wait=True, cancel_futures=True)

    def close(self) -> None:
        """Shut the pool down."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    def describe(self) -> str:
        """See :class:`Executor`."""
        return f"{self.workers} local worker{'s' if self.workers != 1 else ''}"


def _quiet_dask_logs() -> None:
    """Keep Dask's start-up chatter (INFO) off the user's terminal; warnings still show."""
    import dask

    # Worker processes configure their logging from this config (passed on by the nanny).
    dask.config.set({"logging.distributed": "warning"})


def _tune_dask_workers() -> None:
    """Dask defaults that cost our numpy-heavy tasks about a factor 2 (measured, bench).

    The statistical profiler samples the task thread every 10 ms and the GIL monitor every
    1 ms; ``MALLOC_TRIM_THRESHOLD_=65536`` returns freed memory to the OS at once, so each
    large array is page-faulted in again. Setting that variable to any value also switches
    off glibc's dynamic mmap threshold (every array above 128 kB is then mmap'ed and unmapped
    afresh), so it is unset (``None``), not raised. Local process pools have none of these.
    """
    import dask

    dask.config.set({
        "distributed.worker.profile.enabled": False,
        "distributed.admin.system-monitor.gil.enabled": False,
        "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
    })
    names = ["distributed"] + [n for n in logging.root.manager.loggerDict
                               if n.startswith("distributed.")]
    for n in names:
        lg = logging.getLogger(n)
        if lg.level < logging.WARNING:
            lg.setLevel(logging.WARNING)


class DaskExecutor:
    """Dask distributed: a LocalCluster of ``n_workers`` or an existing scheduler.

    Parameters
    ----------
    address : str, optional
        ``tcp://host:port`` of a running scheduler (its workers must have magalign installed
        and see the input and output paths). Trust it like a shell.
    n_workers : int, optional
        Start a LocalCluster with this many single-threaded worker processes.

    """

    def __init__(self, *, address: str | None = None, n_workers: int | None = None):
        try:
            from distributed import Client, LocalCluster
        except ImportError as exc:  # pragma: no cover - dask is a dependency
            raise UsageError("Dask distributed is not installed",
                             hint="pip install 'dask[distributed]'") from exc
        _quiet_dask_logs()
        _tune_dask_workers()
        if (address is None) == (n_workers is None):
            raise UsageError("give either a scheduler address or a number of local workers")
        self._cluster = None
        if address is not None:
            if not address.startswith(("tcp://", "tls://", "ucx://", "inproc://")):
                raise UsageError(f"--scheduler {address!r} is not an address like "
                                 "tcp://host:port")
            try:
                self._client = Client(address, timeout="20s")
            except OSError as exc:
                raise UsageError(f"cannot reach the Dask scheduler at {address}: {exc}",
                                 hint="check the address and that the scheduler runs") from exc
            self.workers = max(1, len(self._client.scheduler_info().get("workers", {})))
            self._where = f"Dask scheduler {address} ({self.workers} worker(s))"
        else:
            assert n_workers is not None  # exactly one of address, n_workers (checked above)
            if n_workers < 1:
                raise UsageError(f"--dask-local must be at least 1, got {n_workers}")
            self._cluster = LocalCluster(
                n_workers=n_workers, threads_per_worker=1, processes=True,
                dashboard_address=None, silence_logs=40,
            )
            self._client = Client(self._cluster)
            self.workers = n_workers
            self._where = f"Dask LocalCluster of {n_workers} worker(s)"

    def map(
        self, fn: Callable[[T], R], items: Iterable[T]
    ) -> Iterator[tuple[T, R | BaseException]]:
        """See :class:`Executor`."""
        from distributed import as_completed

        items = list(items)
        if not items:
            return
        futs = [self._client.submit(fn, it, pure=False) for it in items]
        index = {f.key: it for f, it in zip(futs, items, strict=True)}
        for f in as_completed(futs):
            it = index[f.key]
            try:
                yield it, f.result()
            except Exception as exc:  # noqa: BLE001 - reported per item
                yield it, exc
            finally:
                f.release()

    def close(self) -> None:
        """Close the client (and the LocalCluster it started)."""
        with contextlib.suppress(Exception):
            self._client.close()
        if self._cluster is not None:
            with contextlib.suppress(Exception):
                self._cluster.close()

    def describe(self) -> str:
        """See :class:`Executor`."""
        return self._where


def make_executor(*, jobs: int | None = None, dask_local: int | None = None,
                  scheduler: str | None = None, items: int | None = None) -> Executor:
    """Make the executor the command line asked for (local process pool by default).

    ``items``: how many items will be run, when known. A single item runs in this process
    (unless a Dask cluster was asked for): a worker could isolate nothing but the whole
    command, and would cost a second interpreter that imports the pipeline again (1.5 of a
    small recording's 8 CPU-seconds, docs/performance.md).
    """
    if dask_local is not None and scheduler is not None:
        raise UsageError("give --dask-local or --scheduler, not both")
    if dask_local is not None:
        return DaskExecutor(n_workers=dask_local)
    if scheduler is not None:
        return DaskExecutor(address=scheduler)
    local = LocalExecutor(jobs if jobs is not None else 1)  # checks --jobs either way
    return SerialExecutor() if items == 1 else local
