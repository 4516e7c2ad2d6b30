"""A calibration in other tools' terms: ArduPilot, MATLAB magcal, ROS 2 tf, YAML.

``magalign export CALIBRATION.json --format ardupilot|magcal|ros-tf|yaml`` prints one of
these (``docs/exports.md`` describes each). Every function takes a
:class:`~pipeline.model.calibration.Calibration` and returns the text; none prints.

Our model (CONVENTIONS): ``v_body = R_body_mag @ inv(D) @ (y_mag - o)``, field in nT.
"""

from __future__ import annotations

import json
import math
import shlex
from typing import Any

import numpy as np

from pipeline.core.errors import InputError
from pipeline.core.geometry import matrix_to_quat
from pipeline.model.calibration import Calibration

FORMATS = ("ardupilot", "magcal", "ros-tf", "yaml")

#: ArduPilot's compass unit: 1 milligauss = 1e-7 T = 100 nT.
NT_PER_MILLIGAUSS = 100.0


# ------------------------------------------------------------------ shared pieces

def check_exportable(cal: Calibration, path: str | None = None) -> None:
    """Refuse a calibration whose numbers cannot describe a sensor.

    Raises
    ------
    InputError
        ``R_body_mag`` is not a proper rotation, or ``D`` is not symmetric positive-definite.

    """
    R = np.asarray(cal.R_body_mag, float)
    if not (np.all(np.isfinite(R)) and np.allclose(R @ R.T, np.eye(3), atol=1e-6)
            and abs(np.linalg.det(R) - 1.0) < 1e-6):
        raise InputError("R_body_mag is not a rotation matrix", path=path,
                         hint="regenerate the calibration with magalign calibrate")
    if cal.D is not None:
        D = np.asarray(cal.D, float)
        if not (np.all(np.isfinite(D)) and np.allclose(D, D.T, atol=1e-9)
                and np.linalg.eigvalsh(D).min() > 0):
            raise InputError("D is not symmetric positive-definite", path=path,
                             hint="regenerate the calibration with magalign calibrate")


def _offset(cal: Calibration) -> np.ndarray:
    return np.zeros(3) if cal.offset_nT is None else np.asarray(cal.offset_nT, float)


def _d_inv(cal: Calibration) -> np.ndarray:
    return np.eye(3) if cal.D is None else np.linalg.inv(np.asarray(cal.D, float))


def _num(x: float) -> str:
    """Shortest round-trip decimal of a float (``repr``), ``-0.0`` written as ``0.0``."""
    return repr(float(x) + 0.0)


# ------------------------------------------------------------------ ArduPilot

def rpy_from_matrix(R: np.ndarray) -> tuple[float, float, float]:
    """Roll, pitch, yaw (rad) of ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``.

    This is ArduPilot's ``Matrix3::from_euler(roll, pitch, yaw)`` (321 / ZYX order, the
    matrix that takes body-frame vectors to the frame the angles are measured from). At
    pitch = +-90 deg roll and yaw are not separable; roll is set to 0 there.
    """
    R = np.asarray(R, float)
    pitch = math.asin(max(-1.0, min(1.0, -R[2, 0])))
    if abs(R[2, 0]) > 1 - 1e-12:
        return 0.0, pitch, math.atan2(-R[0, 1], R[1, 1])
    return math.atan2(R[2, 1], R[2, 2]), pitch, math.atan2(R[1, 0], R[0, 0])


def matrix_from_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """``Rz(yaw) @ Ry(pitch) @ Rx(roll)``, ArduPilot's ``Matrix3::from_euler``."""
    cr, sr, cp, sp, cy, sy = (math.cos(roll), math.sin(roll), math.cos(pitch),
                              math.sin(pitch), math.cos(yaw), math.sin(yaw))
    return np.array([[cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy],
                     [cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy],
                     [-sp, sr * cp, cr * cp]])


def ardupilot_params(cal: Calibration) -> dict[str, float]:
    """ArduPilot compass parameters equivalent to the calibration.

    ArduPilot corrects a compass sample ``m`` (sensor frame, milligauss) in this order
    (``AP_Compass_Backend::rotate_field`` then ``correct_field``, libraries/AP_Compass in
    the ArduPilot source; parameter semantics from the ``COMPASS_*`` ``@Param``
    documentation in ``AP_Compass.cpp``):

    1. ``m_b = C @ m`` with the orientation; for ``COMPASS_ORIENT = 100`` (custom, 4.1 and
       older) ``C = from_euler(CUS_ROLL, CUS_PIT, CUS_YAW) = Rz(yaw) Ry(pitch) Rx(roll)``
       (``AP_CustomRotation::init``); 4.2 and newer convert it to ``COMPASS_ORIENT = 102``
       with ``CUST_ROT2_ROLL/PIT/YAW`` (the same angles);
    2. ``m_b += COMPASS_OFS`` (the offset is *added*, in milligauss, after the rotation);
    3. ``m_b *= COMPASS_SCALE``;
    4. ``m_b = S @ m_b`` with ``S = [[DIA_X, ODI_X, ODI_Y], [ODI_X, DIA_Y, ODI_Z],
       [ODI_Y, ODI_Z, DIA_Z]]`` (the soft-iron matrix, symmetric).

    Ours is ``R @ inv(D) @ (y - o)`` with ``R = R_body_mag``. Equal for every ``y`` when
    ``C = R``, ``S * SCALE = R @ inv(D) @ R.T`` and ``OFS = -R @ o`` (in milligauss:
    nT / 100). ``S`` is normalised to determinant 1 (its diagonal near 1, as ArduPilot's
    calibrator leaves it) and the overall size goes to ``COMPASS_SCALE`` (ArduPilot
    applies it only within ``[1/1.5, 1.5]``).

    Returns
    -------
    dict
        Parameter name -> value, in the order they are printed.

    """
    R = np.asarray(cal.R_body_mag, float)
    if cal.D is None:  # no soft iron estimated: ArduPilot's defaults, exactly
        S, scale = np.eye(3), 1.0
    else:
        M = R @ _d_inv(cal) @ R.T
        M = (M + M.T) / 2
        scale = float(np.cbrt(np.linalg.det(M)))
        S = M / scale
    ofs_mG = -(R @ _offset(cal)) / NT_PER_MILLIGAUSS
    roll, pitch, yaw = (math.degrees(a) for a in rpy_from_matrix(R))
    return {
        "COMPASS_OFS_X": ofs_mG[0], "COMPASS_OFS_Y": ofs_mG[1], "COMPASS_OFS_Z": ofs_mG[2],
        "COMPASS_DIA_X": S[0, 0], "COMPASS_DIA_Y": S[1, 1], "COMPASS_DIA_Z": S[2, 2],
        "COMPASS_ODI_X": S[0, 1], "COMPASS_ODI_Y": S[0, 2], "COMPASS_ODI_Z": S[1, 2],
        "COMPASS_SCALE": scale,
        "COMPASS_ORIENT": 100,
        "COMPASS_CUS_ROLL": roll, "COMPASS_CUS_PIT": pitch, "COMPASS_CUS_YAW": yaw,
    }


def ardupilot_correct(params: dict[str, float], m_mG: np.ndarray) -> np.ndarray:
    """Apply ArduPilot's compass correction (steps of :func:`ardupilot_params`) to rows."""
    C = matrix_from_rpy(*(math.radians(params[f"COMPASS_CUS_{k}"])
                          for k in ("ROLL", "PIT", "YAW")))
    p = params
    S = np.array([[p["COMPASS_DIA_X"], p["COMPASS_ODI_X"], p["COMPASS_ODI_Y"]],
                  [p["COMPASS_ODI_X"], p["COMPASS_DIA_Y"], p["COMPASS_ODI_Z"]],
                  [p["COMPASS_ODI_Y"], p["COMPASS_ODI_Z"], p["COMPASS_DIA_Z"]]])
    ofs = np.array([p["COMPASS_OFS_X"], p["COMPASS_OFS_Y"], p["COMPASS_OFS_Z"]])
    m = np.asarray(m_mG, float) @ C.T + ofs
    return (m * p["COMPASS_SCALE"]) @ S.T


def to_ardupilot(cal: Calibration, source: str = "") -> str:
    """ArduPilot parameter file text (``NAME,VALUE`` lines, Mission Planner style)."""
    p = ardupilot_params(cal)
    lines = [
        f"# magalign calibration {source}".rstrip(),
        "# offsets in milligauss (1 mGauss = 100 nT), added after the orientation;",
        "# COMPASS_ORIENT 100 = custom, COMPASS_CUS_ROLL/PIT/YAW in degrees,",
        "# R_body_mag = Rz(yaw) Ry(pitch) Rx(roll) (ArduPilot Matrix3::from_euler).",
        "# ArduPilot 4.2 and newer convert these to COMPASS_ORIENT 102 and",
        f"# CUST_ROT_ENABLE 1, CUST_ROT2_ROLL {p['COMPASS_CUS_ROLL']:.9g}, "
        f"CUST_ROT2_PIT {p['COMPASS_CUS_PIT']:.9g}, CUST_ROT2_YAW {p['COMPASS_CUS_YAW']:.9g}",
    ]
    # 9 significant digits: more than the float32 ArduPilot stores
    lines += [f"{k},{v}" if isinstance(v, int) else f"{k},{float(v) + 0.0:.9g}"
              for k, v in p.items()]
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------ MATLAB magcal

def magcal_A_b(cal: Calibration) -> tuple[np.ndarray, np.ndarray]:
    """MATLAB ``magcal``'s ``A`` (3x3) and ``b`` (1x3, nT): ``C = (D - b) * A``, row vectors.

    Ours in the mag frame is ``inv(D) @ (y - o)``; as a row vector ``(y - o) @ inv(D).T``,
    so ``A = inv(D).T = inv(D)`` (``D`` is symmetric) and ``b = o``. The rotation is not
    part of magcal's model (the result stays in the sensor frame).
    """
    return _d_inv(cal).T, _offset(cal)


def _matlab_matrix(a: np.ndarray) -> str:
    a = np.atleast_2d(a)
    return "[" + "; ".join(" ".join(_num(v) for v in row) for row in a) + "]"


def to_magcal(cal: Calibration, source: str = "") -> str:
    """MATLAB statements defining ``A`` and ``b`` (:func:`magcal_A_b`)."""
    A, b = magcal_A_b(cal)
    return "\n".join([
        f"% magalign calibration {source}".rstrip(),
        "% MATLAB magcal convention: calibrated = (raw - b) * A, one sample per row;",
        "% raw and b in nT (divide b by 1000 for microtesla); A is dimensionless.",
        f"A = {_matlab_matrix(A)};",
        f"b = {_matlab_matrix(b)};",
    ]) + "\n"


# ------------------------------------------------------------------ ROS 2 tf

def to_ros_tf(cal: Calibration, body_frame: str = "base_link", mag_frame: str = "mag") -> str:
    """Return a ``static_transform_publisher`` command: the mag frame's pose in the body frame.

    tf's transform from parent ``body_frame`` to child ``mag_frame`` maps child-frame
    vectors into the parent frame, ``v_body = R @ v_mag``: its rotation is ``R_body_mag``.
    """
    x, y, z, w = matrix_to_quat(np.asarray(cal.R_body_mag, float))
    if w < 0:  # the same rotation; a non-negative w reads more easily
        x, y, z, w = -x, -y, -z, -w
    return ("ros2 run tf2_ros static_transform_publisher --x 0 --y 0 --z 0 "
            f"--qx {_num(x)} --qy {_num(y)} --qz {_num(z)} --qw {_num(w)} "
            f"--frame-id {shlex.quote(body_frame)} --child-frame-id {shlex.quote(mag_frame)}\n")


# ------------------------------------------------------------------ YAML

def _yaml_scalar(v: Any) -> str:
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        f = float(v)
        if math.isnan(f):
            return ".nan"
        if math.isinf(f):
            return ".inf" if f > 0 else "-.inf"
        s = _num(f)
        if "e" in s:  # YAML 1.1 readers want a point in the mantissa and a signed exponent
            mant, exp = s.split("e")
            mant = mant if "." in mant else mant + ".0"
            exp = exp if exp[0] in "+-" else "+" + exp
            s = f"{mant}e{exp}"
        return s
    return json.dumps(str(v))  # a double-quoted YAML scalar


def _yaml_value(v: Any, indent: int) -> str:
    """Format the text after ``key:`` (flow lists for vectors, block lists for matrices)."""
    pad = " " * indent
    if isinstance(v, np.ndarray):
        v = v.tolist()
    if isinstance(v, dict):
        return "\n" + "\n".join(f"{pad}  {k}:{_yaml_value(x, indent + 2)}" for k, x in v.items())
    if isinstance(v, (list, tuple)):
        if v and all(isinstance(r, (list, tuple)) for r in v):
            return "\n" + "\n".join(f"{pad}  - [{', '.join(_yaml_scalar(x) for x in r)}]"
                                    for r in v)
        return " [" + ", ".join(_yaml_scalar(x) for x in v) + "]"
    return " " + _yaml_scalar(v)


def yaml_dict(cal: Calibration) -> dict[str, Any]:
    """Return the values the YAML export carries, as plain Python values (non-finite: None)."""
    d = cal.to_dict()
    keys = ("format", "R_body_mag", "rotvec_body_mag_deg", "sigma_rotvec_deg", "offset_nT",
            "sigma_offset_nT", "D", "sigma_D", "time_offset_s", "sigma_time_offset_s",
            "B_enu_nT", "estimator", "residual_rms_nT", "n_samples")
    out = {k: d.get(k) for k in keys}
    if d.get("verdict") is not None:
        out["verdict"] = d["verdict"]
    return out


def to_yaml(cal: Calibration, source: str = "") -> str:
    """Return a plain YAML document of the calibration (written without a YAML library)."""
    lines = [f"# magalign calibration {source}".rstrip(),
             "# R_body_mag maps mag-frame vectors into the body frame: v_body = R @ v_mag;",
             "# calibrated = R_body_mag @ inv(D) @ (raw - offset_nT); fields in nT, angles",
             "# in degrees, times in seconds; null = not estimated (or sigma unbounded)."]
    lines += [f"{k}:{_yaml_value(v, 0)}" for k, v in yaml_dict(cal).items()]
    return "\n".join(lines) + "\n"
