"""Independent fits of one analysis side by side, on the cores this process may use.

The diagnosis fits many models that do not depend on each other: the held-out folds of a
model, the strongest candidates of a search round, the model without each of its terms.
Each fit is numpy on arrays of thousands of rows, BLAS on one thread
(:func:`pipeline.model.solve.one_blas_thread`) and numba loops compiled without the GIL,
so threads run them in parallel for most of their time.

The cores a process may use are those its BLAS may use, which every executor already sets:
all of them for one recording in the command's own process, ``cpu_count // jobs`` in a
local pool's worker (:func:`pipeline.app.executors.limit_blas_threads`), one in a Dask
worker (the nanny's ``OPENBLAS_NUM_THREADS=1``). So a campaign's workers do not
oversubscribe the machine, and a single recording uses what is free.

The results do not depend on the number of threads: each fit is a pure function of its
inputs, the caches the model keeps between evaluations are per thread
(:mod:`stages.diagnose.model`), and :func:`ordered` returns results in the order of its
items. ``tests/test_parallel_fits.py`` holds a diagnosis on one thread and on several to
the same output.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import os
import threading
from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import Generic, TypeVar

from pipeline.model.solve import blas_threads

T = TypeVar("T")
R = TypeVar("R")

#: At most this many fits at once: beyond it the GIL-held share of each fit (the Python
#: between numpy calls) stops more threads from gaining, and each running fit holds its
#: Jacobian in memory.
MAX_THREADS = 4

#: the pool of the open :func:`side_by_side` block and its threads
_POOL: list[tuple[cf.ThreadPoolExecutor, int]] = []
_LOCAL = threading.local()  # ``inside``: this thread runs one of the pool's fits


def cores() -> int:
    """Return how many calls :func:`ordered` runs at once here.

    1 outside a :func:`side_by_side` block, and inside one of its calls: a fit's own
    independent fits (its held-out folds) then run in turn.
    """
    if not _POOL or getattr(_LOCAL, "inside", False):
        return 1
    return _POOL[0][1]


def free_cores() -> int:
    """Return the cores this process may use.

    Its BLAS's limit, the CPUs it may run on, at most :data:`MAX_THREADS`.
    """
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cpus = os.cpu_count() or 1
    return max(1, min(blas_threads() or cpus, cpus, MAX_THREADS))


@contextlib.contextmanager
def side_by_side(threads: int | None = None) -> Iterator[int]:
    """Run the :func:`ordered` maps of the block on ``threads`` threads; yield the number.

    Default :func:`free_cores`. A block inside another keeps the outer one's threads.
    """
    if _POOL:
        yield cores()
        return
    n = free_cores() if threads is None else max(1, int(threads))
    if n == 1:
        yield 1
        return
    pool = cf.ThreadPoolExecutor(max_workers=n, thread_name_prefix="magalign-fit")
    _POOL.append((pool, n))
    try:
        yield n
    finally:
        _POOL.clear()
        pool.shutdown(wait=True, cancel_futures=True)  # an interrupt: only what runs ends


def _inside(fn: Callable[[T], R], item: T) -> R:
    _LOCAL.inside = True
    try:
        return fn(item)
    finally:
        _LOCAL.inside = False


def ordered(fn: Callable[[T], R], items: Iterable[T],
            each: Callable[[int], None] | None = None) -> list[R]:
    """``[fn(x) for x in items]``, the calls side by side when :func:`cores` allows.

    ``each(k)``: called in the calling thread once the calls of items ``0..k`` have ended,
    in order (a progress display, which belongs to that thread). Every call runs to its
    end; the first exception in the items' order is raised then.
    """
    items = list(items)
    if cores() == 1 or len(items) < 2:
        out = []
        for k, x in enumerate(items):
            out.append(fn(x))
            if each is not None:
                each(k)
        return out
    futures = [_POOL[0][0].submit(_inside, fn, x) for x in items]
    for k, f in enumerate(futures):
        f.exception()  # waits for it, raising nothing
        if each is not None:
            each(k)
    return [f.result() for f in futures]


def call(job: Callable[[], R]) -> R:
    """``job()``: for :func:`ordered` over prepared calls (``functools.partial``)."""
    return job()


class Ahead(Generic[T, R]):
    """``fn`` of items asked for in turn, the next ones computed beside the one asked for.

    For a loop that takes ``fn(items[n])`` one after another and may change what ``fn``
    reads after any of them (the backward step drops a term, a relocation moves the model):
    :meth:`get` computes ``items[n:n + cores()]`` at once, and :meth:`forget` drops what was
    computed from the state that changed. On one thread nothing is computed ahead.
    """

    def __init__(self, fn: Callable[[T], R]):
        self.fn = fn
        self._got: dict[T, R] = {}

    def get(self, items: Sequence[T], n: int) -> R:
        """Return ``fn(items[n])``, with the next items' calls beside it when missing."""
        if items[n] not in self._got:
            batch = items[n:n + cores()]
            self._got = dict(zip(batch, ordered(self.fn, batch), strict=True))
        return self._got[items[n]]

    def forget(self) -> None:
        """Drop the calls computed so far: what ``fn`` reads has changed."""
        self._got = {}


class PerThread(threading.local, Generic[T]):
    """``value``: one of its own in each thread, made by ``factory`` on first use there.

    For what a fit keeps between its evaluations (the last forward pass, the attitude at
    the shifted times): fits side by side would otherwise evict each other's entries.
    """

    def __init__(self, factory: Callable[[], T]):
        self.value: T = factory()
