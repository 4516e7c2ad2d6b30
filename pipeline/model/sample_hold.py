"""Sample-and-hold timing: a sensor that samples slower than its messages.

More in docs/modules.md, ``pipeline.model.sample_hold``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import NDArray

I64 = NDArray[np.int64]
F64 = NDArray[np.float64]
B8 = NDArray[np.bool_]

#: Below this fraction of repeats among samples whose neighbours differ, nothing is reported.
MIN_MOVING_REPEAT_FRACTION = 0.02
#: Runs of identical messages longer than this are not sample-and-hold evidence.
MAX_HOLD_RUN = 8
#: Re-stamping follows the sensor clock over windows of this many conversions (about 0.2 s).
RESTAMP_WINDOW = 41
#: A run of at least this many identical messages (and at most :data:`MAX_HOLD_RUN`) is an
#: anchor of :func:`anchored_times_ns`: a conversion sensed at its centre stamp.
ANCHOR_RUN = 3

#: How the diagnosis times the conversions: the first copy's stamp, the native grid
#: (:attr:`SampleHold.t_sensed_ns`) or the anchor rule (:attr:`SampleHold.t_anchored_ns`).
Handling = Literal["first_stamp", "native_grid", "anchored"]


#: How a calibration's sample-and-hold warning begins (:meth:`SampleHold.warning`).
WARNING_PREFIX = "sample-and-hold:"


@dataclass(frozen=True)
class SampleHold:
    """Sample-and-hold found in a magnetometer series.

    Attributes
    ----------
    native_rate_hz : float
        Distinct conversions per second.
    message_rate_hz : float
        Messages per second (median stamp spacing).
    repeated_fraction : float
        Fraction of messages that repeat the previous one exactly.
    first : ndarray of bool, shape (N,)
        True for the first message of each run (the ones that carry a new conversion).
    t_sensed_ns : ndarray of int64, shape (N,)
        Estimated sensing time of every message's conversion (the same for a whole run), on
        the native grid, ns since the Unix epoch; its constant lag behind the true sensing
        time is part of the time offset.
    lag_rms_s : float
        RMS of ``stamp - t_sensed`` over all messages, s: the timing error that using the
        stamps would leave.
    t_anchored_ns : ndarray of int64, shape (N,)
        Sensing time of every message's conversion by the anchor rule
        (:func:`anchored_times_ns`), ns since the Unix epoch, the same for a whole run; equal
        to the first copy's stamp when no run has :data:`ANCHOR_RUN` to :data:`MAX_HOLD_RUN`
        messages. As for ``t_sensed_ns``, a constant lag behind the true sensing time is the
        time offset's to fit.

    """

    native_rate_hz: float
    message_rate_hz: float
    repeated_fraction: float
    first: B8
    t_sensed_ns: I64
    lag_rms_s: float
    t_anchored_ns: I64

    def params(self) -> dict[str, float]:
        """Return the CONVENTIONS params of the ``sample_hold`` effect."""
        return {
            "native_rate_hz": float(self.native_rate_hz),
            "repeated_fraction": float(self.repeated_fraction),
        }

    def warning(self, left_out: bool) -> str:
        """Return the calibration's warning: the repeats' share and what the fit did with them.

        ``left_out``: the fit left the repeats out (the estimate always; the diagnosis' final
        model only with its ``sample_hold`` finding), else it fitted every message at its own
        stamp because neither handling predicted held-out data better.
        """
        done = ("the repeats were left out" if left_out else
                "every message was fitted at its own stamp: leaving the repeats out, or "
                "timing them at the sensor's rate, did not predict held-out data better")
        return (f"{WARNING_PREFIX} {100 * self.repeated_fraction:.0f} % of the magnetometer "
                f"messages repeat the previous one (native rate {self.native_rate_hz:.1f} Hz, "
                f"messages {self.message_rate_hz:.1f} Hz); {done}")

    def explanation(self, restamped: bool = True, *, handling: Handling | None = None) -> str:
        """One paragraph for a person on the sensor and on how its conversions were timed.

        Parameters
        ----------
        restamped : bool
            The conversions were re-stamped on the native grid (``handling="native_grid"``);
            False: each message was taken at its first copy's stamp (``"first_stamp"``).
        handling : {"first_stamp", "native_grid", "anchored"}, optional
            The handling the diagnosis chose; overrides ``restamped`` when given.

        """
        if handling is None:
            handling = "native_grid" if restamped else "first_stamp"
        how = {
            "native_grid": "the repeats are left out of the fit and the remaining conversions "
                           "are re-stamped on the native grid",
            "first_stamp": "the repeats are left out of the fit and every message is taken at "
                           "the stamp of the first copy of its conversion (re-stamping the "
                           "conversions did not predict held-out data better)",
            "anchored": "the repeats are left out of the fit and every conversion is taken at "
                        "its anchored sensing time: a reading held over three or more messages "
                        "was sensed at its middle message, and the conversions between two "
                        "such readings are evenly spaced between their middles (the sensor "
                        "appears to convert at half the rate and insert a midpoint between "
                        "each pair); this predicted held-out data better than the first "
                        "copy's stamp or a regular native grid",
        }[handling]
        return (
            f"The magnetometer converts at about {self.native_rate_hz:.1f} Hz but its messages "
            f"arrive at {self.message_rate_hz:.1f} Hz: {100 * self.repeated_fraction:.0f} % of "
            "the messages repeat the previous reading, and each repeat is stamped up to one "
            f"native period ({1e3 / self.native_rate_hz:.1f} ms) after the field was sensed. "
            f"The stamps err by {1e3 * self.lag_rms_s:.1f} ms RMS; {how}."
        )


def repeated(mag: F64) -> B8:
    """Messages that repeat the previous one exactly in all three components, (N,)."""
    m = np.asarray(mag)
    out = np.zeros(len(m), bool)
    if len(m) > 1:
        out[1:] = np.all(m[1:] == m[:-1], axis=1)
    return out


def _moving(mag: F64, rep: B8) -> B8:
    """Messages inside runs whose distinct neighbours differ well beyond the typical change."""
    m = np.asarray(mag, float)
    idx = np.flatnonzero(~rep)
    if len(idx) < 3:
        return np.zeros(len(m), bool)
    d = np.linalg.norm(np.diff(m[idx], axis=0), axis=1)  # change between distinct conversions
    pos = d[d > 0]
    if pos.size == 0:
        return np.zeros(len(m), bool)
    # "Moving": the conversion before and after this run differ by more than a small floor
    # (a quantisation step); repeated noisy conversions differ almost always.
    floor = max(float(np.min(pos)), 1e-12)
    run_id = np.cumsum(~rep) - 1
    change_after = np.r_[d, 0.0]  # change from conversion k to k + 1
    return change_after[run_id] > floor


def detect_sample_hold(t_ns: I64, mag_nT: F64) -> SampleHold | None:
    """Find sample-and-hold in a magnetometer series, or return None when there is none.

    Parameters
    ----------
    t_ns : ndarray of int64, shape (N,)
        Message stamps, sorted.
    mag_nT : ndarray, shape (N, 3)
        Readings, any unit (only equality matters).

    Returns
    -------
    SampleHold or None
        None when fewer than :data:`MIN_MOVING_REPEAT_FRACTION` of the moving messages repeat.

    """
    t = np.asarray(t_ns, np.int64)
    n = len(t)
    if n < 10:
        return None
    rep = repeated(mag_nT)
    mov = _moving(mag_nT, rep)
    # a sensor that holds its conversion for a few messages makes short runs; a long run of
    # identical readings is a still (or noise-free, or stuck) reading, not sample-and-hold
    run_id = np.cumsum(~rep) - 1
    mov &= (np.bincount(run_id) <= MAX_HOLD_RUN)[run_id]
    n_mov = int(np.sum(mov))
    if n_mov < 10 or np.sum(rep & mov) < MIN_MOVING_REPEAT_FRACTION * n_mov:
        return None
    first = ~rep
    idx = np.flatnonzero(first)
    span_s = (t[-1] - t[0]) * 1e-9
    dt = np.diff(t)
    msg_rate = 1e9 / float(np.median(dt[dt > 0])) if np.any(dt > 0) else float("nan")
    t_first = t[idx]
    t_sensed_first = t_first - _local_lag_ns(t_first)
    run_id = np.cumsum(first) - 1
    t_sensed = t_sensed_first[run_id]
    lag = (t - t_sensed) * 1e-9
    lag = lag - np.min(lag)
    native = (len(idx) - 1) / span_s if span_s > 0 else float("nan")
    return SampleHold(
        native_rate_hz=float(native),
        message_rate_hz=float(msg_rate),
        repeated_fraction=float(np.mean(rep)),
        first=first,
        t_sensed_ns=t_sensed,
        lag_rms_s=float(np.sqrt(np.mean(lag**2))),
        t_anchored_ns=anchored_times_ns(t, first),
    )


def anchored_times_ns(t_ns: I64, first: B8) -> I64:
    """Sensing time of every message's conversion by the anchor rule, ns, (N,).

    The rule (docs/modules.md: a sensor converting at half the rate with a midpoint inserted
    between each pair, read out faster than it converts):

    1. The messages split into runs of identical readings (``first`` marks each run's first
       message); run ``k`` is one conversion, with centre stamp
       ``c_k = (s_first + s_last) / 2``.
    2. Anchors are the runs of :data:`ANCHOR_RUN` to :data:`MAX_HOLD_RUN` messages: a reading
       held over three messages was sensed at its middle one. Between consecutive anchors
       ``a < a'`` the conversions are evenly spaced,
       ``t_k = c_a + (k - a) (c_a' - c_a) / (a' - a)``; before the first anchor and after the
       last, ``t_k = c_k``.
    3. Every message of a run takes its conversion's ``t_k``.

    Runs longer than :data:`MAX_HOLD_RUN` are still (or stuck) readings, not one held
    conversion: they count an unknown number of conversions, so they are no anchors, take
    their first copy's stamp, and the rule is applied separately on either side of them.
    Without any anchor every message takes its first copy's stamp (a plain sample-and-hold,
    runs of 1 and 2, is left as it is).

    Parameters
    ----------
    t_ns : ndarray of int64, shape (N,)
        Message stamps, ns since the Unix epoch, sorted.
    first : ndarray of bool, shape (N,)
        True for the first message of each run; the first message always starts one.

    Returns
    -------
    ndarray of int64, shape (N,)
        Sensing times, ns since the Unix epoch, non-decreasing and equal within a run; a
        constant lag behind the true sensing time is left to the time offset.

    """
    t = np.asarray(t_ns, dtype=np.int64)
    n = len(t)
    if n == 0:
        return t.copy()
    f = np.asarray(first, dtype=bool).copy()
    f[0] = True  # a series starts a run whatever came before it
    start = np.flatnonzero(f)
    length = np.diff(np.r_[start, n])
    run_of = np.cumsum(f) - 1  # run (conversion) index of every message
    still = length > MAX_HOLD_RUN
    anchor = (length >= ANCHOR_RUN) & ~still
    if not np.any(anchor):
        return t[start][run_of]
    # stamps relative to the first one (float ns: exact below 2**53 ns, about 104 days)
    rel = (t - t[0]).astype(np.float64)
    first_s, last_s = rel[start], rel[start + length - 1]
    sensed = np.where(still, first_s, 0.5 * (first_s + last_s))
    k = np.arange(len(start))
    prev = np.maximum.accumulate(np.where(anchor, k, -1))  # last anchor at or before k
    nxt = np.minimum.accumulate(np.where(anchor, k, len(k))[::-1])[::-1]  # first at or after
    # a still run between two anchors hides how many conversions lie between them
    segment = np.cumsum(still)
    inside = (prev >= 0) & (nxt < len(k)) & (prev < k) & (k < nxt)
    inside[inside] &= segment[prev[inside]] == segment[nxt[inside]]
    p, q = prev[inside], nxt[inside]
    sensed[inside] = sensed[p] + (k[inside] - p) * (sensed[q] - sensed[p]) / (q - p)
    return t[0] + np.round(sensed).astype(np.int64)[run_of]


def _local_lag_ns(t_first: I64) -> I64:
    """Lag of each conversion's stamp above the local native grid, ns, (K,); 0 off-grid.

    Detrended by the mean period, the stamps sit above the grid by a lag in ``[0, one message
    period)``. The sensor's own clock wanders (about 0.4 % over ten seconds on the real
    recordings), so the grid is followed locally: its height is the running minimum of the
    detrended stamps over :data:`RESTAMP_WINDOW` conversions, taken from both sides and
    averaged so that it stays centred.
    """
    k = np.arange(len(t_first), dtype=float)
    ts = (t_first - t_first[0]).astype(float)
    T = (ts[-1] - ts[0]) / max(k[-1], 1.0)
    r = ts - k * T
    w = min(RESTAMP_WINDOW, len(r))
    env = _running_min(r, w)
    lag = np.maximum(np.round(r - env), 0).astype(np.int64)
    # On a regular native grid the first copy of a conversion is at most one message period
    # late. Lags well beyond that mean the conversions are not on a regular grid (a sensor
    # that stalls now and then: runs of 1 and 3 messages, never 2, on the real recordings);
    # then the first copy's own stamp is the best estimate of the sensing time.
    dt = np.diff(t_first)
    msg_period = float(np.min(dt[dt > 0])) if np.any(dt > 0) else 0.0
    if len(lag) and float(np.percentile(lag, 95)) > 1.5 * msg_period:
        return np.zeros(len(t_first), np.int64)
    return lag


def _running_min(x: F64, w: int) -> F64:
    """Centred running minimum over ``w`` samples (shrinking at the ends), (N,)."""
    h = w // 2
    pad = np.concatenate([np.full(h, np.inf), x, np.full(w - 1 - h, np.inf)])
    return sliding_window_view(pad, w).min(axis=1)


def sensing_times_ns(t_ns: I64, mag: F64, handling: Handling) -> I64:
    """Sensing time of every message by the diagnosis' chosen ``handling``, ns, (N,).

    The times the restore evaluates the model at, so that every message is restored with the
    attitude of the moment its conversion was sensed (as the fit that chose the handling
    predicted it): ``first_stamp``, each run of identical messages at its first copy's
    stamp; ``native_grid``, the first copies re-stamped on the native grid
    (:func:`detect_sample_hold`'s ``t_sensed_ns``, the first stamps where the series shows
    no sample-and-hold); ``anchored``, :func:`anchored_times_ns`.

    Parameters
    ----------
    t_ns : ndarray of int64, shape (N,)
        Message stamps, sorted.
    mag : ndarray, shape (N, 3)
        Readings (only equality matters).
    handling : {"first_stamp", "native_grid", "anchored"}
        The timing the diagnosis kept (:func:`handling_of`).

    """
    t = np.asarray(t_ns, dtype=np.int64)
    if len(t) == 0:
        return t.copy()
    first = ~repeated(mag)
    first[0] = True
    if handling == "anchored":
        return anchored_times_ns(t, first)
    if handling == "native_grid":
        sh = detect_sample_hold(t, mag)
        if sh is not None:
            return np.asarray(sh.t_sensed_ns, dtype=np.int64)
    return t[np.flatnonzero(first)][np.cumsum(first) - 1]


def handling_of(effects: dict | None) -> Handling | None:
    """Return the sample-and-hold handling a calibration's ``effects`` carry, or None.

    The diagnosis stores it beside the finding's params (``effects["sample_hold"]``,
    key ``handling``) when timing the conversions predicted held-out data better.
    """
    p = (effects or {}).get("sample_hold")
    if isinstance(p, list):
        p = p[0] if p else None
    h = None if not isinstance(p, dict) else p.get("handling")
    return h if h in ("first_stamp", "native_grid", "anchored") else None
