"""Restore every magnetometer sample to ENU by inverting the fitted model (CONVENTIONS).

The model of one sample stamped ``t`` (CONVENTIONS, "Measurement model")::

    y_mag(t) = D @ R_body_mag.T @ C_enu_body(t - tau).T @ B_enu(t) + o + e(t) + noise

Restoring inverts it::

    b_enu = C_enu_body(t - tau) @ R_body_mag @ inv(D) @ (y_mag - o - e(t))

Effects removed (whatever the calibration holds; absent terms are identity / zero):

- ``offset_nT`` (``o``) and ``D``: from the calibration's own fields; when those are ``None``
  the ``hard_iron`` / ``soft_iron`` entries of ``calibration.effects`` are used instead.
- ``time_offset_s`` (``tau``): the attitude is interpolated at ``t - tau`` (SLERP, READER's
  :func:`stages.resample.interpolate_attitude`); from ``calibration.time_offset_s``, else the
  ``time_offset`` effect.
- ``eddy_current`` (``E_s``, 3x3, seconds): ``e(t) = E_s @ d/dt(y_mag)``, with the derivative
  of the measured magnetometer series by central differences (``numpy.gradient`` over the
  sample stamps); subtracted *before* the offset and ``D``, since it is additive in the mag
  frame like ``o``.
- ``hard_iron_step`` (``windows_s``, ``offset_nT``): the extra offset is subtracted from the
  samples inside its half-open windows (seconds from the first magnetometer sample).

Not removed: ``field_drift`` and ``disturbance`` are variations of the *external* field
``B_enu(t)``; the restored series is meant to show them. ``axis_tilt`` concerns the attitude
source (handled by the turntable stage), not the magnetometer.

Samples without a usable attitude (attitude gap longer than ``max_gap_s`` or outside the
attitude span) are left out of ``restored``; their number is
``len(recording.mag) - len(restored)`` (reported by the metrics stage).
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from pipeline.errors import InputError
from pipeline.recording import Context, Frame, Recording, VectorSeries


def _effect(cal: Any, name: str) -> dict | None:
    eff = getattr(cal, "effects", None) or {}
    p = eff.get(name)
    return p if isinstance(p, dict) else None


def time_offset_of(cal: Any) -> float:
    """``tau`` (s) of a calibration: its field, else its ``time_offset`` effect, else 0."""
    if cal.time_offset_s is not None:
        return float(cal.time_offset_s)
    p = _effect(cal, "time_offset")
    return float(p["time_offset_s"]) if p and p.get("time_offset_s") is not None else 0.0


def offset_of(cal: Any) -> np.ndarray | None:
    """Offset ``o`` (3,) nT, mag frame: the field, else the ``hard_iron`` effect, else None."""
    if cal.offset_nT is not None:
        return np.asarray(cal.offset_nT, dtype=float)
    p = _effect(cal, "hard_iron")
    return None if p is None else np.asarray(p["offset_nT"], dtype=float).reshape(3)


def soft_iron_of(cal: Any) -> np.ndarray | None:
    """``D`` (3, 3): the field, else the ``soft_iron`` effect, else None."""
    if cal.D is not None:
        return np.asarray(cal.D, dtype=float)
    p = _effect(cal, "soft_iron")
    return None if p is None else np.asarray(p["D"], dtype=float).reshape(3, 3)


def additive_effects_nT(cal: Any, t_ns: np.ndarray, mag_nT: np.ndarray) -> np.ndarray:
    """Additive mag-frame terms ``e(t)`` the calibration models, shape (N, 3), nT.

    Parameters
    ----------
    cal : Calibration
        The fitted model (its ``effects`` are read).
    t_ns : ndarray of int64, shape (N,)
        Magnetometer stamps (the whole series, so derivatives see every neighbour).
    mag_nT : ndarray, shape (N, 3)
        Measured magnetometer, mag frame.

    Returns
    -------
    ndarray, shape (N, 3)
        ``E_s @ dy/dt`` (eddy_current) plus the ``hard_iron_step`` offset inside its windows.

    """
    t_ns = np.asarray(t_ns, dtype=np.int64)
    y = np.asarray(mag_nT, dtype=float)
    e = np.zeros_like(y)
    if len(t_ns) == 0:
        return e
    eddy = _effect(cal, "eddy_current")
    if eddy is not None and len(t_ns) >= 2:
        E_s = np.asarray(eddy["E_s"], dtype=float).reshape(3, 3)
        t_s = (t_ns - t_ns[0]).astype(float) * 1e-9
        # Central differences; repeated stamps would divide by zero, so nudge them apart.
        t_s = t_s + np.arange(len(t_s)) * 1e-12
        dy_dt = np.gradient(y, t_s, axis=0)  # nT/s, mag frame
        e += dy_dt @ E_s.T
    step = _effect(cal, "hard_iron_step")
    if step is not None:
        off = np.asarray(step["offset_nT"], dtype=float).reshape(3)
        t_rel_s = (t_ns - t_ns[0]).astype(float) * 1e-9
        inside = np.zeros(len(t_ns), dtype=bool)
        for w0, w1 in step.get("windows_s") or ():
            inside |= (t_rel_s >= float(w0)) & (t_rel_s < float(w1))
        e[inside] += off
    return e


def corrected_mag_nT(cal: Any, t_ns: np.ndarray, mag_nT: np.ndarray) -> np.ndarray:
    """``inv(D) @ (y - o - e(t))``: the magnetometer with sensor terms removed, mag frame (N, 3)."""
    y = np.asarray(mag_nT, dtype=float) - additive_effects_nT(cal, t_ns, mag_nT)
    o = offset_of(cal)
    if o is not None:
        y = y - o
    D = soft_iron_of(cal)
    if D is not None:
        y = np.linalg.solve(D, y.T).T
    return y


#: Results of the last few :func:`attitude_at_mag` / :func:`restore_samples` calls, keyed by
#: the identity of their (immutable) inputs. Restore, Metrics, WriteCorrectedMcap, WriteRerun
#: and Report all need the same interpolated attitude and restored samples of one recording;
#: computing them once removes the SLERP and the rotations that dominated those stages.
_CACHE: dict[tuple, tuple[tuple, Any]] = {}
_CACHE_SIZE = 4


def _cached(key: tuple, objs: tuple, compute: Any) -> Any:
    """``compute()``, or its earlier result for the same objects (by identity) and ``key``."""
    hit = _CACHE.get(key)
    if hit is not None and all(r() is o for r, o in zip(hit[0], objs, strict=True)):
        return hit[1]
    result = compute()
    try:
        refs = tuple(weakref.ref(o) for o in objs)
    except TypeError:  # not weak-referenceable: do not cache
        return result
    for k in [k for k, v in _CACHE.items() if any(r() is None for r in v[0])]:
        del _CACHE[k]  # entries of recordings that no longer exist
    while len(_CACHE) >= _CACHE_SIZE:
        del _CACHE[next(iter(_CACHE))]
    _CACHE[key] = (refs, result)
    return result


def clear_cache() -> None:
    """Forget every cached result (``process_recording`` calls it when a recording is done)."""
    _CACHE.clear()


def _readonly(*arrays: np.ndarray) -> None:
    for a in arrays:
        a.setflags(write=False)


def attitude_at_mag(
    recording: Recording, time_offset_s: float, max_gap_s: float | None
) -> tuple[np.ndarray, np.ndarray]:
    """Attitude ``q_enu_body`` at every magnetometer stamp minus ``tau``.

    The result is cached for the recording (read-only arrays).

    Returns
    -------
    q_enu_body : ndarray, shape (N, 4)
    valid : ndarray of bool, shape (N,)

    """
    key = ("attitude", id(recording), float(time_offset_s), max_gap_s)
    return _cached(key, (recording,),
                   lambda: _attitude_at_mag(recording, time_offset_s, max_gap_s))


def _attitude_at_mag(
    recording: Recording, time_offset_s: float, max_gap_s: float | None
) -> tuple[np.ndarray, np.ndarray]:
    from stages.resample import interpolate_attitude

    if recording.attitude is None or len(recording.attitude) == 0:
        raise InputError(
            "the recording has no attitude to restore the magnetometer with",
            path=recording.path,
            hint="for a turntable recording put TurntableAttitude before Restore",
        )
    if max_gap_s is None:
        from stages.resample import auto_max_gap_s

        max_gap_s = auto_max_gap_s(recording.attitude)
    q, valid = interpolate_attitude(
        recording.attitude, recording.mag.t_ns, time_offset_s=time_offset_s, max_gap_s=max_gap_s
    )
    q, valid = np.array(q, dtype=float), np.array(valid, dtype=bool)
    _readonly(q, valid)
    return q, valid


@dataclass(frozen=True)
class RestoredSamples:
    """Every magnetometer sample of a recording, restored where possible.

    Attributes
    ----------
    t_ns : ndarray of int64, shape (N,)
        All magnetometer stamps.
    calibrated_mag_nT : ndarray, shape (N, 3)
        ``inv(D) @ (y - o - e)``, mag frame (defined for every sample).
    q_enu_body : ndarray, shape (N, 4)
        Attitude at ``t - tau``; meaningless where ``valid`` is false.
    enu_nT : ndarray, shape (N, 3)
        Restored field, ENU; NaN where ``valid`` is false.
    residual_nT : ndarray, shape (N, 3)
        Measured minus predicted by the fitted forward model, mag frame; NaN where invalid.
    valid : ndarray of bool, shape (N,)
        Samples with a usable attitude.

    """

    t_ns: np.ndarray
    calibrated_mag_nT: np.ndarray
    q_enu_body: np.ndarray
    enu_nT: np.ndarray
    residual_nT: np.ndarray
    valid: np.ndarray

    @property
    def n_without_attitude(self) -> int:
        """Samples left out for want of an attitude."""
        return int(np.count_nonzero(~self.valid))


def restore_samples(
    recording: Recording, cal: Any, *, max_gap_s: float | None = None
) -> RestoredSamples:
    """Restore every magnetometer sample and compute the model residual.

    Parameters
    ----------
    recording : Recording
        With ``attitude`` filled.
    cal : Calibration
        The fitted model.
    max_gap_s : float
        Longest attitude gap (s) bridged by interpolation.

    Returns
    -------
    RestoredSamples
        Cached for the recording and calibration objects (read-only arrays).

    """
    key = ("restored", id(recording), id(cal), max_gap_s)
    return _cached(key, (recording, cal), lambda: _restore_samples(recording, cal, max_gap_s))


def _restore_samples(recording: Recording, cal: Any, max_gap_s: float | None) -> RestoredSamples:
    t_ns = recording.mag.t_ns
    y = recording.mag.values
    tau = time_offset_of(cal)
    q, valid = attitude_at_mag(recording, tau, max_gap_s)
    q_safe = np.where(valid[:, None], q, np.array([0.0, 0.0, 0.0, 1.0]))
    q_safe = np.where(np.isfinite(q_safe).all(axis=1)[:, None], q_safe, [0.0, 0.0, 0.0, 1.0])
    m = corrected_mag_nT(cal, t_ns, y)
    # CONVENTIONS inverse model: b_enu = C_enu_body(t - tau) @ R_body_mag @ inv(D) @ (y - o - e)
    from pipeline.geometry import quat_conj, quat_rotate

    enu = quat_rotate(q_safe, m @ np.asarray(cal.R_body_mag).T)
    # Forward model (CONVENTIONS): y = D R.T C.T B + o + e; residual = measured - predicted.
    b_body = quat_rotate(quat_conj(q_safe), np.broadcast_to(cal.B_enu_nT, (len(t_ns), 3)))
    pred = b_body @ np.asarray(cal.R_body_mag)
    D = soft_iron_of(cal)
    if D is not None:
        pred = pred @ D.T
    o = offset_of(cal)
    if o is not None:
        pred = pred + o
    pred = pred + additive_effects_nT(cal, t_ns, y)
    resid = y - pred
    enu[~valid] = np.nan
    resid[~valid] = np.nan
    m = np.array(m, dtype=float)
    _readonly(m, enu, resid)
    return RestoredSamples(t_ns, m, q, enu, resid, valid)


@dataclass(frozen=True)
class Restore:
    """Stage: every magnetometer sample to ENU by the inverse model (module docstring).

    Parameters
    ----------
    max_gap_s : float or None
        Longest attitude gap (s) bridged by interpolation; samples in longer gaps are left out.
        ``None``: READER's :func:`stages.resample.auto_max_gap_s` (as :class:`Resample`).

    Provides ``restored``: VectorSeries, frame ``enu``, nT, one row per magnetometer sample with
    a usable attitude.

    """

    max_gap_s: float | None = None

    requires: ClassVar[frozenset[str]] = frozenset({"recording", "calibration"})
    provides: ClassVar[frozenset[str]] = frozenset({"restored"})

    def run(self, ctx: Context) -> Context:
        """Restore ``ctx.recording.mag`` with ``ctx.calibration``."""
        rs = restore_samples(ctx.recording, ctx.calibration, max_gap_s=self.max_gap_s)
        restored = VectorSeries(rs.t_ns[rs.valid], rs.enu_nT[rs.valid], Frame.ENU, "nT")
        return ctx.replace(restored=restored)


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


def view_data(recording: Recording, cal: Any, *, max_gap_s: float | None = None) -> ViewData:
    """Compute the :class:`ViewData` of a recording restored with ``cal``."""
    from pipeline.geometry import quat_conj, quat_rotate

    rs = restore_samples(recording, cal, max_gap_s=max_gap_s)
    y = np.asarray(recording.mag.values, dtype=float)
    q0, valid0 = attitude_at_mag(recording, 0.0, max_gap_s)
    ident = np.array([0.0, 0.0, 0.0, 1.0])
    q0 = np.where(valid0[:, None] & np.isfinite(q0).all(axis=1)[:, None], q0, ident)
    unc = quat_rotate(q0, y)
    unc[~valid0] = np.nan
    q = np.where(rs.valid[:, None] & np.isfinite(rs.q_enu_body).all(axis=1)[:, None],
                 rs.q_enu_body, ident)
    B = np.asarray(cal.B_enu_nT, dtype=float)
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
        body_after_nT=rs.calibrated_mag_nT @ np.asarray(cal.R_body_mag).T,
        body_ideal_nT=ideal,
        q_enu_body=q,
        valid=rs.valid,
        B_enu_nT=B,
    )
