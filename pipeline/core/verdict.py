"""The verdict on a calibration: OK, QUESTIONABLE or REFUSED, with the reason in words.

The sensor's own noise is measured where the platform stands still (the attitude barely turns
within one second and the reading is steady). The final residual is compared with it: a model
that explains everything but the sensor's noise leaves a residual at that floor; what lies
above it is physics the model leaves out (CONVENTIONS, ``calibration.json`` ``verdict``).
"""

from __future__ import annotations

import enum
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

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

    """

    status: Status
    reason: str
    sensor_noise_nT: float | None
    residual_rms_nT: float

    def to_dict(self) -> dict[str, Any]:
        """Return the CONVENTIONS ``verdict`` object."""
        return {
            "status": self.status.value,
            "reason": self.reason,
            "sensor_noise_nT": None
            if self.sensor_noise_nT is None
            else float(self.sensor_noise_nT),
            "residual_rms_nT": float(self.residual_rms_nT),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Verdict:
        """Build from the ``verdict`` object of a calibration.json."""
        n = d.get("sensor_noise_nT")
        return cls(Status(d["status"]), str(d["reason"]), None if n is None else float(n),
                   float(d["residual_rms_nT"]))

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


def judge(residual_rms_nT: float, sensor_noise: float | None, *,
          refusals: Sequence[str] = (), doubts: Sequence[str] = ()) -> Verdict:
    """Decide the verdict.

    Parameters
    ----------
    residual_rms_nT : float
        Final model residual, nT.
    sensor_noise : float or None
        From :func:`sensor_noise_nT`.
    refusals : sequence of str
        Reasons found by the fit's checks that make the result unusable (start dependence,
        confounded motion); the first becomes the reason.
    doubts : sequence of str
        Reasons for doubt (halves that disagree, terms not determined); joined into the reason.

    """
    res = float(residual_rms_nT)
    parts: list[str] = []
    status = Status.OK
    if sensor_noise is not None and sensor_noise > 0:
        ratio = res / sensor_noise
        explained = (
            f"residual {res:.0f} nT vs sensor noise {sensor_noise:.0f} nT"
        )
        if ratio <= 1.0:
            parts.append(f"{explained}: the model explains all but the sensor's noise")
        else:
            left = 100.0 * (1.0 - sensor_noise / res)
            parts.append(f"{explained}: the model explains all but {left:.0f} %")
        if ratio > REFUSED_RESIDUAL_RATIO:
            status = Status.REFUSED
            parts = [
                f"residual {res:.0f} nT is {ratio:.0f} times the sensor noise "
                f"({sensor_noise:.0f} nT): the model does not describe this recording (a "
                "magnet or another field the model leaves out dominates); run magalign "
                "diagnose"
            ]
        elif ratio > QUESTIONABLE_RESIDUAL_RATIO:
            status = Status.QUESTIONABLE
            parts[-1] += " (more than the model should leave: run magalign diagnose)"
    else:
        parts.append(f"residual {res:.0f} nT; no still window to measure the sensor noise")
    if refusals:
        status = Status.REFUSED
        parts = [refusals[0]] + parts
    elif doubts:
        if status is Status.OK:
            status = Status.QUESTIONABLE
        parts = parts + list(doubts)
    return Verdict(status, "; ".join(parts), sensor_noise, res)
