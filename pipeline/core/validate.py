"""Checks of what magalign reads back from its own output files.

More in docs/modules.md, ``pipeline.core.validate``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal, overload

import numpy as np

from pipeline.core.errors import InputError
from pipeline.core.geometry import quat_to_matrix, rotvec_to_quat, so3_log

CALIBRATION_FORMAT = "magalign.calibration/1"
DIAGNOSIS_FORMAT = "magalign.diagnosis/1"
VERDICT_STATUSES = ("OK", "QUESTIONABLE", "REFUSED")

#: a rotation matrix read back must be orthonormal to this (JSON keeps every bit of a float;
#: a hand-rounded matrix to 7 digits still passes)
ORTHONORMAL_TOL = 1e-6
#: the stored rotation vector must describe the stored matrix to this angle (deg)
ROTVEC_TOL_DEG = 1e-5
#: unit vectors (unobservable axes) must have unit norm to this
UNIT_TOL = 1e-6

_HINT = "regenerate it with magalign calibrate (or process); do not edit it by hand"


#: the first bytes of every MCAP file (its magic)
MCAP_MAGIC = b"\x89MCAP"


def read_json_object(path: str | Path, what: str, hint: str | None = None) -> dict[str, Any]:
    """Read the JSON object in ``path``, which should be ``what`` (e.g. "a calibration.json").

    Any other kind of file (a recording, a folder, an empty or binary file, a missing path)
    is an :class:`InputError` whose one line names the file and what it is instead.
    """
    p = Path(path)
    if p.is_dir():
        raise InputError(f"a folder, not {what}", path=p, hint=hint)
    try:
        data = p.read_bytes()
    except FileNotFoundError as exc:
        raise InputError(f"no such file (expected {what})", path=p) from exc
    except OSError as exc:
        raise InputError(f"cannot read {what}: {exc.strerror}", path=p) from exc
    if data.startswith(MCAP_MAGIC):
        raise InputError(f"an MCAP recording, not {what}", path=p, hint=hint)
    if not data.strip():
        raise InputError(f"an empty file, not {what}", path=p, hint=hint)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(f"a binary file, not {what}", path=p, hint=hint) from exc
    try:
        d = json.loads(text)
    except ValueError as exc:
        raise InputError(f"not valid JSON, so not {what}: {exc}", path=p, hint=hint) from exc
    if not isinstance(d, dict):
        raise InputError(f"not {what}: it holds a JSON {type(d).__name__}, not an object",
                         path=p, hint=hint)
    return d


class _Checker:
    """Raise an InputError naming the file and the dotted field."""

    def __init__(self, path: str | Path | None, what: str = "calibration"):
        self.path = None if path is None else str(path)
        self.what = what

    def fail(self, field: str, problem: str) -> InputError:
        return InputError(f"{self.what} field {field}: {problem}", path=self.path, hint=_HINT)

    def number(self, d: Mapping, key: str, *, nullable: bool = False, lo: float | None = None,
               integer: bool = False) -> float | None:
        if key not in d:
            if nullable:
                return None
            raise self.fail(key, "is missing")
        return self.scalar(d[key], key, nullable=nullable, lo=lo, integer=integer)

    def scalar(self, v: Any, field: str, *, nullable: bool = False, lo: float | None = None,
               integer: bool = False) -> float | None:
        if v is None:
            if nullable:
                return None
            raise self.fail(field, "is null, a number is required")
        if isinstance(v, bool) or not isinstance(v, int | float):
            raise self.fail(field, f"must be a number, not {type(v).__name__}")
        if integer and not (isinstance(v, int) or float(v).is_integer()):
            raise self.fail(field, f"must be a whole number, not {v!r}")
        if not math.isfinite(v):
            raise self.fail(field, f"must be finite, not {v!r}")
        if lo is not None and v < lo:
            raise self.fail(field, f"must be at least {lo:g}, not {v!r}")
        return float(v)

    @overload
    def array(self, d: Mapping, key: str, shape: tuple[int, ...], *,
              nullable: Literal[False] = False, null_items: bool = False,
              lo: float | None = None) -> np.ndarray: ...

    @overload
    def array(self, d: Mapping, key: str, shape: tuple[int, ...], *, nullable: bool,
              null_items: bool = False, lo: float | None = None) -> np.ndarray | None: ...

    def array(self, d: Mapping, key: str, shape: tuple[int, ...], *, nullable: bool = False,
              null_items: bool = False, lo: float | None = None) -> np.ndarray | None:
        """Return a nested list of numbers of ``shape`` as an array (null items: inf)."""
        if key not in d or d[key] is None:
            if nullable:
                return None
            raise self.fail(key, "is missing" if key not in d else "is null")
        out = np.empty(shape)
        self._fill(d[key], key, shape, out, (), null_items, lo)
        return out

    def _fill(self, v: Any, field: str, shape: tuple[int, ...], out: np.ndarray,
              at: tuple[int, ...], null_items: bool, lo: float | None) -> None:
        if not shape:
            x = self.scalar(v, field, nullable=null_items, lo=lo)
            out[at] = np.inf if x is None else x
            return
        if not isinstance(v, list) or len(v) != shape[0]:
            want = "x".join(str(n) for n in shape)
            got = f"{len(v)} items" if isinstance(v, list) else type(v).__name__
            raise self.fail(field, f"must be a list of shape {want}, not {got}")
        for i, item in enumerate(v):
            self._fill(item, f"{field}[{i}]", shape[1:], out, (*at, i), null_items, lo)

    def rotation(self, R: np.ndarray, field: str) -> None:
        err = float(np.abs(R @ R.T - np.eye(3)).max())
        if err > ORTHONORMAL_TOL:
            raise self.fail(field, f"is not a rotation matrix (R R^T differs from I by {err:.3g})")
        det = float(np.linalg.det(R))
        if det <= 0:
            raise self.fail(field, f"is a reflection, not a rotation (determinant {det:.6g})")


def _rotvec_matrix(rotvec_deg: np.ndarray) -> np.ndarray:

    return quat_to_matrix(rotvec_to_quat(np.radians(rotvec_deg)))


def check_calibration_dict(d: Any, path: str | Path | None = None) -> None:
    """Check a ``calibration.json`` object field by field (CONVENTIONS, "Output files").

    Parameters
    ----------
    d : object
        The parsed JSON.
    path : path, optional
        The file it was read from, named in the error.

    Raises
    ------
    InputError
        Naming the file and the first field that is missing, of the wrong type or shape,
        not finite, or inconsistent: ``R_body_mag`` not orthonormal or not of determinant
        +1, ``rotvec_body_mag_deg`` not the rotation of ``R_body_mag`` (within
        :data:`ROTVEC_TOL_DEG`), sigmas negative, ``D`` not symmetric positive-definite,
        unobservable axes not unit vectors, a ``verdict`` not of the CONVENTIONS shape.

    """
    c = _Checker(path)
    if not isinstance(d, dict):
        raise InputError(f"calibration must be a JSON object, not {type(d).__name__}",
                         path=c.path, hint=_HINT)
    fmt = d.get("format")
    if fmt != CALIBRATION_FORMAT:
        raise InputError(f"not a {CALIBRATION_FORMAT} calibration (format is {fmt!r})",
                         path=c.path, hint="pass a calibration.json written by magalign")
    R = c.array(d, "R_body_mag", (3, 3))
    c.rotation(R, "R_body_mag")
    rv = c.array(d, "rotvec_body_mag_deg", (3,))

    ang = float(np.degrees(np.linalg.norm(so3_log(_rotvec_matrix(rv) @ R.T))))
    if not ang <= ROTVEC_TOL_DEG:
        raise c.fail("rotvec_body_mag_deg", f"does not describe R_body_mag (they differ by "
                     f"{ang:.3g} deg): one of them was changed without the other")
    c.array(d, "sigma_rotvec_deg", (3,), null_items=True, lo=0.0)
    axes = d.get("unobservable_axes_body", [])
    if axes is None:
        axes = []
    if not isinstance(axes, list) or len(axes) > 3:
        raise c.fail("unobservable_axes_body", "must be a list of at most 3 unit vectors")
    for i in range(len(axes)):
        a = c.array({f"unobservable_axes_body[{i}]": axes[i]}, f"unobservable_axes_body[{i}]",
                    (3,))
        if abs(float(np.linalg.norm(a)) - 1.0) > UNIT_TOL:
            raise c.fail(f"unobservable_axes_body[{i}]", "is not a unit vector")
    D = c.array(d, "D", (3, 3), nullable=True)
    if D is not None:
        scale = max(float(np.abs(D).max()), 1e-300)
        if float(np.abs(D - D.T).max()) > 1e-6 * scale:
            raise c.fail("D", "is not symmetric")
        if float(np.linalg.eigvalsh(D).min()) <= 0:
            raise c.fail("D", "is not positive-definite")
    c.array(d, "sigma_D", (3, 3), nullable=True, null_items=True, lo=0.0)
    c.array(d, "offset_nT", (3,), nullable=True)
    c.array(d, "sigma_offset_nT", (3,), nullable=True, null_items=True, lo=0.0)
    c.number(d, "time_offset_s", nullable=True)
    c.number(d, "sigma_time_offset_s", nullable=True, lo=0.0)
    c.array(d, "B_enu_nT", (3,))
    c.array(d, "sigma_B_enu_nT", (3,), nullable=True, null_items=True, lo=0.0)
    if not isinstance(d.get("estimator"), str):
        raise c.fail("estimator", "must be a string (the estimator's name)")
    c.number(d, "residual_rms_nT", lo=0.0)
    c.number(d, "n_samples", lo=0.0, integer=True)
    Rn = c.array(d, "R_nominal_body_mag", (3, 3), nullable=True)
    if Rn is not None:
        c.rotation(Rn, "R_nominal_body_mag")
    c.array(d, "rotvec_from_nominal_deg", (3,), nullable=True)
    if not isinstance(d.get("effects", {}) or {}, dict):
        raise c.fail("effects", "must be an object (effect name -> params)")
    warns = d.get("warnings", []) or []
    if not isinstance(warns, list) or not all(isinstance(w, str) for w in warns):
        raise c.fail("warnings", "must be a list of strings")
    if "verdict" in d and d["verdict"] is not None:
        check_verdict(d["verdict"], c)


def check_verdict(v: Any, c: _Checker) -> None:
    """Check a calibration's ``verdict`` (CONVENTIONS): status, reason, noise, residual."""
    if not isinstance(v, dict):
        raise c.fail("verdict", "must be an object {status, reason, sensor_noise_nT, "
                     "residual_rms_nT}")
    if v.get("status") not in VERDICT_STATUSES:
        raise c.fail("verdict.status", f"must be one of {', '.join(VERDICT_STATUSES)}, not "
                     f"{v.get('status')!r}")
    if v.get("reason") is not None and not isinstance(v.get("reason"), str):
        raise c.fail("verdict.reason", "must be a string")
    for key in ("sensor_noise_nT", "residual_rms_nT"):
        c.scalar(v.get(key), f"verdict.{key}", nullable=True, lo=0.0)


def check_diagnosis_dict(d: Any, path: str | Path | None = None) -> None:
    """Check the parts of a ``diagnosis.json`` object that ``regress`` compares.

    Raises
    ------
    InputError
        Naming the file and the field: ``findings`` not a list of objects each with a
        string ``effect`` and an object ``params``.

    """
    c = _Checker(path, "diagnosis")
    if not isinstance(d, dict):
        raise InputError(f"diagnosis must be a JSON object, not {type(d).__name__}",
                         path=c.path, hint=_HINT)
    fmt = d.get("format", DIAGNOSIS_FORMAT)
    if fmt != DIAGNOSIS_FORMAT:
        raise InputError(f"not a {DIAGNOSIS_FORMAT} diagnosis (format is {fmt!r})",
                         path=c.path, hint=_HINT)
    findings = d.get("findings", [])
    if not isinstance(findings, list):
        raise c.fail("findings", "must be a list")
    for i, f in enumerate(findings):
        if not isinstance(f, dict) or not isinstance(f.get("effect"), str):
            raise c.fail(f"findings[{i}].effect", "must be an effect name")
        if not isinstance(f.get("params", {}), dict):
            raise c.fail(f"findings[{i}].params", "must be an object")


def check_metrics_dict(d: Any, path: str | Path | None = None) -> None:
    """Check that a ``metrics.json`` holds an object (its numbers are compared leaf by leaf).

    Raises
    ------
    InputError
        When it is not a JSON object, or ``scopes`` is present but not a list.

    """
    if not isinstance(d, dict):
        raise InputError(f"metrics must be a JSON object, not {type(d).__name__}",
                         path=None if path is None else str(path), hint=_HINT)
    if "scopes" in d and not isinstance(d["scopes"], list):
        raise _Checker(path, "metrics").fail("scopes", "must be a list")
