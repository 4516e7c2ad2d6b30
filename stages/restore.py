"""Restore every magnetometer sample to ENU by inverting the fitted model, once per recording.

The model of one sample stamped ``t`` (CONVENTIONS, "Measurement model") and its inverse are
:mod:`pipeline.model.forward` (equations (M1)-(M6) there)::

    y_mag(t) = D @ R_body_mag.T @ C_enu_body(t - tau).T @ (B_enu + F(t)) + o + e(t) + noise
    b_enu    = C_enu_body(t - tau) @ R_body_mag @ inv(D) @ (y_mag - o - e(t))

Every term the calibration carries is used (:meth:`pipeline.model.calibration.Calibration.restore`):
``o``, ``D`` and ``tau`` (the attitude re-interpolated at ``t - tau``,
:mod:`pipeline.model.attitude`), from the calibration's fields or else its ``hard_iron``,
``soft_iron`` and ``time_offset`` effects; ``eddy_current`` and ``hard_iron_step`` are removed
from the reading. The external-field terms ``field_drift``, ``disturbance`` and
``field_gradient`` stay in the restored field (it is meant to show them) but are part of the
prediction, so the residual is that of the FINAL model, every diagnosed effect included.
``axis_tilt`` concerns the attitude source (the turntable stage applies it).

The :class:`Restore` stage computes all of it once and puts a :class:`RestoreResult` in
``ctx.restored``; the metrics, the corrected MCAP, the rerun recording and the report read it
from there.

Sample counts (:class:`RestoreResult`): every magnetometer sample is either *used*, or
*without a usable attitude* at ``t - tau`` (attitude gap longer than ``max_gap_s`` or outside
the attitude span), or *without an attitude at its own stamp* (``tau = 0``, needed for the
uncalibrated comparison of the metrics) while it has one at ``t - tau``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from pipeline.core.errors import InputError
from pipeline.core.recording import Context, Frame, Recording, VectorSeries
from pipeline.model.attitude import AttitudeInterpolator
from pipeline.model.forward import restore as model_restore

if TYPE_CHECKING:
    from pipeline.model.calibration import Calibration


def _readonly(*arrays: np.ndarray) -> None:
    for a in arrays:
        a.setflags(write=False)


@dataclass(frozen=True)
class RestoreResult:
    """Every magnetometer sample of a recording, restored where possible (module docstring).

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
        What the result was computed from (:func:`model_key_of`): a stage that gets the same
        model and gap rule reuses it instead of restoring again.

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
        """Every magnetometer sample of the recording."""
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
    def n_without_attitude(self) -> int:
        """Samples left out for want of an attitude at ``t - tau``."""
        return int(np.count_nonzero(~self.valid))

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




def model_key_of(cal: Calibration, max_gap_s: float | None) -> str:
    """Return the terms of ``cal`` the restore depends on, and the gap rule, as one string.

    Two calibrations with the same key restore a recording identically (the verdict, the
    sigmas, the checks and the warnings do not enter the model).
    """
    import json

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
    y = np.array(recording.mag.values, dtype=float)
    rs = model_restore(cal.forward_model(), y, t_ns, interp,
                       t0_ns=int(t_ns[0]) if len(t_ns) else None,
                       position=recording.position)
    at0 = interp.at(t_ns, 0.0)
    out = RestoreResult(
        t_ns=t_ns, raw_mag_nT=y, calibrated_mag_nT=np.array(rs.calibrated_mag_nT),
        q_enu_body=np.array(rs.q_enu_body), enu_nT=np.array(rs.enu_nT),
        residual_nT=np.array(rs.residual_nT), valid=np.array(rs.valid),
        q0_enu_body=np.array(at0.q_enu_body), valid0=np.array(at0.valid),
        B_enu_nT=np.array(cal.B_enu_nT, dtype=float), max_gap_s=interp.max_gap_s,
        model_key=model_key_of(cal, max_gap_s),
    )
    _readonly(out.raw_mag_nT, out.calibrated_mag_nT, out.q_enu_body, out.enu_nT,
              out.residual_nT, out.valid, out.q0_enu_body, out.valid0, out.B_enu_nT)
    return out


@dataclass(frozen=True)
class Restore:
    """Stage: every magnetometer sample to ENU by the inverse model (module docstring).

    Parameters
    ----------
    max_gap_s : float or None
        Longest attitude gap (s) bridged by interpolation; samples in longer gaps are left out.
        ``None``: READER's :func:`stages.resample.auto_max_gap_s` (as :class:`Resample`).

    Provides ``restored``: the :class:`RestoreResult` of the recording and its calibration.
    When the context already holds the restore result of the same model and gap rule (the
    ``Diagnose`` stage computes it for the final residual), it is kept, not recomputed.

    """

    max_gap_s: float | None = None

    requires: ClassVar[frozenset[str]] = frozenset({"recording", "calibration"})
    provides: ClassVar[frozenset[str]] = frozenset({"restored"})

    def run(self, ctx: Context) -> Context:
        """Restore ``ctx.recording.mag`` with ``ctx.calibration``."""
        old = ctx.restored
        cal = ctx.need_calibration()
        if (old is not None and old.model_key == model_key_of(cal, self.max_gap_s)
                and old.n_total == len(ctx.need_recording().mag)):
            return ctx.replace(restored=old)
        rs = restore_samples(ctx.need_recording(), cal, max_gap_s=self.max_gap_s)
        return ctx.replace(restored=rs)


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
    from pipeline.core.geometry import quat_conj, quat_rotate

    rs = restored
    y = np.asarray(rs.raw_mag_nT, dtype=float)
    ident = np.array([0.0, 0.0, 0.0, 1.0])
    q0 = np.where(rs.valid0[:, None], rs.q0_enu_body, ident)
    unc = quat_rotate(q0, y)
    unc[~rs.valid0] = np.nan
    q = np.where(rs.valid[:, None], rs.q_enu_body, ident)
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
