"""Restore every magnetometer sample to ENU by inverting the fitted model, once per recording.

More in docs/modules.md, ``stages.restore``.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np

from pipeline.core.errors import InputError
from pipeline.core.geometry import quat_conj, quat_rotate
from pipeline.core.recording import Frame, PositionSeries, Recording, VectorSeries
from pipeline.model.attitude import AttitudeInterpolator
from pipeline.model.calibration import Calibration
from pipeline.model.forward import RATE_STEP_INTERVALS
from pipeline.model.forward import restore as model_restore
from pipeline.model.sample_hold import handling_of, sensing_times_ns


def _readonly(*arrays: np.ndarray) -> None:
    for a in arrays:
        a.setflags(write=False)


@dataclass(frozen=True)
class RestoreResult:
    """Every magnetometer sample of a recording, restored where possible (docs/modules.md).

    Attributes
    ----------
    t_ns : ndarray of int64, shape (N,)
        All magnetometer stamps.
    raw_mag_nT : ndarray, shape (N, 3)
        Measured magnetometer, mag frame.
    calibrated_mag_nT : ndarray, shape (N, 3)
        ``inv(D) @ (y - o - e)``, mag frame.
    q_enu_body : ndarray, shape (N, 4)
        Attitude at ``t - tau``; NaN where ``valid`` is false.
    enu_nT : ndarray, shape (N, 3)
        Restored field, ENU; NaN where ``valid`` is false.
    residual_nT : ndarray, shape (N, 3)
        Measured minus predicted by the FINAL model (every term of the calibration, diagnosed
        effects included), mag frame; NaN where invalid.
    valid : ndarray of bool, shape (N,)
        Samples with a usable attitude at ``t - tau``.
    q0_enu_body : ndarray, shape (N, 4)
        Attitude at the stamp itself (``tau = 0``) for the uncalibrated comparison.
    valid0 : ndarray of bool, shape (N,)
    B_enu_nT : ndarray, shape (3,)
        The calibration's background field.
    max_gap_s : float
        Attitude gap rule used.
    model_key : str
        What the result was computed from (:func:`model_key_of`).

    """

    t_ns: np.ndarray
    raw_mag_nT: np.ndarray
    calibrated_mag_nT: np.ndarray
    q_enu_body: np.ndarray
    enu_nT: np.ndarray
    residual_nT: np.ndarray
    valid: np.ndarray
    q0_enu_body: np.ndarray
    valid0: np.ndarray
    B_enu_nT: np.ndarray
    max_gap_s: float
    model_key: str = ""

    # ------------------------------------------------------------------ counts
    @property
    def n_total(self) -> int:
        """Every magnetometer sample of these rows."""
        return int(self.t_ns.shape[0])

    @property
    def used(self) -> np.ndarray:
        """Samples restored and compared (attitude at ``t - tau`` and at ``t``), (N,) bool."""
        return self.valid & self.valid0

    @property
    def n_used(self) -> int:
        """Samples restored and compared with the uncalibrated field."""
        return int(np.count_nonzero(self.used))

    @property
    def n_valid(self) -> int:
        """Samples restored (attitude at ``t - tau``)."""
        return int(np.count_nonzero(self.valid))

    @property
    def n_without_attitude(self) -> int:
        """Samples left out for want of an attitude at ``t - tau``."""
        return self.n_total - self.n_valid

    @property
    def n_without_attitude_at_stamp(self) -> int:
        """Samples restored (attitude at ``t - tau``) but without one at ``t`` itself."""
        return int(np.count_nonzero(self.valid & ~self.valid0))

    # ------------------------------------------------------------------ derived
    @property
    def series(self) -> VectorSeries:
        """The restored field of the valid samples: VectorSeries, frame ``enu``, nT."""
        return VectorSeries(self.t_ns[self.valid], self.enu_nT[self.valid], Frame.ENU, "nT")

    @property
    def residual_rms_nT(self) -> float:
        """RMS over every component of the final model's residual, valid samples, nT."""
        r = self.residual_nT[self.valid]
        return float(np.sqrt(np.mean(r * r))) if r.size else float("nan")

    def uncalibrated_enu_nT(self) -> np.ndarray:
        """Return ``C_enu_body(t) @ y_mag`` (attitude only, Li 2020 Figs. 5, 8 "before"), (N, 3).

        NaN without an attitude at the stamp. Computed on the first call and kept (the
        metrics, the rerun recording and the report's views all need it); read-only.
        """
        return self._uncalibrated_enu_nT

    @cached_property
    def _uncalibrated_enu_nT(self) -> np.ndarray:
        q0 = np.where(self.valid0[:, None], self.q0_enu_body, _IDENTITY_Q)
        unc = quat_rotate(q0, np.asarray(self.raw_mag_nT, dtype=float))
        unc[~self.valid0] = np.nan
        unc.flags.writeable = False
        return unc

    def q_or_identity(self) -> np.ndarray:
        """Return the attitude at ``t - tau``, identity where not valid, (N, 4)."""
        return np.where(self.valid[:, None], self.q_enu_body, _IDENTITY_Q)

    @classmethod
    def concat(cls, parts: list[RestoreResult]) -> RestoreResult:
        """Join results of consecutive rows (chunks)."""
        arrays: dict[str, Any] = {f: np.concatenate([getattr(p, f) for p in parts])
                                  for f in _ROW_FIELDS}
        return dataclasses.replace(parts[0], **arrays)

    def rows(self, sl: slice | np.ndarray, *, copy: bool = True) -> RestoreResult:
        """Return the result restricted to rows ``sl`` (a slice or index array).

        ``copy``: the arrays are copies (rows kept while the rest goes, as a long recording's
        sample for the figures: a view would keep the whole arrays alive); ``False``: views
        of a slice, for rows used at once.
        """
        arrays: dict[str, Any] = {f: (np.array if copy else np.asarray)(getattr(self, f)[sl])
                                  for f in _ROW_FIELDS}
        return dataclasses.replace(self, **arrays)


_IDENTITY_Q = np.array([0.0, 0.0, 0.0, 1.0])

#: the per-row arrays of a RestoreResult
_ROW_FIELDS = ("t_ns", "raw_mag_nT", "calibrated_mag_nT", "q_enu_body", "enu_nT",
               "residual_nT", "valid", "q0_enu_body", "valid0")


@dataclass(frozen=True)
class RestoreTotals:
    """Counts and residual sum of squares over every sample of a recording restored in chunks.

    Attributes
    ----------
    n_total, n_valid, n_used : int
        Every magnetometer sample; those with an attitude at ``t - tau``; those with one at
        ``t - tau`` and at ``t``.
    residual_sumsq_nT2 : float
        Sum over the valid samples and the three components of the squared residual, nT^2.

    """

    n_total: int = 0
    n_valid: int = 0
    n_used: int = 0
    residual_sumsq_nT2: float = 0.0

    def __add__(self, other: RestoreTotals) -> RestoreTotals:
        return RestoreTotals(self.n_total + other.n_total, self.n_valid + other.n_valid,
                             self.n_used + other.n_used,
                             self.residual_sumsq_nT2 + other.residual_sumsq_nT2)

    @classmethod
    def of(cls, rs: RestoreResult) -> RestoreTotals:
        """Return the totals of a (chunk's) restore result."""
        r = rs.residual_nT[rs.valid]
        return cls(int(rs.t_ns.shape[0]), int(np.count_nonzero(rs.valid)),
                   int(np.count_nonzero(rs.used)), float(np.sum(r * r)))

    @property
    def residual_rms_nT(self) -> float:
        """RMS over every component of the residual, nT."""
        return (float(np.sqrt(self.residual_sumsq_nT2 / (3 * self.n_valid))) if self.n_valid
                else float("nan"))




def model_key_of(cal: Calibration, max_gap_s: float | None) -> str:
    """Return the terms of ``cal`` the restore depends on, and the gap rule, as one string.

    Two calibrations with the same key restore a recording identically (the verdict, the
    sigmas, the checks and the warnings do not enter the model).
    """
    d = cal.to_dict()
    keys = ("R_body_mag", "B_enu_nT", "D", "offset_nT", "time_offset_s", "effects")
    return json.dumps({"model": {k: d[k] for k in keys}, "max_gap_s": max_gap_s},
                      sort_keys=True, default=str)


def restore_samples(
    recording: Recording, cal: Calibration, *, max_gap_s: float | None = None
) -> RestoreResult:
    """Restore every magnetometer sample and compute the final model's residual.

    Parameters
    ----------
    recording : Recording
        With ``attitude`` filled.
    cal : Calibration
        The fitted model (every term it carries is used).
    max_gap_s : float or None
        Longest attitude gap (s) bridged by interpolation; None: the automatic rule.

    Returns
    -------
    RestoreResult
        Read-only arrays.

    """
    if recording.attitude is None or len(recording.attitude) == 0:
        raise InputError(
            "the recording has no attitude to restore the magnetometer with",
            path=recording.path,
            hint="for a turntable recording put TurntableAttitude before Restore",
        )
    interp = AttitudeInterpolator.of(recording.attitude, max_gap_s=max_gap_s)
    t_ns = np.asarray(recording.mag.t_ns, dtype=np.int64)
    # windows in seconds count from the recording's first sample, which a long recording's
    # analysed windows do not hold (Recording.first_ns)
    return restore_rows(cal, t_ns, recording.mag.values, interp,
                        t0_ns=recording.origin_ns(), position=recording.position,
                        model_key=model_key_of(cal, max_gap_s))


def restore_rows(cal: Calibration, t_ns: np.ndarray, mag_nT: np.ndarray,
                 interp: AttitudeInterpolator, *, t0_ns: int, position: Any = None,
                 model_key: str = "", t_sensed_ns: np.ndarray | None = None) -> RestoreResult:
    """Restore the magnetometer rows ``t_ns``, ``mag_nT`` with the attitude of ``interp``.

    The one place a :class:`RestoreResult` is computed: :func:`restore_samples` calls it on
    a whole recording, :class:`ChunkedRestore` on each chunk of a long one (with an
    interpolator over the chunk's attitude and its neighbours, which gives the same
    attitude as one over the whole series).

    Parameters
    ----------
    cal : Calibration
        The fitted model (every term it carries is used).
    t_ns : ndarray of int64, shape (N,)
        Magnetometer stamps, sorted.
    mag_nT : ndarray, shape (N, 3)
        Readings, mag frame.
    interp : AttitudeInterpolator
        THE interpolator over the attitude around these rows.
    t0_ns : int
        First magnetometer stamp of the RECORDING (effect windows and drifts count from it).
    position : PositionSeries, optional
        Marker positions (the field gradient term).
    model_key : str
        :func:`model_key_of` the calibration.
    t_sensed_ns : ndarray of int64, shape (N,), optional
        When each row's conversion was sensed, where the calibration carries a
        sample-and-hold handling (:func:`pipeline.model.sample_hold.sensing_times_ns`);
        None: computed from these rows.

    """
    t_ns = np.asarray(t_ns, dtype=np.int64)
    y = np.array(mag_nT, dtype=float)
    model = cal.forward_model()
    if t_sensed_ns is None:
        handling = handling_of(cal.effects)
        t_sensed_ns = t_ns if handling is None else sensing_times_ns(t_ns, y, handling)
    # the model at the moment each conversion was sensed (sample_hold); the rows keep their
    # stamps
    rs = model_restore(model, y, np.asarray(t_sensed_ns, dtype=np.int64), interp,
                       t0_ns=t0_ns, position=position)
    # The arrays of rs and at0 are the model's own fresh results, referenced by nothing
    # else: kept as they are (read-only below), not copied (five copies of every sample's
    # rows were a tenth of a long recording's restore).
    if model.time_offset_s or not np.array_equal(t_sensed_ns, t_ns):
        at0 = interp.at(t_ns, 0.0)
        q0, valid0 = at0.q_enu_body, at0.valid
    else:  # the attitude at the stamp is the one just interpolated
        q0, valid0 = rs.q_enu_body, rs.valid
    out = RestoreResult(
        t_ns=t_ns, raw_mag_nT=y, calibrated_mag_nT=rs.calibrated_mag_nT,
        q_enu_body=rs.q_enu_body, enu_nT=rs.enu_nT, residual_nT=rs.residual_nT,
        valid=rs.valid,
        q0_enu_body=q0, valid0=valid0,
        B_enu_nT=np.array(cal.B_enu_nT, dtype=float), max_gap_s=interp.max_gap_s,
        model_key=model_key,
    )
    _readonly(out.raw_mag_nT, out.calibrated_mag_nT, out.q_enu_body, out.enu_nT,
              out.residual_nT, out.valid, out.q0_enu_body, out.valid0, out.B_enu_nT)
    return out


class ChunkedAttitude:
    """THE interpolator over a long recording's attitude, chunk by chunk.

    Feed the recording's chunks in time order (:meth:`add`); each call returns the
    magnetometer rows whose attitude is settled, with an interpolator over the attitude
    samples around them (:meth:`finish`: the rest). The attitude of a query at ``t`` comes
    from the cubic over its bracketing samples and their neighbours
    (pipeline/model/attitude.py, (A4)-(A5)), so a row is settled once the attitude two
    samples past its latest query has arrived, and the attitude samples kept from one chunk
    to the next are the two before the earliest waiting query. The interpolator's blend
    weight and gap rule are the recording's (given), not the chunk's: every chunk is
    interpolated as the whole series would be.

    Parameters
    ----------
    max_gap_s : float
        The recording's gap rule (s).
    cubic_weight : float
        The recording's ``lam`` of (A7).
    time_offset_s : float
        ``tau``: the rows are queried at ``t`` and at ``t - tau``.
    sensing_margin_s : float
        How far from its stamp a row's sensing time may lie (sample-and-hold handling): the
        queries are then at ``t_sensed - tau``.
    step_s : float or None
        The series' attitude spacing (s): every piece's interpolator takes it, and the
        pieces reach far enough for the eddy regressor's differences. Required for a
        calibration with ``eddy_current``.

    """

    def __init__(self, *, max_gap_s: float, cubic_weight: float, time_offset_s: float = 0.0,
                 sensing_margin_s: float = 0.0, step_s: float | None = None):
        self.max_gap_s = float(max_gap_s)
        self.cubic_weight = float(cubic_weight)
        self.step_s = step_s
        tau = float(time_offset_s)
        # the eddy regressor differences the attitude RATE_STEP_INTERVALS samples either
        # side of each query (pipeline.model.forward.rate_matrices)
        m = float(sensing_margin_s) + (0.0 if step_s is None
                                       else max(RATE_STEP_INTERVALS * step_s, 1e-3))
        # the queries are t and t - tau (a sensing time within m of t): the earliest and
        # latest of them, relative to t
        self._lo_ns = int(np.floor((min(0.0, -tau) - m) * 1e9)) - 1
        self._hi_ns = int(np.ceil((max(0.0, -tau) + m) * 1e9)) + 1
        self._att_t = np.zeros(0, np.int64)
        self._att_q = np.zeros((0, 4))
        self._mag_t = np.zeros(0, np.int64)
        self._mag_v = np.zeros((0, 3))

    def add(self, mag_t_ns: np.ndarray, mag_nT: np.ndarray, att_t_ns: np.ndarray | None,
            q_enu_body: np.ndarray | None, *, last: bool = False
            ) -> tuple[np.ndarray, np.ndarray, AttitudeInterpolator] | None:
        """Take one chunk; return ``(t_ns, mag_nT, interpolator)`` of the settled rows.

        ``last``: no chunk follows, every row is settled (a recording held whole is one
        chunk: its rows are interpolated at once, over the whole series).
        """
        if att_t_ns is not None and len(att_t_ns):
            self._att_t = np.concatenate([self._att_t, np.asarray(att_t_ns, np.int64)])
            self._att_q = np.concatenate([self._att_q, np.asarray(q_enu_body, float)])
            if np.any(np.diff(self._att_t[-len(att_t_ns) - 1:]) <= 0):
                o = np.argsort(self._att_t, kind="stable")
                self._att_t, self._att_q = self._att_t[o], self._att_q[o]
        self._mag_t = np.concatenate([self._mag_t, np.asarray(mag_t_ns, np.int64)])
        self._mag_v = np.concatenate([self._mag_v, np.asarray(mag_nT, float)])
        if np.any(np.diff(self._mag_t) < 0):  # a logger's stamps may straddle chunks
            o = np.argsort(self._mag_t, kind="stable")
            self._mag_t, self._mag_v = self._mag_t[o], self._mag_v[o]
        if last:
            return self.finish()
        if len(self._att_t) < 4:
            return None
        # settled: the latest query lies before the third-last attitude sample, whose
        # segment's tangents (A5) need nothing later
        ready = int(np.searchsorted(self._mag_t, self._att_t[-3] - self._hi_ns, "right"))
        return self._emit(ready)

    def finish(self) -> tuple[np.ndarray, np.ndarray, AttitudeInterpolator] | None:
        """Return the rows still waiting (the end of the recording)."""
        return self._emit(len(self._mag_t))

    def _emit(self, ready: int) -> tuple[np.ndarray, np.ndarray, AttitudeInterpolator] | None:
        if ready == 0:
            return None
        t, v = self._mag_t[:ready], self._mag_v[:ready]
        self._mag_t, self._mag_v = self._mag_t[ready:], self._mag_v[ready:]
        # attitude samples from two before the earliest query to two after the latest
        a = max(int(np.searchsorted(self._att_t, t[0] + self._lo_ns, "right")) - 2, 0)
        b = min(int(np.searchsorted(self._att_t, t[-1] + self._hi_ns, "right")) + 2,
                len(self._att_t))
        interp = AttitudeInterpolator(self._att_t[a:b], self._att_q[a:b],
                                      max_gap_s=self.max_gap_s,
                                      cubic_weight=self.cubic_weight, step_s=self.step_s)
        # keep what the waiting queries (and later ones) can still need
        first = t[-1] if not len(self._mag_t) else min(int(self._mag_t[0]), int(t[-1]))
        keep = max(int(np.searchsorted(self._att_t, first + self._lo_ns, "right")) - 2, 0)
        self._att_t, self._att_q = self._att_t[keep:], self._att_q[keep:]
        return t, v, interp

    @property
    def held(self) -> int:
        """Samples held between chunks (attitude and magnetometer): about one chunk's."""
        return max(len(self._att_t), len(self._mag_t))


#: Messages either side of a row from which a long recording's restore times its conversion
#: (sample-and-hold handling): runs of identical messages and the anchors between which
#: conversions are evenly spaced lie within a few messages of it.
SENSING_CONTEXT = 256
#: How far a sensing time may lie from its stamp, s (at most a few message periods).
SENSING_MARGIN_S = 0.25


def _head(parts: list[np.ndarray], n: int) -> np.ndarray:
    """Return the first ``n`` rows of the parts joined, copying no more than those rows."""
    out, have = [], 0
    for p in parts:
        if have >= n:
            break
        out.append(p[:n - have])
        have += len(out[-1])
    return np.concatenate(out)


class ChunkedPositions:
    """A long recording's positions, chunk by chunk, held back until they bracket the rows.

    The spatial terms of the field (``field_gradient``, ``local_source``, ``field_map``) need
    the position at each magnetometer row: :meth:`PositionSeries.at` interpolates linearly
    between the valid positions either side of it and gives NaN across a gap longer than the
    series' rule. A row is therefore settled once a valid position at or after it has
    arrived, or once no later position can bracket it: when the latest stamp read is more
    than the gap rule past the latest valid position (the span would be too long), or when
    no valid position has come yet (the row lies before the first one). The gap rule is the
    first chunk's (:meth:`PositionSeries.gap_rule_s`): every piece is interpolated as the
    whole series would be.
    """

    def __init__(self) -> None:
        self._t = np.zeros(0, np.int64)
        self._p = np.zeros((0, 3))
        self._like: PositionSeries | None = None
        self._seen_ns: int | None = None

    def add(self, position: PositionSeries | None, seen_ns: int | None) -> None:
        """Take a chunk's positions (valid rows, sorted); ``seen_ns``: its latest stamp."""
        if seen_ns is not None:
            self._seen_ns = seen_ns if self._seen_ns is None else max(self._seen_ns, seen_ns)
        if position is None or not len(position):
            return
        ok = position.valid
        if self._like is None and int(np.count_nonzero(ok)) >= 2:
            self._like = dataclasses.replace(
                position, t_ns=position.t_ns[:0], p_m=position.p_m[:0],
                max_gap_s=position.gap_rule_s())
        self._t = np.concatenate([self._t, position.t_ns[ok]])
        self._p = np.concatenate([self._p, position.p_m[ok]])
        if np.any(np.diff(self._t[-int(np.count_nonzero(ok)) - 1:]) < 0):
            o = np.argsort(self._t, kind="stable")
            self._t, self._p = self._t[o], self._p[o]

    def settled(self, t_ns: np.ndarray, margin_ns: int = 0) -> int:
        """Return how many of the (sorted) rows ``t_ns`` no later position can change.

        ``margin_ns``: a row is queried up to this much after its stamp (its sensing time).
        """
        t_ns = np.asarray(t_ns, dtype=np.int64) + int(margin_ns)
        if self._like is None:
            # fewer than two valid positions yet: rows before the first (or, without any,
            # before the stamps read) lie before every pair that could bracket them
            first = int(self._t[0]) if len(self._t) else self._seen_ns
            return 0 if first is None else int(np.searchsorted(t_ns, first, "left"))
        last = int(self._t[-1])
        gap_ns = float(self._like.gap_rule_s()) * 1e9
        if self._seen_ns is not None and self._seen_ns - last > gap_ns:
            return len(t_ns)
        return int(np.searchsorted(t_ns, last, "right"))

    def series(self, t_first_ns: int, t_last_ns: int, margin_ns: int = 0
               ) -> PositionSeries | None:
        """Return the positions bracketing ``[t_first_ns, t_last_ns]``; drop earlier ones.

        ``margin_ns``: the rows are queried up to this much either side of their stamps
        (their sensing times).
        """
        if self._like is None:
            return None
        lo, hi = t_first_ns - margin_ns, t_last_ns + margin_ns
        a = max(int(np.searchsorted(self._t, lo, "right")) - 1, 0)
        b = min(int(np.searchsorted(self._t, hi, "left")) + 1, len(self._t))
        out = dataclasses.replace(self._like, t_ns=self._t[a:b], p_m=self._p[a:b])
        # the rows after these are queried from t_last_ns - margin_ns on
        keep = max(int(np.searchsorted(self._t, t_last_ns - margin_ns, "right")) - 1, 0)
        self._t, self._p = self._t[keep:], self._p[keep:]
        return out


class ChunkedRestore:
    """Restore a long recording chunk by chunk, in memory that does not grow with its length.

    :class:`ChunkedAttitude` (the attitude as a whole-series interpolator gives it, at ``t``
    and ``t - tau``) and :func:`restore_rows` on each chunk's settled rows: feed the chunks in
    time order (:meth:`add`), each call returns the :class:`RestoreResult` of the rows now
    settled, and :meth:`finish` the rest. With ``positions``, rows also wait for the
    positions that bracket them (:class:`ChunkedPositions`), for the field's spatial terms.
    Where the calibration carries a sample-and-hold handling, rows wait for
    :data:`SENSING_CONTEXT` messages after them: each row's sensing time
    (:func:`pipeline.model.sample_hold.sensing_times_ns`) comes from the messages either
    side of it, as from the whole series (the native grid's period, fitted over the
    context, is the one exception: it can differ from the whole series' by parts in 1e4).

    Parameters
    ----------
    cal : Calibration
    t0_ns : int
        First magnetometer stamp of the recording.
    max_gap_s : float
        The recording's gap rule (s).
    cubic_weight : float
        The recording's ``lam`` of (A7).
    step_s : float
        The recording's attitude spacing, s (:attr:`AttitudeInterpolator.step_s`).
    model_key : str
        :func:`model_key_of` the calibration.
    positions : bool
        The recording has positions (each chunk's are given to :meth:`add`).

    """

    def __init__(self, cal: Calibration, *, t0_ns: int, max_gap_s: float, cubic_weight: float,
                 step_s: float, model_key: str = "", positions: bool = False):
        self.cal = cal
        self.t0_ns = int(t0_ns)
        self.model_key = model_key
        self.handling = handling_of(cal.effects)
        self.attitude = ChunkedAttitude(
            max_gap_s=max_gap_s, cubic_weight=cubic_weight,
            time_offset_s=float(cal.forward_model().time_offset_s),
            sensing_margin_s=0.0 if self.handling is None else SENSING_MARGIN_S,
            step_s=step_s)
        self.positions = ChunkedPositions() if positions else None
        self._waiting: list[tuple[np.ndarray, np.ndarray, AttitudeInterpolator]] = []
        # the rows before the waiting ones: the sensing times' context
        self._before_t = np.zeros(0, np.int64)
        self._before_v = np.zeros((0, 3))

    def add(self, mag_t_ns: np.ndarray, mag_nT: np.ndarray, att_t_ns: np.ndarray | None,
            q_enu_body: np.ndarray | None, position: PositionSeries | None = None, *,
            last: bool = False) -> RestoreResult | None:
        """Take one chunk (sorted stamps); return the rows now settled, or None.

        ``last``: no chunk follows; every row is restored now, as by :meth:`finish`.
        """
        rows = self.attitude.add(mag_t_ns, mag_nT, att_t_ns, q_enu_body, last=last)
        if self.positions is not None:
            seen = [int(a[-1]) for a in (mag_t_ns, att_t_ns) if a is not None and len(a)]
            self.positions.add(position, max(seen) if seen else None)
        return self._drain(rows, final=last)

    def finish(self) -> RestoreResult | None:
        """Return the rows still waiting (the end of the recording)."""
        return self._drain(self.attitude.finish(), final=True)

    def _drain(self, rows: tuple[np.ndarray, np.ndarray, AttitudeInterpolator] | None,
               final: bool) -> RestoreResult | None:
        if self.positions is None and self.handling is None:
            return self._restore(rows, None, None)
        if rows is not None:
            self._waiting.append(rows)
        parts: list[RestoreResult] = []
        while self._waiting:
            t, v, interp = self._waiting[0]
            later = [w[0] for w in self._waiting[1:]]
            n = len(t)
            margin_ns = 0 if self.handling is None else int(SENSING_MARGIN_S * 1e9)
            if not final and self.positions is not None:
                n = min(n, self.positions.settled(t, margin_ns))
            if not final and self.handling is not None:
                # a row's sensing time needs SENSING_CONTEXT messages after it
                n = min(n, max(len(t) + sum(len(x) for x in later) - SENSING_CONTEXT, 0))
            if n == 0:
                break
            t_sensed = None
            if self.handling is not None:
                after_t = _head([t[n:], *later], SENSING_CONTEXT)
                after_v = _head([v[n:], *(w[1] for w in self._waiting[1:])], SENSING_CONTEXT)
                t_sensed = self._sensing(t[:n], v[:n], after_t, after_v)
            if n < len(t):
                self._waiting[0] = (t[n:], v[n:], interp)
            else:
                self._waiting.pop(0)
            position = (None if self.positions is None
                        else self.positions.series(int(t[0]), int(t[n - 1]), margin_ns))
            rs = self._restore((t[:n], v[:n], interp), position, t_sensed)
            if rs is not None:
                parts.append(rs)
        if not parts:
            return None
        return parts[0] if len(parts) == 1 else RestoreResult.concat(parts)

    def _sensing(self, t: np.ndarray, v: np.ndarray, after_t: np.ndarray,
                 after_v: np.ndarray) -> np.ndarray:
        """Sensing times of rows ``t`` from them and SENSING_CONTEXT messages either side."""
        assert self.handling is not None
        nb = len(self._before_t)
        all_t = np.concatenate([self._before_t, t, after_t])
        all_v = np.concatenate([self._before_v, v, after_v])
        out = sensing_times_ns(all_t, all_v, self.handling)[nb:nb + len(t)]
        self._before_t = np.concatenate([self._before_t, t])[-SENSING_CONTEXT:]
        self._before_v = np.concatenate([self._before_v, v])[-SENSING_CONTEXT:]
        return out

    def _restore(self, rows: tuple[np.ndarray, np.ndarray, AttitudeInterpolator] | None,
                 position: PositionSeries | None, t_sensed_ns: np.ndarray | None
                 ) -> RestoreResult | None:
        if rows is None:
            return None
        t, v, interp = rows
        return restore_rows(self.cal, t, v, interp, t0_ns=self.t0_ns, position=position,
                            model_key=self.model_key, t_sensed_ns=t_sensed_ns)


@dataclass(frozen=True)
class ViewData:
    """The series the rerun recording and the report figures show (one row per mag sample).

    Attributes
    ----------
    t_ns : ndarray of int64, shape (N,)
    t_s : ndarray, shape (N,)
        Seconds from the first magnetometer sample.
    raw_mag_nT : ndarray, shape (N, 3)
        Measured magnetometer, mag frame.
    uncalibrated_enu_nT : ndarray, shape (N, 3)
        ``C_enu_body(t) @ y_mag`` (attitude only; Li 2020 Figs. 5 and 8, "before"); NaN
        without attitude.
    calibrated_enu_nT : ndarray, shape (N, 3)
        Restored field (Figs. 5 and 8, "after"); NaN without attitude.
    residual_nT : ndarray, shape (N, 3)
        Measured minus predicted, mag frame; NaN without attitude.
    body_before_nT, body_after_nT, body_ideal_nT : ndarray, shape (N, 3)
        Field seen in the body frame (Li 2020 Fig. 7): the raw reading taken as if the axes
        were aligned, the calibrated reading ``R_body_mag @ inv(D) @ (y - o - e)`` and the
        ideal ``C_enu_body(t - tau).T @ B_enu``.
    q_enu_body : ndarray, shape (N, 4)
        Attitude at ``t - tau`` (identity where invalid).
    valid : ndarray of bool, shape (N,)
    B_enu_nT : ndarray, shape (3,)

    """

    t_ns: np.ndarray
    t_s: np.ndarray
    raw_mag_nT: np.ndarray
    uncalibrated_enu_nT: np.ndarray
    calibrated_enu_nT: np.ndarray
    residual_nT: np.ndarray
    body_before_nT: np.ndarray
    body_after_nT: np.ndarray
    body_ideal_nT: np.ndarray
    q_enu_body: np.ndarray
    valid: np.ndarray
    B_enu_nT: np.ndarray


def view_data(restored: RestoreResult, R_body_mag: np.ndarray) -> ViewData:
    """Compute the :class:`ViewData` from a :class:`RestoreResult` (nothing is recomputed).

    ``R_body_mag``: the calibration's rotation (for the body-frame "after" series).
    """
    rs = restored
    y = np.asarray(rs.raw_mag_nT, dtype=float)
    unc = rs.uncalibrated_enu_nT()
    q = rs.q_or_identity()
    B = np.asarray(rs.B_enu_nT, dtype=float)
    ideal = quat_rotate(quat_conj(q), np.broadcast_to(B, y.shape))
    ideal[~rs.valid] = np.nan
    t_ns = rs.t_ns
    t_s = (t_ns - t_ns[0]).astype(float) * 1e-9 if len(t_ns) else np.zeros(0)
    return ViewData(
        t_ns=t_ns,
        t_s=t_s,
        raw_mag_nT=y,
        uncalibrated_enu_nT=unc,
        calibrated_enu_nT=rs.enu_nT,
        residual_nT=rs.residual_nT,
        body_before_nT=y,
        body_after_nT=rs.calibrated_mag_nT @ np.asarray(R_body_mag).T,
        body_ideal_nT=ideal,
        q_enu_body=q,
        valid=rs.valid,
        B_enu_nT=B,
    )
