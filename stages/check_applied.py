"""Stage: a calibration made on another recording, checked on this one (its own verdict).

More in docs/modules.md, ``stages.check_applied``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from pipeline.core.errors import DataQualityError
from pipeline.core.recording import AlignedSeries
from pipeline.core.verdict import (
    QUESTIONABLE_RESIDUAL_RATIO,
    Status,
    Verdict,
    plain_words,
    sensor_noise_nT,
)
from pipeline.model.calibration import Calibration
from pipeline.model.sample_hold import repeated
from stages.context import Context
from stages.estimate import POOR_AXIS_SIGMA_DEG, fit_calibration
from stages.restore import restore_samples

#: The line's own rotation differs from the calibration's by more than this many combined
#: sigmas about an axis the line determines: the line contradicts the calibration.
DISAGREE_SIGMAS = 3.0
_RANK = {Status.OK: 0, Status.QUESTIONABLE: 1, Status.REFUSED: 2}


def calibration_source(path: str | Path) -> str:
    """Name a calibration file for a verdict, never by a machine's path.

    Its folder and name: in a campaign's output, the folder is the recording it came from.
    """
    p = Path(path)
    return f"{p.parent.name}/{p.name}" if p.parent.name else p.name


def rotation_check(cal: Calibration, refit: Calibration) -> dict[str, Any]:
    """Compare the line's refitted rotation with the calibration's, axis by axis.

    Parameters
    ----------
    cal : Calibration
        The calibration applied (its ``rotvec_body_mag_deg`` and sigmas).
    refit : Calibration
        The rotation fitted on this line alone.

    Returns
    -------
    dict
        ``determined_axes`` (body axes ``x``/``y``/``z`` whose refitted sigma is below
        :data:`stages.estimate.POOR_AXIS_SIGMA_DEG`: a straight line determines little, and
        a sigma of degrees compares nothing), ``difference_deg`` [3] (refit minus
        calibration, rotation vector about body x, y, z), ``z`` [3] (per axis, in combined
        sigmas; null where not determined), ``max_z`` (null without a determined axis),
        ``refit_rotvec_deg`` and ``refit_sigma_deg``.

    """
    a = np.asarray(cal.rotvec_body_mag_deg, float)
    b = np.asarray(refit.rotvec_body_mag_deg, float)
    sa = np.asarray(cal.sigma_rotvec_deg, float)
    sb = np.asarray(refit.sigma_rotvec_deg, float)
    det = np.isfinite(sb) & (sb < POOR_AXIS_SIGMA_DEG) & np.isfinite(sa)
    if len(refit.unobservable_axes_body):
        u = np.abs(np.asarray(refit.unobservable_axes_body, float))
        det &= ~np.any(u > 0.5, axis=0)  # an axis the motion leaves undetermined
    d = b - a
    z = np.where(det, np.abs(d) / np.sqrt(np.where(det, sa**2 + sb**2, 1.0)), np.nan)
    return {
        "determined_axes": [ax for ax, ok in zip("xyz", det, strict=True) if ok],
        "difference_deg": d.tolist(),
        "z": [None if not np.isfinite(v) else float(v) for v in z],
        "max_z": None if not det.any() else float(np.nanmax(z)),
        "refit_rotvec_deg": b.tolist(),
        "refit_sigma_deg": [None if not np.isfinite(v) else float(v) for v in sb],
    }


def src_ok_floor(applied: dict[str, Any]) -> float | None:
    """Return the calibration run's residual (nT) when its verdict was OK, else None."""
    if applied.get("source_status") != "OK":
        return None
    r = applied.get("source_residual_rms_nT")
    return None if r is None or not np.isfinite(r) or r <= 0 else float(r)


def applied_verdict(cal: Calibration, residual_rms_nT: float) -> Verdict:
    """Return the verdict of a line restored with ``cal`` (docs/modules.md).

    ``cal.checks["applied"]`` holds what :class:`CheckApplied` measured on the line (the
    source and its verdict, the line's noise and the rotation check); ``residual_rms_nT`` is
    the line's residual over every sample.
    """
    ap = cal.checks.get("applied") or {}
    rot = ap.get("rotation") or {}
    doubts: list[str] = []
    max_z = rot.get("max_z")
    if max_z is not None and max_z > DISAGREE_SIGMAS:
        d = np.asarray(rot["difference_deg"], float)
        zs = [np.nan if z is None else z for z in rot["z"]]
        i = int(np.nanargmax(zs))
        doubts.append(
            f"the rotation refitted on this recording differs from the calibration's by "
            f"{d[i]:+.2f} deg about body {'xyz'[i]} ({max_z:.1f} sigmas): the sensor may "
            "have moved on its mount since the calibration; calibrate again")
    noise = ap.get("sensor_noise_nT")
    noise_from = ""
    if noise is None and ap.get("source_noise_nT") is not None:
        # the same sensor: its noise measured on the calibration run stands
        noise = ap["source_noise_nT"]
        noise_from = ("the sensor noise was measured on the calibration run (this recording "
                      "has no still window)")
    elif noise is None and (floor := src_ok_floor(ap)) is not None:
        # neither has a still window: what the accepted model left there is the floor
        noise = floor
        noise_from = ("no still window here or in the calibration run: the floor is the "
                      "calibration run's residual")
    res = float(residual_rms_nT)
    status = Status.OK
    advice = None
    if noise is None or noise <= 0:
        fit = f"the model leaves {res:.0f} nT here; no still window to measure the noise"
    elif res <= QUESTIONABLE_RESIDUAL_RATIO * noise:
        fit = f"the model leaves {res:.0f} nT here against a sensor noise of {noise:.0f} nT"
    else:
        # never REFUSED: the restore does not depend on the field, and on a survey line the
        # field's own changes (the anomalies surveyed) are the product, not a fault
        status = Status.QUESTIONABLE
        fit = (f"the field here departs from the calibration's model by {res:.0f} nT, "
               f"{res / noise:.1f} times the sensor's noise ({noise:.0f} nT)")
        advice = ("magalign diagnose on this recording tells the survey's own anomalies from "
                  "a disturbance or a change of the sensor")
    if doubts:
        status = Status.QUESTIONABLE
        cause, advice = plain_words(doubts[0])
        fit = f"{fit}; {cause}"
    src_status = Status(ap.get("source_status", "OK"))
    status = max(status, src_status, key=lambda s: _RANK[s])
    if max_z is None:
        rotation = ("this recording's motion does not determine the rotation: only the "
                    "residual is checked")
    elif max_z <= DISAGREE_SIGMAS:
        rotation = (f"the rotation refitted here agrees within {max_z:.1f} sigmas about "
                    f"body {', '.join(rot['determined_axes'])}")
    else:
        rotation = ""
    source = (f"Calibration from {ap.get('source', 'another recording')} "
              f"({src_status.value} there).")
    parts = [source, fit[:1].upper() + fit[1:] + "."]
    if noise_from:
        parts.append(noise_from[:1].upper() + noise_from[1:] + ".")
    if rotation:
        parts.append(rotation[:1].upper() + rotation[1:] + ".")
    if advice:
        parts.append(f"What to do: {advice}.")
    return Verdict(status, " ".join(parts), None if noise is None else float(noise), res)


def check_applied(cal: Calibration, aligned: AlignedSeries, refit: Calibration | None,
                  source: str) -> Calibration:
    """Return ``cal`` with ``checks["applied"]``: the line's noise and rotation check.

    Parameters
    ----------
    cal : Calibration
        The calibration applied (loaded from ``source``).
    aligned : AlignedSeries
        The line's samples with their attitude.
    refit : Calibration or None
        The rotation fitted on the line alone; None when it could not be fitted.
    source : str
        Where the calibration came from, as the verdict names it (a file name).

    """
    keep = ~repeated(aligned.mag_nT)
    noise = sensor_noise_nT(aligned.t_ns, aligned.mag_nT, aligned.q_enu_body, keep)
    src = cal.verdict
    applied = {
        "source": source,
        "source_status": "OK" if src is None else src.status.value,
        "source_reason": None if src is None else src.reason,
        "source_residual_rms_nT": float(cal.residual_rms_nT),
        "source_noise_nT": None if src is None else src.sensor_noise_nT,
        "sensor_noise_nT": noise,
        "rotation": None if refit is None else rotation_check(cal, refit),
    }
    return cal.replace(checks={**cal.checks, "applied": applied})


@dataclass(frozen=True)
class CheckApplied:
    """Stage: check a calibration made elsewhere on this recording; its verdict is the line's.

    Provides ``calibration``: the same model, with this line's verdict, residual and
    ``checks["applied"]``.

    Parameters
    ----------
    source : str
        Where the calibration came from (the verdict names it).
    max_gap_s : float or None
        The gap rule of the restore (as :class:`stages.restore.Restore`).

    """

    source: str
    max_gap_s: float | None = None

    requires: ClassVar[frozenset[str]] = frozenset({"recording", "aligned", "calibration"})
    provides: ClassVar[frozenset[str]] = frozenset({"calibration"})

    def run(self, ctx: Context) -> Context:
        """Return ``ctx`` with the line's own verdict on the calibration."""
        cal = ctx.need_calibration()
        rec, al = ctx.need_recording(), ctx.need_aligned()
        try:
            refit = fit_calibration(rec, al)
        except DataQualityError:  # too little data to fit anything: no comparison
            refit = None
        cal = check_applied(cal, al, refit, self.source)
        restored = restore_samples(rec, cal, max_gap_s=self.max_gap_s)
        res = float(restored.residual_rms_nT)
        cal = cal.replace(residual_rms_nT=res, verdict=applied_verdict(cal, res))
        return ctx.replace(calibration=cal)
