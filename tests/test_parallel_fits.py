"""Independent fits side by side (pipeline.model.parallel): the same answer on any number of
threads, and the maps they run in keep their items' order and errors."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from _diag_sim import lissajous_m, make_data

from pipeline.core.vocabulary import EffectKind as K
from pipeline.model import parallel
from pipeline.model.effects.soft_iron import SOFT_BASIS
from stages.diagnose.model import Term
from stages.diagnose.result import DiagnoseConfig
from stages.diagnose.search import diagnose_data


def _numbers(x, out: list[float]) -> list[float]:
    """Every number of a nested JSON-like value, in order."""
    if isinstance(x, dict):
        for k in sorted(x):
            _numbers(x[k], out)
    elif isinstance(x, list | tuple):
        for v in x:
            _numbers(v, out)
    elif isinstance(x, bool | str) or x is None:
        pass
    else:
        out.append(float(x))
    return out


def test_a_diagnosis_on_two_threads_is_the_one_on_one():
    """A search of several rounds (a lag, a gradient along a path, held-out folds, refits of
    several candidates, the backward step): the same findings, values and evidence."""
    G = np.array([[2000.0, 500.0, 0.0], [500.0, -1200.0, 300.0], [0.0, 300.0, -800.0]])
    g, *_ = np.linalg.lstsq(SOFT_BASIS.reshape(5, 9).T, G.ravel(), rcond=None)
    data, _ = make_data((Term(K.TIME_OFFSET), Term(K.FIELD_GRADIENT)),
                        (np.array([0.012]), g), noise_nT=20.0, seed=21, duration_s=40.0,
                        positions=lissajous_m)
    runs = []
    for threads in (1, 2):
        with parallel.side_by_side(threads) as n:
            assert n == threads and parallel.cores() == threads
            diag, res = diagnose_data(data, cfg=DiagnoseConfig())
        runs.append((diag, res))
    (d1, r1), (d2, r2) = runs
    assert {"time_offset", "field_gradient"} <= d1.effects, d1.table()
    assert d1.effects == d2.effects
    assert [f.effect for f in d1.findings] == [f.effect for f in d2.findings]
    a, b = _numbers(d1.to_dict(), []), _numbers(d2.to_dict(), [])
    assert len(a) == len(b)
    np.testing.assert_allclose(b, a, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(r2.state.flat_values(), r1.state.flat_values(), rtol=1e-9,
                               atol=1e-12)


def test_ordered_keeps_order_runs_every_call_and_raises_the_first_error():
    seen: list[int] = []
    lock = threading.Lock()

    def f(x: int) -> int:
        with lock:
            seen.append(x)
        if x in (3, 5):
            raise ValueError(f"item {x}")
        return x * x

    with parallel.side_by_side(2):
        assert parallel.ordered(lambda x: x + 1, range(6)) == [1, 2, 3, 4, 5, 6]
        with pytest.raises(ValueError, match="item 3"):
            parallel.ordered(f, range(8))
    assert sorted(seen) == list(range(8))


def test_a_call_inside_runs_its_own_maps_in_turn_and_blocks_do_not_nest():
    assert parallel.cores() == 1  # outside a block
    with parallel.side_by_side(2):
        inner = parallel.ordered(lambda _: parallel.cores(), range(2))
        assert inner == [1, 1]
        with parallel.side_by_side(3) as n:
            assert n == 2  # the outer block's
        assert parallel.cores() == 2
    assert parallel.cores() == 1
    with parallel.side_by_side(1) as n:
        assert n == 1 and parallel.ordered(lambda x: -x, [1, 2]) == [-1, -2]


def test_free_cores_follow_the_blas_limit_of_the_process():
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        assert parallel.free_cores() == 1
    assert 1 <= parallel.free_cores() <= parallel.MAX_THREADS


def test_per_thread_values_are_their_own():
    box: parallel.PerThread[list[int]] = parallel.PerThread(list)
    box.value.append(1)
    other: list[list[int]] = []
    th = threading.Thread(target=lambda: other.append(box.value))
    th.start()
    th.join()
    assert box.value == [1] and other == [[]]


def test_each_is_told_in_order_on_the_calling_thread():
    told: list[tuple[int, str]] = []

    def each(k: int) -> None:
        told.append((k, threading.current_thread().name))

    me = threading.current_thread().name
    for threads in (1, 2):
        told.clear()
        with parallel.side_by_side(threads):
            parallel.ordered(lambda x: x, range(5), each)
        assert told == [(k, me) for k in range(5)]


def test_ahead_computes_the_next_ones_beside_and_forgets_on_change():
    calls: list[tuple[int, int]] = []
    state = {"v": 0}
    lock = threading.Lock()

    def fn(k: int) -> int:
        with lock:
            calls.append((k, state["v"]))
        return 10 * state["v"] + k

    items = [0, 1, 2, 3]
    for threads, first in ((1, [(0, 0)]), (2, [(0, 0), (1, 0)])):
        calls.clear()
        state["v"] = 0
        with parallel.side_by_side(threads):
            ahead = parallel.Ahead(fn)
            assert ahead.get(items, 0) == 0
            assert sorted(calls) == first  # nothing beyond what the threads take at once
            state["v"] = 1  # what fn reads changed
            ahead.forget()
            before = len(calls)
            assert [ahead.get(items, n) for n in (1, 2, 3)] == [11, 12, 13]
        assert sorted(calls[before:]) == [(1, 1), (2, 1), (3, 1)]  # each once, from the new
