"""Anchored sensing times of a sample-and-hold magnetometer (``SampleHold.t_anchored_ns``).

The lab magnetometer's 285.714 Hz messages repeat a conversion in runs of 1 or 3 messages. The
synthetic sensor here converts at 101 Hz and inserts a midpoint between each pair of raw
conversions; a raw conversion that falls near a message is held over three messages centred on
it, the conversions in between one message each. The anchor rule of
:func:`pipeline.model.sample_hold.anchored_times_ns` must recover the sensing instants: exactly
when the sensor's timing is locked to the read-out (the timing the rule assumes), to a fraction
of a millisecond RMS when it runs free on a regular 202 Hz grid. A plain sample-and-hold (runs of
1 and 2) must be left at its first-copy stamps.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray

from pipeline.model.sample_hold import (
    MAX_HOLD_RUN,
    anchored_times_ns,
    detect_sample_hold,
)

I64 = NDArray[np.int64]
F64 = NDArray[np.float64]

#: message period of the lab magnetometer, ns (285.714 Hz)
MSG_NS = 3_500_000
#: raw conversion rate, Hz; a midpoint is inserted between each pair
RAW_HZ = 101.0
#: spacing of the conversions (raw and inserted), ns
CONV_NS = 1e9 / (2 * RAW_HZ)
#: constant lag of the stamps behind the sensing instants, ns (the time offset's to fit)
LAG_NS = 15_000_000
T_START_NS = 1_700_000_000_000_000_000


def midpoint_sensor(n_conv: int, locked: bool = False) -> tuple[I64, I64, F64]:
    """Messages of a 101 Hz sensor with midpoints inserted, read out every 3.5 ms.

    The anchors are raw conversions (even index) held over three messages, the middle one
    the message closest to ``instant + LAG_NS``; between two anchors each conversion takes one
    message, so the next anchor is 4 or 6 conversions on (6 or 8 messages), whichever keeps
    its middle message closest to its instant (as on the lab recordings: anchors 4 or 6
    conversions apart, never 2 runs of 2).

    Parameters
    ----------
    n_conv : int
        Conversions to draw (the recording ends on the last anchor before it).
    locked : bool
        False: a free-running sensor, conversions every 1 / 202 s exactly; an anchor's middle
        message is then up to about 1.5 ms off its instant (the 3.5 ms message grid).
        True: the sensor's conversions are timed by the read-out clock: each anchor sensed
        exactly at its middle message (less the lag), the conversions between two anchors
        evenly spaced (101 Hz on average): the timing the anchor rule assumes.

    Returns
    -------
    t_ns : ndarray of int64, shape (N,)
        Message stamps, ns.
    conv : ndarray of int64, shape (N,)
        Conversion carried by each message.
    instant_ns : ndarray of float, shape (K,)
        True sensing instant of each conversion, ns after ``T_START_NS`` (float ns since the
        epoch would round to 256 ns); ``K <= n_conv``: up to the last anchor.

    """
    instant = MSG_NS - LAG_NS + np.arange(n_conv, dtype=np.float64) * CONV_NS
    lengths = [3]
    anchors, middles = [0], [1]  # anchor conversions and their middle messages
    k, err = 0, 0.0  # last anchor; its middle message's stamp minus (instant + lag), ns
    gaps = np.array([4, 6])
    while True:
        errs = err + (gaps + 2) * MSG_NS - gaps * CONV_NS
        g = int(gaps[np.argmin(np.abs(errs))])
        if k + g >= n_conv:
            break
        lengths += [1] * (g - 1) + [3]
        k, err = k + g, float(errs[np.argmin(np.abs(errs))])
        anchors.append(k)
        middles.append(middles[-1] + g + 2)
    # the recording ends on an anchor (after the last one the rule has nothing to go by)
    conv = np.repeat(np.arange(k + 1, dtype=np.int64), lengths)
    t_ns = T_START_NS + np.arange(len(conv), dtype=np.int64) * MSG_NS
    if locked:
        at = np.asarray(middles, dtype=float) * MSG_NS - LAG_NS
        locked_ns = np.interp(np.arange(k + 1.0), np.asarray(anchors, float), at)
        return t_ns, conv, np.asarray(locked_ns, dtype=np.float64)
    return t_ns, conv, instant[:k + 1]


def field_nT(t_s: F64) -> F64:
    """A field turning with the platform (about 1 rad/s), nT, (N, 3): every conversion new."""
    return 4e4 * np.stack([np.cos(1.3 * t_s), np.sin(0.9 * t_s), 0.5 + 0.1 * np.sin(3 * t_s)],
                          axis=1)


def _first(conv: I64) -> NDArray[np.bool_]:
    return np.r_[True, conv[1:] != conv[:-1]]


def test_pattern_is_that_of_the_lab_sensor():
    _, conv, _ = midpoint_sensor(20_000)
    runs = np.bincount(np.bincount(conv))
    assert runs[2] == 0 and runs[1] > 0 and runs[3] > 0  # runs of 1 and 3, never 2
    rep = 1 - len(np.unique(conv)) / len(conv)
    assert rep == pytest.approx(0.29, abs=0.01)  # 29 % repeats, as the lab recordings


def _first_copy_ns(t_ns: I64, first: NDArray[np.bool_]) -> I64:
    return t_ns[np.maximum.accumulate(np.where(first, np.arange(len(t_ns)), 0))]


def _rms(x: F64) -> float:
    return float(np.sqrt(np.mean(x**2)))


def test_anchored_times_recover_the_sensing_instants_noise_free():
    """Read-out-locked sensor (the timing the rule assumes): recovered to the nanosecond."""
    t_ns, conv, instant = midpoint_sensor(20_000, locked=True)
    y = field_nT(instant * 1e-9)[conv]
    sh = detect_sample_hold(t_ns, y)
    assert sh is not None
    assert sh.native_rate_hz == pytest.approx(2 * RAW_HZ, rel=0.01)
    assert np.array_equal(sh.t_anchored_ns, anchored_times_ns(t_ns, sh.first))
    err_ms = (sh.t_anchored_ns - T_START_NS - instant[conv]) * 1e-6
    assert np.allclose(err_ms, LAG_NS * 1e-6, rtol=0, atol=1e-6)  # the lag alone, 1 ns
    # the first copy's stamp, the fallback the anchors replace, errs by milliseconds
    first_ms = (_first_copy_ns(t_ns, sh.first) - T_START_NS - instant[conv]) * 1e-6
    assert _rms(first_ms - np.median(first_ms)) > 1.5


def test_anchored_times_free_running_sensor():
    """A sensor converting exactly every 1 / 202 s: the anchors' middle messages are off their
    instants by up to about 1.5 ms (the 3.5 ms message grid); the rule still recovers the
    instants to well under a millisecond RMS, three times closer than the first copies'
    stamps."""
    t_ns, conv, instant = midpoint_sensor(20_000)
    y = field_nT(instant * 1e-9)[conv]
    sh = detect_sample_hold(t_ns, y)
    assert sh is not None
    err_ms = (sh.t_anchored_ns - T_START_NS - instant[conv]) * 1e-6
    assert np.median(err_ms) == pytest.approx(LAG_NS * 1e-6, abs=0.3)  # the lag stays constant
    err_ms -= np.median(err_ms)
    assert np.max(np.abs(err_ms)) < 1.5  # ms
    assert _rms(err_ms) < 0.75  # ms
    first_ms = (_first_copy_ns(t_ns, sh.first) - T_START_NS - instant[conv]) * 1e-6
    assert _rms(first_ms - np.median(first_ms)) > 3.0 * _rms(err_ms)


def test_anchored_times_with_stamp_jitter_and_sensor_noise():
    """Stamps jittered by 50 us RMS and readings noisy (100 nT): still a fraction of a ms."""
    rng = np.random.default_rng(7)
    t_ns, conv, instant = midpoint_sensor(20_000, locked=True)
    t_ns = t_ns + np.round(rng.normal(0.0, 50_000.0, len(t_ns))).astype(np.int64)
    y = field_nT(instant * 1e-9) + rng.normal(0.0, 100.0, (len(instant), 3))
    sh = detect_sample_hold(t_ns, y[conv])
    assert sh is not None
    err_ms = (sh.t_anchored_ns - T_START_NS - instant[conv]) * 1e-6 - LAG_NS * 1e-6
    assert np.max(np.abs(err_ms)) < 0.3  # ms
    assert _rms(err_ms) < 0.06  # ms: below the stamps' own jitter


def test_plain_sample_and_hold_keeps_the_first_copy_stamps():
    """Regular 202 Hz conversions read at 285.714 Hz: runs of 1 and 2, no anchors."""
    n = 20_000
    t_msg = T_START_NS + np.arange(n, dtype=np.int64) * MSG_NS
    t_conv = T_START_NS + np.arange(int(n * MSG_NS / CONV_NS) + 5) * CONV_NS
    k = np.searchsorted(t_conv, t_msg, side="right") - 1  # latest conversion at each read
    y = field_nT((t_conv - T_START_NS) * 1e-9)[k]
    sh = detect_sample_hold(t_msg, y)
    assert sh is not None
    assert set(np.unique(np.bincount(k - k[0]))) <= {1, 2}
    assert np.array_equal(sh.t_anchored_ns, _first_copy_ns(t_msg, sh.first))


def test_edges():
    t = T_START_NS + np.arange(12, dtype=np.int64) * MSG_NS
    # no messages; every message a new conversion (no runs at all)
    assert len(anchored_times_ns(t[:0], np.zeros(0, bool))) == 0
    assert np.array_equal(anchored_times_ns(t, np.ones(12, bool)), t)
    # a single anchor: it sits at its middle message, the rest at their centres (= stamps)
    lengths = [1, 1, 3, 1, 1, 1, 1, 1, 2]
    first = _first(np.repeat(np.arange(len(lengths)), lengths))
    out = anchored_times_ns(t, first)
    assert np.array_equal(out[:5], np.r_[t[:2], [t[3]] * 3])
    assert np.array_equal(out[5:10], t[5:10])
    assert np.array_equal(out[10:], [t[10] + MSG_NS // 2] * 2)  # a 2-run outside anchors
    # the first message always starts a run
    first[0] = False
    assert np.array_equal(anchored_times_ns(t, first), out)


def test_still_run_is_no_anchor_and_splits_the_rule():
    long = MAX_HOLD_RUN + 1
    lengths = [3, 1, 1, long, 1, 1, 3]  # anchors on both sides of a still reading
    conv = np.repeat(np.arange(len(lengths)), lengths)
    t = T_START_NS + np.arange(len(conv), dtype=np.int64) * MSG_NS
    out = anchored_times_ns(t, _first(conv))
    start = np.r_[0, np.cumsum(lengths)[:-1]]
    per_run = out[start]
    assert per_run[0] == t[1] and per_run[-1] == t[start[-1] + 1]  # anchors at the middle
    assert per_run[3] == t[start[3]]  # the still run: its first copy's stamp
    # not interpolated across it: the single conversions keep their own stamps
    assert np.array_equal(per_run[[1, 2, 4, 5]], t[start[[1, 2, 4, 5]]])
    # a still reading alone is no anchor: nothing changes
    lengths = [1, 2, long, 1, 2]
    conv = np.repeat(np.arange(len(lengths)), lengths)
    t = t[:len(conv)]
    first = _first(conv)
    assert np.array_equal(anchored_times_ns(t, first), _first_copy_ns(t, first))


def test_explanation_names_the_handling():
    t_ns, conv, instant = midpoint_sensor(5_000)
    sh = detect_sample_hold(t_ns, field_nT(instant * 1e-9)[conv])
    assert sh is not None
    assert "middle message" in sh.explanation(handling="anchored")
    assert "first copy" in sh.explanation(restamped=False)
    assert sh.explanation(restamped=False) == sh.explanation(handling="first_stamp")
    assert "native grid" in sh.explanation()


@st.composite
def run_patterns(draw: st.DrawFn) -> tuple[list[int], float]:
    """Run lengths of the lab kind (1 and 3) or of a plain hold (1 and 2), with the odd still
    reading, and the stamp jitter (fraction of a message period)."""
    short = draw(st.sampled_from([(1, 3), (1, 2)]))
    lengths = draw(st.lists(st.one_of(st.sampled_from(short).map(int),
                                      st.integers(MAX_HOLD_RUN + 1, 3 * MAX_HOLD_RUN)),
                            min_size=1, max_size=80)
                   .filter(lambda xs: any(x <= MAX_HOLD_RUN for x in xs)))
    jitter = draw(st.sampled_from([0.0, 0.02, 0.2]))
    return lengths, jitter


@settings(max_examples=200, deadline=None)
@given(run_patterns(), st.integers(0, 2**32 - 1))
def test_anchored_times_property(pattern: tuple[list[int], float], seed: int):
    lengths, jitter = pattern
    conv = np.repeat(np.arange(len(lengths)), lengths)
    rng = np.random.default_rng(seed)
    j_ns = jitter * MSG_NS
    # jitter below half a message period keeps the stamps sorted
    t = (T_START_NS + np.arange(len(conv), dtype=np.int64) * MSG_NS
         + np.round(rng.uniform(-j_ns, j_ns, len(conv))).astype(np.int64))
    first = _first(conv)
    out = anchored_times_ns(t, first)
    assert out.dtype == np.int64 and out.shape == t.shape
    assert np.all(np.diff(out) >= 0)  # non-decreasing
    assert np.all(out[~first] == out[np.flatnonzero(~first) - 1])  # equal within a run
    # within one native period (mean spacing of the held conversions) of the stamps, up to
    # the jitter of the stamps involved (a centre, two anchors, the message's own)
    size = np.asarray(lengths)[conv]
    held = size <= MAX_HOLD_RUN
    native_ns = MSG_NS * held.sum() / (np.asarray(lengths) <= MAX_HOLD_RUN).sum()
    assert np.all(np.abs(out - t)[held] <= native_ns + 2 * j_ns + 1)
    # a still reading keeps its first copy's stamp
    start = np.flatnonzero(first)
    assert np.array_equal(out[start][np.asarray(lengths) > MAX_HOLD_RUN],
                          t[start][np.asarray(lengths) > MAX_HOLD_RUN])
    if 3 not in lengths:  # no anchor: the first copies' stamps
        assert np.array_equal(out, t[start][conv])
