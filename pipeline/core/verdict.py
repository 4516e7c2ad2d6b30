"""The verdict on a calibration: OK, QUESTIONABLE or REFUSED, with the reason in words.

The sensor's own noise is measured where the platform stands still (the attitude barely turns
within one second and the reading is steady). The final residual is compared with it: a model
that explains everything but the sensor's noise leaves a residual at that floor; what lies
above it is physics the model leaves out (CONVENTIONS, ``calibration.json`` ``verdict``).
:func:`verdict_line` says a calibration and its verdict in one line for a person.
"""

from __future__ import annotations

import enum
import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from pipeline.core.style import nT_text, num
from pipeline.core.words import sig2_decimals

F64 = NDArray[np.float64]

#: Still windows are this long, s.
STILL_WINDOW_S = 1.0
#: A window is still when the attitude turns by less than this within it, rad (0.2 deg; a
#: turn of 0.2 deg in a 50,000 nT field changes the reading by 175 nT at most, well below
#: the noise of the sensors this targets, and optical or INS attitude noise is smaller).
STILL_MAX_ANGLE_RAD = np.radians(0.2)
#: At least this many still windows are needed for a noise figure.
MIN_STILL_WINDOWS = 3
#: Residual above this multiple of the sensor noise: the model misses something a user should
#: hear about (QUESTIONABLE).
QUESTIONABLE_RESIDUAL_RATIO = 1.5
#: Residual above this multiple of the sensor noise: the model does not describe the data
#: (REFUSED): what it leaves out is larger than the field changes that determine the rotation.
REFUSED_RESIDUAL_RATIO = 5.0


class Status(str, enum.Enum):
    """Verdict status (CONVENTIONS)."""

    OK = "OK"
    QUESTIONABLE = "QUESTIONABLE"
    REFUSED = "REFUSED"


@dataclass(frozen=True)
class Verdict:
    """A verdict on one calibration.

    Attributes
    ----------
    status : Status
    reason : str
        One sentence for a person: what decided the status.
    sensor_noise_nT : float or None
        Per-axis noise measured in still windows (RMS over the axes), nT; None without any.
    residual_rms_nT : float
        The final model's residual, nT (per component RMS, as ``residual_rms_nT``).
    heldout_rms_nT : float or None
        The final model's error on samples it was not fitted to, nT, when the diagnosis
        measured it: the figure the verdict judges and quotes. None when not measured.

    """

    status: Status
    reason: str
    sensor_noise_nT: float | None
    residual_rms_nT: float
    heldout_rms_nT: float | None = None

    def to_dict(self) -> dict[str, Any]:
        """Return the CONVENTIONS ``verdict`` object."""
        return {
            "status": self.status.value,
            "reason": self.reason,
            "sensor_noise_nT": None
            if self.sensor_noise_nT is None
            else float(self.sensor_noise_nT),
            "residual_rms_nT": float(self.residual_rms_nT),
            # beside the CONVENTIONS keys, only when measured: a reader of the file quotes
            # the figure the verdict judged
            **({} if self.heldout_rms_nT is None
               else {"heldout_rms_nT": float(self.heldout_rms_nT)}),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Verdict:
        """Build from the ``verdict`` object of a calibration.json."""
        n = d.get("sensor_noise_nT")
        h = d.get("heldout_rms_nT")
        return cls(Status(d["status"]), str(d["reason"]), None if n is None else float(n),
                   float(d["residual_rms_nT"]), None if h is None else float(h))

    def line(self) -> str:
        """Return the verdict as one line: status and reason."""
        return f"{self.status.value}: {self.reason}"


def still_windows(t_ns: NDArray[np.int64], q_enu_body: F64,
                  window_s: float = STILL_WINDOW_S) -> list[tuple[int, int]]:
    """Return the index ranges ``[i0, i1)`` of the one-second windows of still attitude.

    Parameters
    ----------
    t_ns : ndarray int64 (N,)
        Sample stamps, sorted.
    q_enu_body : ndarray (N, 4)
        Attitude at the samples, scalar-last.
    window_s : float
        Window length, s.

    """
    t = np.asarray(t_ns, np.int64)
    if len(t) < 10:
        return []
    w_ns = int(window_s * 1e9)
    edges = np.arange(t[0], t[-1] + 1, w_ns)
    idx = np.searchsorted(t, edges)
    out = []
    q = np.asarray(q_enu_body, float)
    for i0, i1 in zip(idx[:-1], idx[1:], strict=True):
        if i1 - i0 < 10:
            continue
        # angle between each attitude and the window's first one: 2 acos |<q0, q>|
        dots = np.abs(q[i0:i1] @ q[i0])
        ang = 2.0 * np.arccos(np.clip(dots, 0.0, 1.0))
        if float(np.max(ang)) < STILL_MAX_ANGLE_RAD:
            out.append((int(i0), int(i1)))
    return out


def sensor_noise_nT(t_ns: NDArray[np.int64], mag_nT: F64, q_enu_body: F64,
                    keep: NDArray[np.bool_] | None = None) -> float | None:
    """Magnetometer noise per axis measured in still windows (RMS over axes), nT.

    In each still window every component is detrended by a straight line (a slow drift of the
    field or of the sensor is not noise) and its standard deviation taken; the median over
    windows, per axis, resists a window with a passing disturbance. ``keep`` leaves samples
    out (repeated sample-and-hold messages carry no new noise).

    Returns None when there are fewer than :data:`MIN_STILL_WINDOWS` still windows.
    """
    t = np.asarray(t_ns, np.int64)
    y = np.asarray(mag_nT, float)
    q = np.asarray(q_enu_body, float)
    if keep is not None:
        t, y, q = t[keep], y[keep], q[keep]
    wins = still_windows(t, q)
    if len(wins) < MIN_STILL_WINDOWS:
        return None
    stds = []
    for i0, i1 in wins:
        tt = (t[i0:i1] - t[i0]) * 1e-9
        A = np.stack([np.ones_like(tt), tt], 1)
        coef, *_ = np.linalg.lstsq(A, y[i0:i1], rcond=None)
        r = y[i0:i1] - A @ coef
        stds.append(np.sqrt(np.sum(r**2, 0) / max(i1 - i0 - 2, 1)))
    per_axis = np.median(np.array(stds), axis=0)
    return float(np.sqrt(np.mean(per_axis**2)))


#: body axes and their degrees in a doubt: ``x``, ``y and z``, ``x, y and z``
_AXES = r"([xyz](?:(?:, | and )[xyz])*)"
_DEGREES = r"([\d.]+(?:(?:, | and )[\d.]+)*)"

#: A doubt in plain words: its cause (``re`` groups fill the template) and what to do.
#: The checks write their doubts with the details a report shows; the verdict's reason gives
#: a person the cause in degrees and nanotesla and one thing to do. Patterns are matched on
#: the start of the check's own words (tests/test_verdict_words.py holds every producer).
_PLAIN: tuple[tuple[str, str, str], ...] = (
    (r"the two halves of the recording disagree by ([\d.]+) deg",
     "the two halves of the recording give rotations {0} deg apart, more than their sigmas "
     "allow (the sigmas now include it)",
     "record a longer run turning about all three axes, or look in the diagnosis for what "
     "changes over the recording"),
    (r"the motion cannot determine hard iron or soft iron",
     "the motion cannot tell a magnetised or soft-magnetic part near the sensor from the "
     "Earth's field",
     "turn the sensor through large angles about all three axes, or give the field with "
     "--reference-field E,N,U"),
    (r"the motion cannot determine (hard|soft) iron",
     "the motion cannot tell a {0}-magnetic part near the sensor from the Earth's field",
     "turn the sensor through large angles about all three axes, or give the field with "
     "--reference-field E,N,U"),
    (r"the motion barely determines the rotation about one axis",
     "the motion barely turned the sensor about one axis: the rotation about it is poorly "
     "known",
     "turn the sensor about a second, very different axis"),
    (r"not estimated \(the motion cannot determine them\): (.+)$",
     "the motion cannot determine the {0} asked for",
     "turn the sensor through large angles about all three axes, or ask for fewer terms"),
    (r"the (offset|soft-iron matrix) trades against",
     "the motion cannot determine the {0}",
     "turn the sensor through large angles about all three axes, or ask for fewer terms"),
    (r"the model was restricted: the data also ask for (.+?), which move the "
     r"misalignment by ([\d.]+) deg",
     "the model asked for leaves out {0}, which moves the misalignment by {1} deg (the "
     "sigmas include that)",
     "run without --estimate for the model the data select"),
    (r"the rotation refitted on this recording differs from the calibration's by "
     r"([+-]?[\d.]+) deg about body (\w)",
     "this recording's own rotation differs from the calibration's by {0} deg about body "
     "{1}: the sensor may have moved on its mount",
     "calibrate again with this installation"),
    (rf"the rotation about body {_AXES} is only known to {_DEGREES} deg: the motion",
     "the rotation about body {0} is only known to +-{1} deg",
     "turn the sensor about body {0} as well"),
)

#: A poorly known rotation that the motion determines well: its sigma is wide because of
#: what the residual holds (``stages.estimate.poor_axis_doubts`` writes it).
_RESIDUAL_AXES = re.compile(
    rf"the rotation about body {_AXES} is only known to {_DEGREES} deg, though the motion "
    rf"alone determines it to {_DEGREES} deg: what the residual holds widens the sigma"
    r"(?: \(its samples are correlated in time: ((?:fewer than )?[\d\u00a0]+) independent "
    r"samples of ([\d\u00a0]+)\))?(?:; the largest effect in the model is (.+))?$")


def _residual_axes_words(m: re.Match[str]) -> tuple[str, str]:
    """Return the cause and the remedy of a :data:`_RESIDUAL_AXES` doubt.

    The remedy acts on the largest effect in the model: when it acted for a while (a magnet
    or magnetic object brought near the sensor), take it away or leave that time out;
    when it acted throughout, or there is none, the residual shows what to look for.
    """
    axes, sig, motion, n_eff, n, effect = m.groups()
    cause = (f"the rotation about body {axes} is only known to +-{sig} deg, though the motion "
             f"alone determines it to +-{motion} deg: the residual is correlated in time")
    if n_eff is not None:
        cause += f" ({n_eff} independent samples of {n})"
    if effect is None:
        return cause, ("look at the residual (the report's residual figure) for what changes "
                       "over the recording, and record again without it")
    effect = effect.replace("_", " ")
    cause += f" and the model holds {effect}"
    windows = re.findall(r"([\d.]+)-([\d.]+) s", effect.split(" at ", 1)[-1])
    if " at " not in effect or not windows:
        return cause, (f"look at the residual in the report: the model holds {effect}; record "
                       "again away from its cause")
    when = ", ".join(f"{a}-{b} s" for a, b in windows)
    exclude = " ".join(f"--exclude {a}:{b}" for a, b in windows)
    return cause, (f"remove the magnet or magnetic object near the sensor during {when}, or "
                   f"leave that time out with {exclude}")


def plain_words(doubt: str) -> tuple[str, str | None]:
    """Return a check's doubt as ``(cause, what to do)`` for a person.

    ``cause`` is in degrees and nanotesla without internal names; ``what to do`` is None for
    a doubt without advice (its words up to the first colon are the cause).
    """
    m = _RESIDUAL_AXES.match(doubt)
    if m:
        return _residual_axes_words(m)
    for pattern, cause, advice in _PLAIN:
        m = re.match(pattern, doubt)
        if m:
            g = tuple(x.replace("_", " ") for x in m.groups())
            return cause.format(*g), advice.format(*g)
    return doubt.split(":", 1)[0].strip(), None


def _sentence(cause: str, advice: str | None, more: int) -> str:
    text = cause[:1].upper() + cause[1:] + "."
    if advice:
        text += f" What to do: {advice}."
    if more:
        text += f" ({more} more {'doubt' if more == 1 else 'doubts'} in the report.)"
    return text


def judge(residual_rms_nT: float, sensor_noise: float | None, *,
          refusals: Sequence[str] = (), doubts: Sequence[str] = (),
          diagnosed: bool = False, heldout_rms_nT: float | None = None) -> Verdict:
    """Decide the verdict and say it in words a person can act on.

    The one rule of every command (``calibrate``, ``diagnose`` and ``process`` reach it
    through ``stages.estimate.with_verdict`` with the same inputs), in this order: a refusal
    of the fit's checks, or a model error above :data:`REFUSED_RESIDUAL_RATIO` times the
    sensor's noise, is REFUSED; an error above :data:`QUESTIONABLE_RESIDUAL_RATIO` times
    the noise, or any doubt (halves that fail their check, terms the motion does not
    determine, a poorly known axis), is QUESTIONABLE; else OK. The model's error is how well
    it predicts: the held-out figure when the diagnosis measured one (samples the fit did
    not see; the fitted residual is smaller by what the fit absorbed), else the residual.

    The reason is one cause, in nanotesla and degrees, then one thing to do; the checks'
    own words (``refusals``, ``doubts``) stay in ``Calibration.checks`` for the report.

    Parameters
    ----------
    residual_rms_nT : float
        Final model residual, nT.
    sensor_noise : float or None
        From :func:`sensor_noise_nT`.
    refusals : sequence of str
        Reasons found by the fit's checks that make the result unusable (start dependence,
        confounded motion); the first becomes the cause.
    doubts : sequence of str
        Reasons for doubt (halves that disagree, terms not determined); the first becomes
        the cause when the residual does not already decide.
    diagnosed : bool
        The diagnosis ran: its findings, not a new run, tell what the model misses.
    heldout_rms_nT : float or None
        The final model's error on held-out samples, nT (the diagnosis' cross-validation);
        None or not finite: not measured, and the residual stands for it.

    """
    res = float(residual_rms_nT)
    held = (None if heldout_rms_nT is None or not np.isfinite(heldout_rms_nT)
            else float(heldout_rms_nT))
    err = res if held is None else held
    what = (f"the model leaves {nT_text(res)} nT" if held is None
            else f"the model's error on samples it was not fitted to is {nT_text(held)} nT")
    find = ("the diagnosis names what the model cannot describe (see its findings): exclude "
            "those stretches with --exclude, or record again away from them" if diagnosed
            else "run magalign diagnose to find what the model misses")
    ratio = err / sensor_noise if sensor_noise is not None and sensor_noise > 0 else None
    fit_words = (f"{what}; no still window to measure the sensor's "
                 "noise (record a few seconds without moving)" if ratio is None
                 else f"{what} against a sensor noise of {nT_text(sensor_noise)} nT")
    if refusals:
        cause, advice = plain_words(refusals[0])
        return Verdict(Status.REFUSED, _sentence(cause, advice, len(refusals) - 1 + len(doubts)),
                       sensor_noise, res, held)
    if ratio is not None and ratio > REFUSED_RESIDUAL_RATIO:
        cause = (f"{what}, {ratio:.0f} times the sensor's noise "
                 f"({nT_text(sensor_noise)} nT): something it does not model dominates")
        return Verdict(Status.REFUSED, _sentence(cause, find, len(doubts)), sensor_noise, res,
                       held)
    if ratio is not None and ratio > QUESTIONABLE_RESIDUAL_RATIO:
        cause = (f"{what}, {ratio:.1f} times the sensor's noise "
                 f"({nT_text(sensor_noise)} nT)")
        return Verdict(Status.QUESTIONABLE, _sentence(cause, find, len(doubts)), sensor_noise,
                       res, held)
    if doubts:
        cause, advice = plain_words(doubts[0])
        return Verdict(Status.QUESTIONABLE, _sentence(cause, advice, len(doubts) - 1),
                       sensor_noise, res, held)
    return Verdict(Status.OK, _sentence(fit_words, None, 0), sensor_noise, res, held)


class StatedCalibration(Protocol):
    """What :func:`verdict_line` reads of a calibration.

    ``pipeline.model.calibration.Calibration`` has all of it; the framework names only these
    attributes, so the line stays beside the verdict without the framework knowing the model.
    """

    @property
    def rotvec_body_mag_deg(self) -> np.ndarray:
        """Rotation vector of ``R_body_mag``, deg (3,)."""
        ...

    @property
    def sigma_rotvec_deg(self) -> np.ndarray:
        """Its 1-sigma per body axis, deg (3,); inf about an unobservable axis."""
        ...

    @property
    def time_offset_s(self) -> float | None:
        """The estimated time offset ``tau``, s; None when not estimated."""
        ...

    @property
    def verdict(self) -> Verdict | None:
        """The verdict; None before the calibration is judged."""
        ...


def verdict_line(cal: StatedCalibration, with_status: bool = True) -> str:
    """One line for a person: misalignment angle +- sigma and axis, time offset, verdict.

    Parameters
    ----------
    cal : StatedCalibration
        A calibration (``pipeline.model.calibration.Calibration``).
    with_status : bool
        End with the verdict's status (False where it is shown beside the line).

    Returns
    -------
    str

    """
    rv = np.asarray(cal.rotvec_body_mag_deg, float)
    sg = np.asarray(cal.sigma_rotvec_deg, float)
    ang = float(np.linalg.norm(rv))
    u = rv / ang if ang > 0 else np.array([0.0, 0.0, 1.0])
    s_ang = float(np.sqrt(np.sum((u * sg) ** 2))) if np.all(np.isfinite(sg)) else float("inf")
    # the sigma to two significant digits, the angle to the same decimals (never "+- 0.00")
    dec = sig2_decimals(s_ang)
    parts = [
        f"misalignment {ang:.{dec}f} +- {s_ang:.{dec}f} deg about body ["
        + ", ".join(f"{c:+.2f}" for c in u) + "]"
    ]
    if cal.time_offset_s is not None:
        # the digits of the report's calibration table (one value everywhere)
        parts.append(f"time offset {num(cal.time_offset_s * 1e3, '+.2f')} ms")
    if cal.verdict is not None:
        v = cal.verdict
        # the figure the verdict judged: the error on held-out samples when it was measured
        err = (f"residual {nT_text(v.residual_rms_nT)} nT" if v.heldout_rms_nT is None
               else f"held-out error {nT_text(v.heldout_rms_nT)} nT")
        if v.sensor_noise_nT is not None:
            err += f" vs noise {nT_text(v.sensor_noise_nT)} nT"
        parts.append(err)
        if with_status:
            parts.append(v.status.value)
    return "; ".join(parts)
