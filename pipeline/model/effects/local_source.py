"""``local_source``: a compact magnetised object fixed in the surroundings (a dipole, ``F(t)``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from pipeline.core.vocabulary import EffectKind
from pipeline.core.words import vec
from pipeline.model.dipole_kernels import add_dipole_field, dipole_columns
from pipeline.model.effects.base import (
    F64,
    Effect,
    FitView,
    Linearisation,
    Motion,
    RestorePart,
    Samples,
    TermShape,
    register,
    standard_deviations,
)
from pipeline.model.forward import (
    dipole_field,
    dipole_gradient,
    in_windows,
    source_offset_enu,
    windows_span,
)


def bearing_rad(term: Any, value: F64) -> float:
    """Return the position frame's bearing: fitted (``value[6]``) or the term's."""
    return float(value[6]) if term.fit_yaw else float(term.yaw_rad)



def same_object(a: dict[str, Any], b: dict[str, Any]) -> bool:
    """Return whether two located dipoles are one object the data do not resolve into two.

    A dipole's anomaly seen from a distance ``d`` is about ``d`` wide: the vertical
    component of a vertical dipole along a straight pass falls to half its peak ``0.50 d``
    to either side, the magnitude ``0.67-1.09 d`` (docs/effects.md, "One object, several
    dipoles"). Two dipoles closer together than the sensor ever came to either of them
    lie within each other's width at half maximum (Rayleigh's criterion): the data see
    one object larger than a point at that distance (a magnet a few centimetres across
    seen from 5 cm, steel of irregular shape), described by two dipoles, not two objects.
    Both need a closest approach and the same position frame.
    """
    if a.get("position_frame") != b.get("position_frame"):
        return False
    da, db = a.get("closest_approach_m"), b.get("closest_approach_m")
    if da is None or db is None:
        return False
    return _gap_m(a, b) < min(float(da), float(db))


def _gap_m(a: dict[str, Any], b: dict[str, Any]) -> float:
    """Distance between two located dipoles' positions, m."""
    return float(np.linalg.norm(np.asarray(a["position_m"], float)
                                - np.asarray(b["position_m"], float)))


def objects(params: list[dict[str, Any]]) -> list[list[int]]:
    """Group located dipoles into objects: linked by :func:`same_object`, transitively.

    Returns the groups of indices into ``params``, each ascending, ordered by their first
    member (the order found).
    """
    group = list(range(len(params)))

    def root(i: int) -> int:
        while group[i] != i:
            i = group[i]
        return i

    for i in range(len(params)):
        for j in range(i + 1, len(params)):
            if same_object(params[i], params[j]):
                a, b = sorted((root(i), root(j)))
                group[b] = a
    out: dict[int, list[int]] = {}
    for i in range(len(params)):
        out.setdefault(root(i), []).append(i)
    return list(out.values())


@dataclass(frozen=True, eq=False)
class SourcePart(RestorePart):
    """A fitted ``local_source`` in the restore: a point dipole where it was there.

    ``position_m`` in the position frame, ``moment_Am2`` in ENU, ``yaw_rad`` the bearing of
    the position frame (``r = Rz(psi) (p - c)``), ``windows_s`` when it was there (empty:
    the whole recording).
    """

    needs_positions: ClassVar[bool] = True
    position_m: F64
    moment_Am2: F64
    yaw_rad: float
    windows_s: tuple[tuple[float, float], ...]

    def field_enu(self, t_s: F64, p_m: F64 | None, lever_enu: F64 | None) -> F64 | None:
        """Return the dipole's field where it was there (see :meth:`RestorePart.field_enu`)."""
        if p_m is None:
            return None
        r = source_offset_enu(self.position_m, self.yaw_rad, p_m, lever_enu)
        f = dipole_field(r, self.moment_Am2)
        if self.windows_s:
            f[~in_windows(t_s, self.windows_s)] = 0.0
        return np.asarray(f)


@register
class LocalSource(Effect):
    """The ``local_source`` effect (see :class:`~pipeline.model.effects.base.Effect`)."""

    kind: ClassVar[EffectKind] = EffectKind.LOCAL_SOURCE
    physics: ClassVar[str] = (
        "a compact magnetised object fixed in the surroundings (a magnet or a tool on a "
        "table, buried steel, a parked vehicle): it stays where it is while the sensor moves"
    )
    signature: ClassVar[str] = (
        "an ENU residual that grows steeply (as the cube of the inverse distance) wherever "
        "the sensor comes near one place, whenever that is"
    )
    frame: ClassVar[str] = "enu"
    local_in_space: ClassVar[bool] = True
    # tested at zero moment, where the position has no gradient: the moment carries the
    # evidence (the position is fitted once the moment is there)
    identifiable_in_part: ClassVar[bool] = True

    def n_params(self, term: TermShape) -> int:
        """Return position (3) and moment (3), plus the bearing of the position frame."""
        return 7 if term.fit_yaw else 6

    def add_field(self, term: Any, value: F64, at: Samples, B_enu: F64) -> Any:
        """Add ``100 nT (3 (m.u) u - m) / r^3`` (CONVENTIONS), where the source is present.

        Returns the offsets ``r`` (N, 3) for the columns (see :meth:`Effect.add_field`).
        """
        if at.p_m is None:
            return None
        r_src = source_offset_enu(value[0:3], bearing_rad(term, value), at.p_m, at.lever_enu)
        add_dipole_field(r_src, value[3:6], B_enu,
                         term.presence(at.t_s) if term.windows_s else None)
        return r_src

    def gradient_enu(self, term: Any, value: F64, at: Samples) -> F64 | None:
        """Return ``K(r) = dB/dr`` where present (see :meth:`Effect.gradient_enu`)."""
        if at.p_m is None:
            return None
        r = source_offset_enu(value[0:3], bearing_rad(term, value), at.p_m, at.lever_enu)
        return term.presence(at.t_s)[:, None, None] * dipole_gradient(r, value[3:6])

    def columns(self, term: Any, value: F64, lin: Linearisation, kept: Any, out: F64) -> None:
        """Write the columns of the place, the moment and the bearing (:meth:`Effect.columns`).

        ``r = Rz(psi) (p - c) + C l``, ``B = P(r) m``: ``dB/dc = -K Rz(psi)``, ``dB/dm = P(r)``,
        ``dB/dpsi = K (e_z x Rz(psi) (p - c))``, ``K = dB/dr`` (dipole_gradient).
        """
        if lin.p_m is None:
            return
        r_src = kept  # as the field's: the same offsets
        psi = bearing_rad(term, value)
        r_p = None
        if term.fit_yaw:
            r_p = r_src if lin.lever_enu is None else source_offset_enu(value[0:3], psi, lin.p_m)
        dipole_columns(r_src, value[3:6], psi, lin.G, r_p,
                       term.presence(lin.t_s) if term.windows_s else None, out)

    def column_windows(self, term: Any) -> tuple[tuple[int, int, float, float], ...]:
        """Return every column over the source's windows, if it has any (its presence).

        See :meth:`Effect.column_windows`.
        """
        if not term.windows_s:
            return ()
        return ((0, self.n_params(term), *windows_span(term.windows_s)),)

    def undetermined(self, motion: Motion, efficiency: float,
                     horizontal_fraction: float | None = None) -> str | None:
        """Return why a source cannot be located: only without positions (see the base class)."""
        if not motion.has_positions:
            return ("no positions in the recording: a source fixed in the surroundings is seen "
                    "only through where the sensor is")
        return None

    def params(self, term: Any, value: F64, fit: FitView) -> dict[str, Any]:
        """Return the CONVENTIONS params (see :meth:`Effect.params`)."""
        return fit.source_params(term, value)

    def sigma(self, term: Any, cov: F64, fit: FitView) -> dict[str, Any]:
        """Return their 1-sigma (see :meth:`Effect.sigma`)."""
        sd = standard_deviations(cov)
        return {"position_m": sd[0:3].tolist(), "moment_Am2": sd[3:6].tolist(),
                "closest_approach_m": float(np.linalg.norm(sd[0:3]))}

    def remark(self, params: dict[str, Any], duration_s: float, note: str | None = None) -> str:
        """Return what the fitted values suggest (see :meth:`Effect.remark`)."""
        text = ""
        pos = ", ".join(f"{x:.2f}" for x in params["position_m"])
        m = float(np.linalg.norm(params["moment_Am2"]))
        frame = ("the attitude source's own frame (the motion-capture room)"
                 if params.get("position_frame") == "attitude_source_local" else "local ENU")
        text += f". Located at ({pos}) m in {frame}, moment {m:.3g} A m^2"
        if params.get("closest_approach_m") is not None:
            text += (f"; the sensor came closest, {100 * params['closest_approach_m']:.0f} cm, "
                     f"at {params['closest_approach_s']:.1f} s")
        text += (
            ". It belongs to the surroundings, not to the sensor: the restored field keeps it "
            "(a survey maps it); calibrate away from it, or keep it in the model"
        )
        return text

    def beside_kin(self, params: list[dict[str, Any]], short: bool = False) -> list[str]:
        """Name the dipoles that are one object (:func:`objects`; :meth:`Effect.beside_kin`)."""
        words = [""] * len(params)
        for g in objects(params):
            if len(g) < 2:
                continue
            for i in g:
                others = [j for j in g if j != i]
                gaps = [_gap_m(params[i], params[j]) for j in others]
                near = min(float(params[j]["closest_approach_m"]) for j in g)
                at = "; ".join(vec(np.asarray(params[j]["position_m"], float), 2) for j in others)
                cm = ", ".join(f"{100 * x:.1f}" for x in gaps)
                if short:
                    words[i] = (f" It and the dipole at {at} m, {cm} cm away, are one object: "
                                f"closer than the sensor came to any of them ({100 * near:.1f} "
                                "cm), the data do not resolve them apart.")
                    continue
                words[i] = (
                    f". With the local_source at {at} m ({cm} cm away) it is one object: the "
                    "dipoles lie closer together than the "
                    f"sensor came to any of them ({100 * near:.1f} cm), so the data do not "
                    "resolve them as separate objects; together they describe an object larger "
                    "than a point at that distance, listed once among the targets"
                )
        return words

    def restore_part(self, params: dict[str, Any]) -> SourcePart:
        """Return the dipole for the restore (see :meth:`Effect.restore_part`)."""
        return SourcePart(np.asarray(params["position_m"], dtype=float).reshape(3),
                          np.asarray(params["moment_Am2"], dtype=float).reshape(3),
                          float(np.radians(params.get("frame_yaw_deg") or 0.0)),
                          tuple(tuple(w) for w in params.get("windows_s") or ()))

    def sentence(self, params: dict[str, Any], sigma: dict[str, Any]) -> str:
        """Return where the object is, its moment and the closest pass (:meth:`Effect.sentence`)."""
        pos = np.asarray(params["position_m"], float)
        sp = sigma.get("position_m")
        frame = ("the motion-capture room's frame" if params.get("position_frame")
                 == "attitude_source_local" else "local east, north, up")
        where = ""
        if params.get("closest_approach_m") is not None:
            where = (f"; the sensor passed {100 * float(params['closest_approach_m']):.0f} cm "
                     f"from it at {float(params['closest_approach_s']):.1f} s")
        where_at = vec(pos, 3) + " m"
        if sp is not None and np.all(np.isfinite(sp)):
            # the sigma in cm with the digits it has (a located source is often sub-cm)
            sc = 100 * np.asarray(sp, float)
            nd = 1 if float(np.min(sc)) >= 0.1 else 2
            where_at += " \u00b1 " + vec(sc, nd) + " cm"
        return (f"A magnetised object fixed in the surroundings (not on the sensor): located "
                f"at {where_at} in {frame}, moment "
                f"{float(np.linalg.norm(params['moment_Am2'])):.3g} A m\u00b2{where}. The "
                "restored field keeps it.")
