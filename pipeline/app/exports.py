"""A calibration in other tools' terms: ArduPilot, MATLAB magcal, ROS 2 tf, YAML.

More in docs/modules.md, ``pipeline.app.exports``.
"""

from __future__ import annotations

import json
import math
import re
import shlex
import textwrap
from typing import Any

import numpy as np

from pipeline.core.errors import InputError
from pipeline.core.geometry import matrix_to_quat
from pipeline.core.style import nT_text, num, unsigned_zeros
from pipeline.core.verdict import Status
from pipeline.model.calibration import Calibration

FORMATS = ("ardupilot", "magcal", "ros-tf", "yaml")

#: ArduPilot's compass unit: 1 milligauss = 1e-7 T = 100 nT.
NT_PER_MILLIGAUSS = 100.0

#: Comment lines are wrapped to this width (the reason of a verdict is one long sentence).
COMMENT_WIDTH = 96

#: The ``--estimate`` word that adds each optional term (CONVENTIONS, "Command line"); the
#: same words name the terms in a calibration's ``not_estimated``.
_ESTIMATE_WORD = {"offset_nT": "offset", "D": "soft_iron", "time_offset_s": "time_offset"}


# ------------------------------------------------------------------ shared pieces

def check_exportable(cal: Calibration, path: str | None = None) -> None:
    """Refuse a calibration whose numbers cannot describe a sensor, or that was refused.

    Raises
    ------
    InputError
        The verdict is REFUSED, ``R_body_mag`` is not a proper rotation, or ``D`` is not
        symmetric positive-definite.

    """
    if cal.verdict is not None and cal.verdict.status is Status.REFUSED:
        raise InputError(f"the calibration was refused ({cal.verdict.reason}); it is not "
                         "exported", path=path, hint="record the motion the reason asks for "
                         "and calibrate again")
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


def _check_rotation_determined(cal: Calibration, fmt: str, path: str | None) -> None:
    """Refuse a rotation with an undetermined axis where the format must carry all of it.

    Along an unobservable axis the rotation in calibration.json is not a measurement; an
    orientation or a transform has no way to leave one axis of a rotation out.
    """
    if cal.unobservable_axes_body:
        axes = "; ".join(_vec(a, "+.2f") for a in cal.unobservable_axes_body)
        raise InputError(
            f"R_body_mag: the recording did not determine the rotation about body axis "
            f"{axes}, and a {fmt} export cannot leave part of a rotation out; nothing is "
            "exported", path=path,
            hint="record rotations about a second axis and calibrate again; --format yaml "
            "exports the rotation with its unbounded sigma")


def _vec(v: Any, spec: str = ".3g") -> str:
    return "[" + ", ".join(num(float(x), spec) for x in v) + "]"


def _why_not_estimated(cal: Calibration, key: str) -> str:
    """Say why a term is null: the motion could not determine it, or it was not in the model."""
    word = _ESTIMATE_WORD[key]
    for d in cal.not_estimated:
        if d.get("term") == word:
            return f"asked for, but the motion could not determine it: {d.get('reason')}"
    return f"the fitted model has no {word} term; magalign calibrate --estimate {word} fits one"


def _verdict_lines(cal: Calibration) -> list[str]:
    v = cal.verdict
    if v is None:
        return ["verdict: none recorded (the file predates verdicts): compare the residual "
                f"RMS, {nT_text(cal.residual_rms_nT)} nT, with the sensor's noise before use"]
    lines = [f"verdict {v.status.value}: {' '.join(str(v.reason).split())}"]
    noise = "not measured (no still period)" if v.sensor_noise_nT is None else \
        f"{nT_text(v.sensor_noise_nT)} nT"
    lines.append(f"residual RMS {nT_text(v.residual_rms_nT)} nT; sensor noise {noise}")
    if v.status is Status.QUESTIONABLE:
        lines.append("QUESTIONABLE: check the reason above before loading these values")
    return lines


def _rotation_lines(cal: Calibration) -> list[str]:
    rv, sg = cal.rotvec_body_mag_deg, cal.sigma_rotvec_deg
    parts = [f"{num(v, '+.3f')} +- {num(s, '.3f') if np.isfinite(s) else 'inf'}"
             for v, s in zip(rv, sg, strict=True)]
    return ["R_body_mag maps mag-frame vectors into the body frame (v_body = R @ v_mag); "
            f"its rotation vector about body x, y, z [deg]: {', '.join(parts)}"]


def _held_lines(cal: Calibration, key: str) -> list[str]:
    """Say which part of the offset (``key`` ``offset_nT``) or of ``D`` (``D``) is held.

    The diagnosis fits iron in part when the motion determines only some of its components
    (``checks.undetermined_iron.held``: mag-frame unit vectors for the offset, unit symmetric
    matrices for ``D``); the exported value then carries a reference along them (no offset,
    an identity ``D``), not a measurement.
    """
    held = ((cal.checks or {}).get("undetermined_iron") or {}).get("held") or {}
    if key == "offset_nT" and cal.offset_nT is not None and held.get("hard_iron"):
        o = np.asarray(cal.offset_nT, dtype=float)
        return [f"the offset's component along mag-frame {_vec(u, '+.2f')} was not determined "
                "by the motion: it is held at "
                f"{num(float(o @ np.asarray(u, float)), '.0f')} nT, not "
                "measured (sigma_offset_nT gives its prior's sigma); tilt the platform more or "
                "give a reference field to determine it" for u in held["hard_iron"]]
    if key == "D" and cal.D is not None and held.get("soft_iron"):
        return ["D along " + "[" + ", ".join(_vec(r, "+.2f") for r in M) + "] (unit norm) "
                "was not determined by the motion: it is held at the identity's value there, "
                "not measured (sigma_D includes its prior's sigma); tilt the platform more or "
                "give a reference field to determine it" for M in held["soft_iron"]]
    return []


def _effects_line(cal: Calibration, tool: str) -> list[str]:
    if not cal.effects:
        return []
    return [f"calibration.json also models {', '.join(sorted(cal.effects))}; {tool} has no "
            "place for it: not in this file"]


#: A number and its unit stay on one line when a comment is wrapped.
_NUMBER_UNIT = re.compile(r"(\d) (%|nT|ms|deg|s)\b")


def _comment(prefix: str, lines: list[str]) -> list[str]:
    """Wrap each line as comments (continuations indented), blank lines kept as bare marks."""
    out: list[str] = []
    for line in lines:
        glued = _NUMBER_UNIT.sub("\\1\0\\2", line)
        out += [w.replace("\0", " ") for w in textwrap.wrap(
            glued, COMMENT_WIDTH, initial_indent=f"{prefix} ",
            subsequent_indent=f"{prefix}   ", break_long_words=False,
            break_on_hyphens=False)] or [prefix]
    return out


def _header(prefix: str, cal: Calibration, path: str | None, notes: list[str]) -> list[str]:
    """Return the comment block a file starts with: its source, its verdict, then ``notes``.

    The source line is not wrapped: a path cut in two cannot be copied.
    """
    where = " ".join(str(path).splitlines())  # a comment is one line
    src = f"{prefix} magalign calibration from {where}" if path else \
        f"{prefix} magalign calibration"
    return [src, *_comment(prefix, _verdict_lines(cal) + notes)]


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

    Only what was estimated is returned: without ``D`` there is no ``DIA``, ``ODI`` or
    ``SCALE``, without an offset no ``OFS`` (:func:`to_ardupilot` says so in comments), so
    loading the file leaves the autopilot's own values of those in place.

    Returns
    -------
    dict
        Parameter name -> value, in the order they are printed.

    """
    R = np.asarray(cal.R_body_mag, float)
    out: dict[str, float] = {}
    if cal.offset_nT is not None:
        ofs_mG = -(R @ _offset(cal)) / NT_PER_MILLIGAUSS
        out |= {"COMPASS_OFS_X": ofs_mG[0], "COMPASS_OFS_Y": ofs_mG[1],
                "COMPASS_OFS_Z": ofs_mG[2]}
    if cal.D is not None:
        M = R @ _d_inv(cal) @ R.T
        M = (M + M.T) / 2
        scale = float(np.cbrt(np.linalg.det(M)))
        S = M / scale
        out |= {"COMPASS_DIA_X": S[0, 0], "COMPASS_DIA_Y": S[1, 1], "COMPASS_DIA_Z": S[2, 2],
                "COMPASS_ODI_X": S[0, 1], "COMPASS_ODI_Y": S[0, 2], "COMPASS_ODI_Z": S[1, 2],
                "COMPASS_SCALE": scale}
    roll, pitch, yaw = (math.degrees(a) for a in rpy_from_matrix(R))
    out |= {"COMPASS_ORIENT": 100,
            "COMPASS_CUS_ROLL": roll, "COMPASS_CUS_PIT": pitch, "COMPASS_CUS_YAW": yaw}
    return out


#: ArduPilot's own defaults of the parameters :func:`ardupilot_params` may leave out (what a
#: fresh autopilot applies; one with a compass calibration applies that instead).
ARDUPILOT_DEFAULTS = {"COMPASS_OFS_X": 0.0, "COMPASS_OFS_Y": 0.0, "COMPASS_OFS_Z": 0.0,
                      "COMPASS_DIA_X": 1.0, "COMPASS_DIA_Y": 1.0, "COMPASS_DIA_Z": 1.0,
                      "COMPASS_ODI_X": 0.0, "COMPASS_ODI_Y": 0.0, "COMPASS_ODI_Z": 0.0,
                      "COMPASS_SCALE": 1.0}


def ardupilot_correct(params: dict[str, float], m_mG: np.ndarray) -> np.ndarray:
    """Apply ArduPilot's compass correction (steps of :func:`ardupilot_params`) to rows.

    A parameter missing from ``params`` takes its value from :data:`ARDUPILOT_DEFAULTS`.
    """
    C = matrix_from_rpy(*(math.radians(params[f"COMPASS_CUS_{k}"])
                          for k in ("ROLL", "PIT", "YAW")))
    p = ARDUPILOT_DEFAULTS | dict(params)
    S = np.array([[p["COMPASS_DIA_X"], p["COMPASS_ODI_X"], p["COMPASS_ODI_Y"]],
                  [p["COMPASS_ODI_X"], p["COMPASS_DIA_Y"], p["COMPASS_ODI_Z"]],
                  [p["COMPASS_ODI_Y"], p["COMPASS_ODI_Z"], p["COMPASS_DIA_Z"]]])
    ofs = np.array([p["COMPASS_OFS_X"], p["COMPASS_OFS_Y"], p["COMPASS_OFS_Z"]])
    m = np.asarray(m_mG, float) @ C.T + ofs
    return (m * p["COMPASS_SCALE"]) @ S.T


def to_ardupilot(cal: Calibration, path: str | None = None) -> str:
    """ArduPilot parameter file text (``NAME,VALUE`` lines, Mission Planner style).

    Raises
    ------
    InputError
        The calibration was refused, is not a sensor's, or leaves a rotation axis
        undetermined (an orientation cannot leave one out).

    """
    check_exportable(cal, path)
    _check_rotation_determined(cal, "ArduPilot", path)
    p = ardupilot_params(cal)
    notes = _rotation_lines(cal) + [
        "COMPASS_ORIENT 100 = custom, COMPASS_CUS_ROLL/PIT/YAW in degrees, "
        "R_body_mag = Rz(yaw) Ry(pitch) Rx(roll) (ArduPilot Matrix3::from_euler).",
        "ArduPilot 4.2 and newer convert these to COMPASS_ORIENT 102 and CUST_ROT_ENABLE 1, "
        f"CUST_ROT2_ROLL {num(p['COMPASS_CUS_ROLL'], '.9g')}, CUST_ROT2_PIT "
        f"{num(p['COMPASS_CUS_PIT'], '.9g')}, CUST_ROT2_YAW {num(p['COMPASS_CUS_YAW'], '.9g')}",
    ]
    if cal.offset_nT is None:
        notes.append("COMPASS_OFS_X/Y/Z are left out, so the autopilot keeps its own: the "
                     f"offset was not estimated ({_why_not_estimated(cal, 'offset_nT')}).")
    else:
        notes.append("COMPASS_OFS_X/Y/Z: the offset in the body frame, negated (ArduPilot "
                     "adds it after the orientation), in milligauss (1 mGauss = 100 nT)")
        notes += _held_lines(cal, "offset_nT")
    notes += _held_lines(cal, "D")
    if cal.D is None:
        notes.append("COMPASS_DIA_*, COMPASS_ODI_* and COMPASS_SCALE are left out, so the "
                     "autopilot keeps its own: the soft-iron matrix D was not estimated ("
                     f"{_why_not_estimated(cal, 'D')}).")
    if cal.offset_nT is None or cal.D is None:
        # both apply after the orientation, in the frame it rotates into
        notes.append("ArduPilot applies its own offsets and soft-iron matrix after the "
                     "orientation: values it calibrated under a different orientation need "
                     "its compass calibration again.")
    if cal.time_offset_s is not None:
        notes.append(f"time offset {num(cal.time_offset_s * 1e3, '+.1f')} ms (positive: the "
                     "magnetometer "
                     "stamps are late): ArduPilot has no parameter for it, not in "
                     "this file")
    notes += _effects_line(cal, "ArduPilot")
    lines = _header("#", cal, path, notes)
    # 9 significant digits: more than the float32 ArduPilot stores
    lines += [f"{k},{v}" if isinstance(v, int) else f"{k},{num(float(v), '.9g')}"
              for k, v in p.items()]
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------ MATLAB magcal

def magcal_A_b(cal: Calibration) -> tuple[np.ndarray | None, np.ndarray | None]:
    """MATLAB ``magcal``'s ``A`` (3x3) and ``b`` (1x3, nT): ``C = (D - b) * A``, row vectors.

    Ours in the mag frame is ``inv(D) @ (y - o)``; as a row vector ``(y - o) @ inv(D).T``,
    so ``A = inv(D).T = inv(D)`` (``D`` is symmetric) and ``b = o``. The rotation is not
    part of magcal's model (the result stays in the sensor frame). ``A`` is None when ``D``
    was not estimated, ``b`` when the offset was not.
    """
    A = None if cal.D is None else _d_inv(cal).T
    b = None if cal.offset_nT is None else _offset(cal)
    return A, b


def _matlab_matrix(a: np.ndarray) -> str:
    a = np.atleast_2d(a)
    return "[" + "; ".join(" ".join(_num(v) for v in row) for row in a) + "]"


#: Where the rotation is, for the formats that cannot carry it.
_ROTATION_ELSEWHERE = ("the rotation is R_body_mag in calibration.json, and magalign export "
                       "--format yaml or ros-tf writes it")


def to_magcal(cal: Calibration, path: str | None = None) -> str:
    """MATLAB statements defining ``A`` and ``b`` (:func:`magcal_A_b`), each only if estimated.

    Raises
    ------
    InputError
        The calibration was refused or is not a sensor's, or neither ``D`` nor the offset
        was estimated (the file would define nothing).

    """
    check_exportable(cal, path)
    A, b = magcal_A_b(cal)
    if A is None and b is None:
        raise InputError(
            "nothing to export as magcal: D and offset_nT were not estimated (null), and the "
            "rotation is not part of magcal's model", path=path,
            hint="the rotation: --format yaml or ros-tf; magalign calibrate --estimate "
            "offset,soft_iron fits D and the offset")
    notes = [
        "MATLAB magcal convention: calibrated = (raw - b) * A, one sample per row; raw and b "
        "in nT (divide b by 1000 for microtesla); A is dimensionless.",
        "The misalignment (the rotation from the magnetometer's axes to the body's) is not "
        "part of magcal's model: A and b correct the field in the magnetometer's own frame; "
        f"{_ROTATION_ELSEWHERE}.",
    ]
    if A is None:
        notes.append("A is left out, keep your own: the soft-iron matrix D was not "
                     f"estimated ({_why_not_estimated(cal, 'D')}).")
    if b is None:
        notes.append("b is left out, keep your own: the offset was not estimated ("
                     f"{_why_not_estimated(cal, 'offset_nT')}).")
    notes += _held_lines(cal, "D") + _held_lines(cal, "offset_nT")
    if cal.time_offset_s is not None:
        notes.append(f"time offset {num(cal.time_offset_s * 1e3, '+.1f')} ms (positive: the "
                     "magnetometer "
                     "stamps are late): not part of magcal's model")
    notes += _effects_line(cal, "magcal")
    lines = _header("%", cal, path, notes)
    if A is not None:
        lines.append(f"A = {_matlab_matrix(A)};")
    if b is not None:
        lines.append(f"b = {_matlab_matrix(b)};")
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------ ROS 2 tf

def to_ros_tf(cal: Calibration, body_frame: str = "base_link", mag_frame: str = "mag",
              path: str | None = None) -> str:
    """Return a ``static_transform_publisher`` command: the mag frame's pose in the body frame.

    tf's transform from parent ``body_frame`` to child ``mag_frame`` maps child-frame
    vectors into the parent frame, ``v_body = R @ v_mag``: its rotation is ``R_body_mag``.
    Shell comments before the command carry the verdict (a script, or ``eval``, skips them).

    Raises
    ------
    InputError
        The calibration was refused or is not a sensor's, or leaves a rotation axis
        undetermined (a transform cannot leave one out).

    """
    check_exportable(cal, path)
    _check_rotation_determined(cal, "ros-tf", path)
    x, y, z, w = matrix_to_quat(np.asarray(cal.R_body_mag, float))
    if w < 0:  # the same rotation; a non-negative w reads more easily
        x, y, z, w = -x, -y, -z, -w
    notes = _rotation_lines(cal) + [
        "No translation was estimated: --x --y --z are 0, not a measured lever arm."]
    terms = [k for k in ("offset_nT", "D", "time_offset_s") if getattr(cal, k) is not None]
    if terms:
        notes.append(f"calibration.json also holds {', '.join(terms)}; a transform carries "
                     "only the rotation: magalign export --format yaml writes "
                     + ("it" if len(terms) == 1 else "them"))
    notes += _effects_line(cal, "a transform")
    lines = _header("#", cal, path, notes)
    lines.append("ros2 run tf2_ros static_transform_publisher --x 0 --y 0 --z 0 "
                 f"--qx {_num(x)} --qy {_num(y)} --qz {_num(z)} --qw {_num(w)} "
                 f"--frame-id {shlex.quote(body_frame)} --child-frame-id "
                 f"{shlex.quote(mag_frame)}")
    return "\n".join(lines) + "\n"


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
    keys = ("format", "R_body_mag", "rotvec_body_mag_deg", "sigma_rotvec_deg",
            "unobservable_axes_body", "offset_nT", "sigma_offset_nT", "D", "sigma_D",
            "time_offset_s", "sigma_time_offset_s", "B_enu_nT", "estimator",
            "residual_rms_nT", "n_samples")
    out = {k: d.get(k) for k in keys}
    if d.get("verdict") is not None:
        out["verdict"] = d["verdict"]
    return out


def to_yaml(cal: Calibration, path: str | None = None) -> str:
    """Return a plain YAML document of the calibration (written without a YAML library).

    A term that was not estimated stays as ``null`` (as in calibration.json, never a
    default value), with a comment above it saying why.

    Raises
    ------
    InputError
        The calibration was refused or is not a sensor's.

    """
    check_exportable(cal, path)
    notes = [
        "R_body_mag maps mag-frame vectors into the body frame: v_body = R @ v_mag; "
        "calibrated = R_body_mag @ inv(D) @ (raw - offset_nT); fields in nT, angles in "
        "degrees, times in seconds; null = not estimated (or a sigma without bound)."]
    notes += _effects_line(cal, "this YAML")
    lines = _header("#", cal, path, notes)
    for k, v in yaml_dict(cal).items():
        if k in _ESTIMATE_WORD and v is None:
            lines += _comment("#", [f"{k}: not estimated: {_why_not_estimated(cal, k)}"])
        if k in ("offset_nT", "D"):
            lines += _comment("#", _held_lines(cal, k))
        if k == "sigma_rotvec_deg" and cal.unobservable_axes_body:
            lines += _comment("#", ["the recording did not determine the rotation about "
                                    "unobservable_axes_body: its sigma is null (unbounded) "
                                    "and R_body_mag about those axes is not a measurement"])
        lines.append(f"{k}:{_yaml_value(v, 0)}")
    return "\n".join(lines) + "\n"


def export_text(cal: Calibration, fmt: str, path: str | None = None, *,
                body_frame: str = "base_link", mag_frame: str = "mag") -> str:
    """Return the calibration in format ``fmt`` (one of :data:`FORMATS`).

    Raises
    ------
    InputError
        The calibration cannot be exported in this format (each ``to_*`` says when).

    """
    # the verdict's and the checks' own words carry numbers formatted elsewhere
    if fmt == "ardupilot":
        return unsigned_zeros(to_ardupilot(cal, path))
    if fmt == "magcal":
        return unsigned_zeros(to_magcal(cal, path))
    if fmt == "ros-tf":
        return unsigned_zeros(to_ros_tf(cal, body_frame, mag_frame, path))
    if fmt == "yaml":
        return unsigned_zeros(to_yaml(cal, path))
    raise ValueError(f"unknown export format {fmt!r}; one of {', '.join(FORMATS)}")
