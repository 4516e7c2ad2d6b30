"""A fitted calibration: a frozen value, kept apart from the estimator that made it (imucal).

``calibration.json`` follows CONVENTIONS.md, format ``magalign.calibration/1``.

Model (CONVENTIONS): ``y_mag(t) = D @ R_body_mag.T @ C_enu_body(t - tau).T @ B_enu + o + e``;
restoring inverts it: ``b_enu = C_enu_body(t - tau) @ R_body_mag @ inv(D) @ (y_mag - o - e)``.
Both are :mod:`pipeline.model.forward` (:meth:`Calibration.predict`, :meth:`Calibration.restore`).
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from pipeline.core.errors import InputError
from pipeline.core.geometry import matrix_to_quat, quat_to_rotvec
from pipeline.core.style import unsigned_zeros_in
from pipeline.core.validate import check_calibration_dict, read_json_object
from pipeline.core.verdict import Verdict
from pipeline.core.vocabulary import EffectKind
from pipeline.model.effects import EFFECTS
from pipeline.model.forward import ForwardModel, predict, restore

if TYPE_CHECKING:
    from pipeline.core.recording import AttitudeSeries, PositionSeries
    from pipeline.model.forward import ForwardModel, Restoration

FORMAT = "magalign.calibration/1"


def _entries(p: Any) -> list[dict]:
    """Return the params of one kind in ``effects``: a dict, or a list of them (CONVENTIONS)."""
    if p is None:
        return []
    return [x for x in (p if isinstance(p, list) else [p]) if isinstance(x, dict)]

#: Numerical floor of a rotation sigma, deg. Below it a rotation is not known, whatever the
#: noise: the attitude arrives rounded. A single-precision angle of up to 360 deg is rounded
#: to 2**-15 deg (a uniform error of standard deviation 2**-15 / sqrt(12) = 8.8e-6 deg), a
#: single-precision quaternion component to 2**-24 (up to 6.8e-6 deg of rotation); the float64
#: solve itself settles to about 1e-14 deg (noise-free simulations). 1e-5 deg of a
#: 50,000 nT field is 0.009 nT, below any magnetometer's noise: the floor shows only on
#: noise-free data, where it keeps a sigma of 1e-15 deg from being read as a precision.
SIGMA_FLOOR_DEG = 1e-5


def _arr(x: Any, shape: tuple[int, ...] | None = None) -> np.ndarray | None:
    if x is None:
        return None
    a = np.array(x, dtype=float)
    if shape is not None:
        a = a.reshape(shape)
    a.flags.writeable = False
    return a


def _list(x: np.ndarray | None) -> Any:
    if x is None:
        return None
    a = np.asarray(x, dtype=float)
    if np.all(np.isfinite(a)):
        return a.tolist()
    # JSON has no inf: an unobservable (infinite-sigma) entry is written as null.
    return _nulls(a)


def _jsonable(x: Any) -> Any:
    """Plain JSON values (numpy scalars and arrays converted, non-finite floats as null)."""
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, (np.floating, float)):
        return float(x) if np.isfinite(x) else None
    if isinstance(x, (np.integer,)):
        return int(x)
    return x


def _nulls(a: np.ndarray) -> Any:
    if a.ndim == 0:
        return float(a) if np.isfinite(a) else None
    return [_nulls(v) for v in a]


@dataclass(frozen=True)
class Calibration:
    """A fitted misalignment calibration.

    Attributes
    ----------
    R_body_mag : ndarray, shape (3, 3)
        Rotation mapping mag-frame vectors into the body frame (Li 2020, Eq. 1).
    sigma_rotvec_deg : ndarray, shape (3,)
        1-sigma of the rotation error about body x, y, z (deg); ``inf`` along unobservable axes;
        never below :data:`SIGMA_FLOOR_DEG`.
    unobservable_axes_body : tuple of ndarray (3,)
        Unit vectors (body frame) about which the data do not determine the rotation.
    B_enu_nT : ndarray, shape (3,)
        Background field in ENU used or estimated.
    estimator : str
    residual_rms_nT : float
    n_samples : int
    D : ndarray (3, 3) or None
        Symmetric positive-definite scale / soft-iron matrix.
    offset_nT : ndarray (3,) or None
        Offset ``o`` in the mag frame.
    time_offset_s : float or None
        ``tau``; positive when the magnetometer stamps are late.
    sigma_D, sigma_offset_nT, sigma_time_offset_s, sigma_B_enu_nT
        1-sigma twins.
    R_nominal_body_mag : ndarray (3, 3) or None
        Nominal mounting given in the configuration; the result is then also reported as the
        small rotation from it.
    effects : dict
        Further model terms (CONVENTIONS effect names -> params), e.g. ``eddy_current``.
    warnings : tuple of str
        Observability and data-quality warnings in words.
    verdict : Verdict or None
        OK, QUESTIONABLE or REFUSED with the reason (:mod:`pipeline.core.verdict`).
    n_eff : float or None
        Effective number of independent samples behind the rotation's sigma (the samples
        divided by the inflation of its variance by correlated residuals).
    not_estimated : tuple of dict
        ``{term, reason}`` for requested terms the motion could not determine.
    checks : dict
        What the estimator's global checks found (JSON values): ``split`` (halves),
        ``starts`` (multi-start), ``n_eff_fraction``, ``refusals`` and ``doubts``; the
        diagnosis' ``fit_samples`` ``{n, stride, of}`` and, for a long recording analysed in
        windows, ``analysed_samples`` ``{n, of, windows}`` (the samples its analysis saw).
    sample_hold : dict or None
        ``{native_rate_hz, repeated_fraction}`` when the magnetometer's messages repeat its
        samples (sample-and-hold). Whether the fit left the repeats out is in its warning and
        in ``checks["fit_samples"]``; the restore's handling is in ``effects["sample_hold"]``.

    """

    R_body_mag: np.ndarray
    sigma_rotvec_deg: np.ndarray
    B_enu_nT: np.ndarray
    estimator: str
    residual_rms_nT: float
    n_samples: int
    unobservable_axes_body: tuple[np.ndarray, ...] = ()
    D: np.ndarray | None = None
    offset_nT: np.ndarray | None = None
    time_offset_s: float | None = None
    sigma_D: np.ndarray | None = None
    sigma_offset_nT: np.ndarray | None = None
    sigma_time_offset_s: float | None = None
    sigma_B_enu_nT: np.ndarray | None = None
    R_nominal_body_mag: np.ndarray | None = None
    effects: dict = field(default_factory=dict)
    warnings: tuple[str, ...] = ()
    verdict: Verdict | None = None
    n_eff: float | None = None
    not_estimated: tuple[dict, ...] = ()
    checks: dict = field(default_factory=dict)
    sample_hold: dict | None = None

    def __post_init__(self) -> None:
        set_ = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731
        set_("R_body_mag", _arr(self.R_body_mag, (3, 3)))
        sig = _arr(self.sigma_rotvec_deg, (3,))
        if sig is not None:
            # the numerical floor (idempotent: a calibration read back keeps its sigmas)
            sig = np.where(np.isnan(sig), sig, np.fmax(sig, SIGMA_FLOOR_DEG))
        set_("sigma_rotvec_deg", sig)
        set_("B_enu_nT", _arr(self.B_enu_nT, (3,)))
        set_("D", _arr(self.D, (3, 3)))
        set_("offset_nT", _arr(self.offset_nT, (3,)))
        set_("sigma_D", _arr(self.sigma_D, (3, 3)))
        set_("sigma_offset_nT", _arr(self.sigma_offset_nT, (3,)))
        set_("sigma_B_enu_nT", _arr(self.sigma_B_enu_nT, (3,)))
        set_("R_nominal_body_mag", _arr(self.R_nominal_body_mag, (3, 3)))
        set_("unobservable_axes_body", tuple(_arr(a, (3,)) for a in self.unobservable_axes_body))
        set_("warnings", tuple(self.warnings))
        set_("not_estimated", tuple(self.not_estimated))
        if self.time_offset_s is not None:
            set_("time_offset_s", float(self.time_offset_s))

    # ------------------------------------------------------------------ derived values
    @property
    def rotvec_body_mag_deg(self) -> np.ndarray:
        """Rotation vector of ``R_body_mag`` in degrees."""
        return np.degrees(quat_to_rotvec(matrix_to_quat(self.R_body_mag)))

    @property
    def rotvec_from_nominal_deg(self) -> np.ndarray | None:
        """Rotation vector (deg) of ``R_body_mag @ R_nominal.T``, or None without a nominal."""
        if self.R_nominal_body_mag is None:
            return None
        dR = self.R_body_mag @ self.R_nominal_body_mag.T
        return np.degrees(quat_to_rotvec(matrix_to_quat(dR)))

    # ------------------------------------------------------------------ model
    def calibrated_mag(self, mag_nT: np.ndarray) -> np.ndarray:
        """Remove offset and ``D``: ``inv(D) @ (y - o)``, mag frame, shape (N, 3)."""
        y = np.asarray(mag_nT, dtype=float)
        if self.offset_nT is not None:
            y = y - self.offset_nT
        if self.D is not None:
            y = np.linalg.solve(self.D, y.T).T
        return y

    def forward_model(self) -> ForwardModel:
        """Return the measurement model this calibration carries: its fields and its effects.

        Each effect's module reads its CONVENTIONS params (``pipeline.model.effects``): a
        sensor constant sets the model's field (:meth:`Effect.model_fields`; the first of a
        kind), the other terms become its parts (:meth:`Effect.restore_part`), in the
        registry's order, which is the order (M1) sums the fields in. ``offset_nT`` / ``D`` /
        ``time_offset_s`` of the calibration itself take precedence over the ``hard_iron`` /
        ``soft_iron`` / ``time_offset`` effects. A ``disturbance``, ``field_drift``,
        ``heading_drift`` or ``field_map`` whose params lack the fitted curve (written by
        ``diagnose``) is listed in ``unmodelled``.
        """
        fields: dict[str, Any] = {}
        parts = []
        unmodelled: list[str] = []
        for kind in EffectKind:
            effect = EFFECTS[kind]
            for params in _entries((self.effects or {}).get(kind.value)):
                if not effect.restorable(params):
                    unmodelled.append(kind.value)
                    continue
                for name, value in effect.model_fields(params).items():
                    fields.setdefault(name, value)
                part = effect.restore_part(params)
                if part is not None:
                    parts.append(part)
        if self.offset_nT is not None:
            fields["offset_nT"] = np.asarray(self.offset_nT, dtype=float)
        if self.D is not None:
            fields["D"] = np.asarray(self.D, dtype=float)
        if self.time_offset_s is not None:
            fields["time_offset_s"] = float(self.time_offset_s)
        return ForwardModel(R_body_mag=np.asarray(self.R_body_mag, dtype=float),
                            B_enu_nT=np.asarray(self.B_enu_nT, dtype=float),
                            parts=tuple(parts), unmodelled=tuple(unmodelled), **fields)

    def predict(
        self,
        t_ns: np.ndarray,
        attitude: AttitudeSeries,
        *,
        t0_ns: int | None = None,
        max_gap_s: float | None = None,
        position: PositionSeries | None = None,
    ) -> np.ndarray:
        """Forward model: the magnetometer readings predicted at the stamps ``t_ns``.

        Every term the calibration carries (``D``, ``o``, ``tau`` by re-interpolating the
        attitude at ``t - tau``, and the diagnosed effects: eddy currents, offset steps,
        disturbances, field drift and gradient); :func:`pipeline.model.forward.evaluate`.

        Parameters
        ----------
        t_ns : ndarray of int64, shape (N,)
            Magnetometer stamps, ns since the epoch.
        attitude : AttitudeSeries
            The attitude samples ``q_enu_body`` (THE interpolator,
            with the gap rule).
        t0_ns : int, optional
            First magnetometer stamp of the recording (effect windows count from it);
            default ``t_ns[0]``.
        max_gap_s : float, optional
            Attitude gap bridged, s; default the automatic rule.
        position : PositionSeries, optional
            Positions for a ``field_gradient`` effect.

        Returns
        -------
        ndarray, shape (N, 3)
            Predicted ``y_mag``, nT; NaN where no attitude is available.

        """
        return predict(self.forward_model(), t_ns, attitude, t0_ns=t0_ns,
                       max_gap_s=max_gap_s, position=position)

    def restore(
        self,
        mag_nT: np.ndarray,
        t_ns: np.ndarray,
        attitude: AttitudeSeries,
        *,
        t0_ns: int | None = None,
        max_gap_s: float | None = None,
        position: PositionSeries | None = None,
    ) -> Restoration:
        """Restore magnetometer samples to ENU by inverting every term (CONVENTIONS).

        Parameters as :meth:`predict`, with ``mag_nT`` (N, 3) the raw readings, mag frame.

        Returns
        -------
        Restoration
            ``enu_nT`` (restored field, ENU, nT), ``calibrated_mag_nT``, ``residual_nT`` of
            the full model, ``valid`` (:class:`pipeline.model.forward.Restoration`).

        """
        return restore(self.forward_model(), mag_nT, t_ns, attitude, t0_ns=t0_ns,
                       max_gap_s=max_gap_s, position=position)

    # ------------------------------------------------------------------ serialisation
    def to_dict(self) -> dict[str, Any]:
        """Return the calibration.json object (CONVENTIONS)."""
        return {
            "format": FORMAT,
            "R_body_mag": _list(self.R_body_mag),
            "rotvec_body_mag_deg": _list(self.rotvec_body_mag_deg),
            "sigma_rotvec_deg": [
                None if not np.isfinite(s) else float(s) for s in self.sigma_rotvec_deg
            ],
            "unobservable_axes_body": [_list(a) for a in self.unobservable_axes_body],
            "D": _list(self.D),
            "sigma_D": _list(self.sigma_D),
            "offset_nT": _list(self.offset_nT),
            "sigma_offset_nT": _list(self.sigma_offset_nT),
            "time_offset_s": self.time_offset_s,
            "sigma_time_offset_s": None
            if self.sigma_time_offset_s is None or not np.isfinite(self.sigma_time_offset_s)
            else float(self.sigma_time_offset_s),
            "B_enu_nT": _list(self.B_enu_nT),
            "sigma_B_enu_nT": _list(self.sigma_B_enu_nT),
            "estimator": self.estimator,
            "residual_rms_nT": float(self.residual_rms_nT),
            "n_samples": int(self.n_samples),
            "R_nominal_body_mag": _list(self.R_nominal_body_mag),
            "rotvec_from_nominal_deg": _list(self.rotvec_from_nominal_deg),
            "effects": self.effects,
            "warnings": list(self.warnings),
            "verdict": None if self.verdict is None else self.verdict.to_dict(),
            "n_eff": None if self.n_eff is None else float(self.n_eff),
            "not_estimated": [dict(d) for d in self.not_estimated],
            "checks": _jsonable(self.checks),
            "sample_hold": self.sample_hold,
        }

    def to_json(self, indent: int = 2) -> str:
        """Serialise to the calibration.json text."""
        return json.dumps(unsigned_zeros_in(self.to_dict()), indent=indent, allow_nan=False)

    @classmethod
    def from_dict(cls, d: dict[str, Any], path: str | None = None) -> Calibration:
        """Build from a calibration.json object; checks the format version."""
        if d.get("format") != FORMAT:
            raise InputError(
                f"not a {FORMAT} calibration (format is {d.get('format')!r})",
                path=path,
                hint="pass a calibration.json written by magalign",
            )
        try:
            sig = [np.inf if s is None else s for s in d["sigma_rotvec_deg"]]
            return cls(
                R_body_mag=d["R_body_mag"],
                sigma_rotvec_deg=np.asarray(sig, dtype=float),
                B_enu_nT=d["B_enu_nT"],
                estimator=d["estimator"],
                residual_rms_nT=d["residual_rms_nT"],
                n_samples=d["n_samples"],
                unobservable_axes_body=tuple(d.get("unobservable_axes_body") or ()),
                D=d.get("D"),
                offset_nT=d.get("offset_nT"),
                time_offset_s=d.get("time_offset_s"),
                sigma_D=d.get("sigma_D"),
                sigma_offset_nT=d.get("sigma_offset_nT"),
                sigma_time_offset_s=d.get("sigma_time_offset_s"),
                sigma_B_enu_nT=d.get("sigma_B_enu_nT"),
                R_nominal_body_mag=d.get("R_nominal_body_mag"),
                effects=d.get("effects") or {},
                warnings=tuple(d.get("warnings") or ()),
                verdict=None if d.get("verdict") is None else Verdict.from_dict(d["verdict"]),
                n_eff=d.get("n_eff"),
                not_estimated=tuple(d.get("not_estimated") or ()),
                checks=d.get("checks") or {},
                sample_hold=d.get("sample_hold"),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"calibration file is incomplete or malformed: {exc}",
                             path=path) from exc

    @classmethod
    def from_json(cls, text: str, path: str | None = None) -> Calibration:
        """Parse calibration.json text."""
        try:
            d = json.loads(text)
        except json.JSONDecodeError as exc:
            raise InputError(f"calibration is not valid JSON: {exc}", path=path) from exc
        check_calibration_dict(d, path)
        return cls.from_dict(d, path=path)

    @classmethod
    def load(cls, path: str | Path) -> Calibration:
        """Read a calibration.json file."""
        p = Path(path)
        d = read_json_object(p, "a calibration.json",
                             hint="give the calibration.json written by magalign calibrate, "
                             "diagnose or process")
        check_calibration_dict(d, str(p))
        return cls.from_dict(d, path=str(p))

    def replace(self, **changes: Any) -> Calibration:
        """Return a new calibration with ``changes``."""
        return dataclasses.replace(self, **changes)
