"""``field_drift``: a slow change of the field in time (ENU polynomial, ``F(t)``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from pipeline.core.vocabulary import EffectKind
from pipeline.core.words import vec
from pipeline.model.effects.base import (
    F64,
    MIN_TURN_DEG,
    Effect,
    FitView,
    Linearisation,
    Motion,
    RestorePart,
    Samples,
    register,
    standard_deviations,
)
from pipeline.model.forward import DRIFT_DEGREE, drift_basis

#: Rate of change of the geomagnetic field: about 0.1 nT/min for the quiet diurnal variation,
#: rarely above 10 nT/min at mid latitudes even in a storm. A fitted drift much faster than
#: that is more likely the sensor moving through a spatially varying field.
GEOMAGNETIC_RATE_NT_MIN = 10.0



@dataclass(frozen=True, eq=False)
class DriftPart(RestorePart):
    """A fitted ``field_drift`` in the restore: Legendre P1..P4 per ENU axis over ``span_s``."""

    legendre_nT: F64
    span_s: float

    def field_enu(self, t_s: F64, p_m: F64 | None, lever_enu: F64 | None) -> F64:
        """Return ``F(t)`` (see :meth:`RestorePart.field_enu`)."""
        return np.asarray(drift_basis(t_s, self.span_s) @ self.legendre_nT)


@register
class FieldDrift(Effect):
    """The ``field_drift`` effect (see :class:`~pipeline.model.effects.base.Effect`)."""

    kind: ClassVar[EffectKind] = EffectKind.FIELD_DRIFT
    physics: ClassVar[str] = (
        "slow change of the field around the sensor during the recording. Outdoors: diurnal "
        "variation, a geomagnetic storm or another external drift of the background field. "
        "Indoors, or on a platform that moves through a non-uniform field (steel in floors "
        "and walls, a survey line crossing a regional gradient): the field varying with the "
        "sensor's position, which appears as a change in time as the sensor moves"
    )
    signature: ClassVar[str] = (
        "a slow trend common to all headings once rotated to ENU"
    )
    frame: ClassVar[str] = "enu"
    each_round: ClassVar[bool] = True
    contains: ClassVar[EffectKind | None] = EffectKind.HEADING_DRIFT
    # a step or a disturbance in mid recording reads in part as a slow change: a drift beside
    # one can gain by moving its offset (docs/effects.md, "A drift beside a transient")
    trades_with: ClassVar[frozenset[EffectKind]] = frozenset(
        {EffectKind.DISTURBANCE, EffectKind.HARD_IRON_STEP})
    n_fixed: ClassVar[int | None] = 3 * DRIFT_DEGREE
    # without turning a drift is still a change of the field: its own words say what it
    # cannot be told from then
    needs_turning: ClassVar[bool] = False
    confounded_with: ClassVar[str] = "slow attitude changes and the field"

    def motion_reason(self, motion: Motion, horizontal_fraction: float | None) -> str | None:
        """Return why a platform that hardly turned hides a drift (:meth:`Effect.motion_reason`)."""
        if motion.total_turn_deg < MIN_TURN_DEG:
            return (
                "the platform hardly turned: a slow field change cannot be told from a slow change "
                "of attitude or offset"
            )
        return None

    def add_field(self, term: Any, value: F64, at: Samples, B_enu: F64) -> Any:
        """Add ``F(t)``, Legendre P1..P4 per ENU axis, (M1) (see :meth:`Effect.add_field`)."""
        B_enu += drift_basis(at.t_s, at.span_s) @ value.reshape(-1, 3)
        return None

    def columns(self, term: Any, value: F64, lin: Linearisation, kept: Any, out: F64) -> None:
        """Write ``dy/dc_kd = G e_d P_k(t)`` (see :meth:`Effect.columns`)."""
        P = drift_basis(lin.t_s, lin.span_s)
        kk = 3 * P.shape[1]
        out[:] = (P[:, :, None, None] * lin.G[:, None, :, :]).transpose(0, 2, 1, 3).reshape(
            len(P), 3, kk)

    def params(self, term: Any, value: F64, fit: FitView) -> dict[str, Any]:
        """Return the CONVENTIONS params (see :meth:`Effect.params`)."""
        tt = np.linspace(0.0, fit.span_s, 512)
        f = drift_basis(tt, fit.span_s) @ value.reshape(-1, 3)
        return {"peak_to_peak_nT": (f.max(axis=0) - f.min(axis=0)).tolist()}

    def sigma(self, term: Any, cov: F64, fit: FitView) -> dict[str, Any]:
        """Return their 1-sigma (see :meth:`Effect.sigma`)."""
        sd = standard_deviations(cov)
        # first-order sigma of the range: max - min of the fitted curve differs by the
        # coefficients' errors times the basis swing (2 for each Legendre polynomial)
        s = sd.reshape(-1, 3)
        return {"peak_to_peak_nT": (2.0 * np.sqrt(np.sum(s**2, axis=0))).tolist()}

    def remark(self, params: dict[str, Any], duration_s: float, note: str | None = None) -> str:
        """Return what the fitted values suggest (see :meth:`Effect.remark`)."""
        text = ""
        p2p = float(np.max(params["peak_to_peak_nT"]))
        rate = p2p / max(duration_s / 60.0, 1e-9)
        text += (
            f". The fitted change reaches {p2p:.0f} nT over {duration_s:.0f} s "
            f"(about {rate:.1f} nT/min); "
        )
        if rate > GEOMAGNETIC_RATE_NT_MIN:
            text += (
                f"that is faster than geomagnetic variation (below ~{GEOMAGNETIC_RATE_NT_MIN:.0f} "
                "nT/min outside severe storms), so the sensor most likely moved through a "
                "spatially varying field"
            )
        else:
            text += "that is within the range of diurnal or storm-time geomagnetic variation"
        if note is None:
            text += (
                ". A spatial field gradient cannot be separated from a drift in time without "
                "the sensor's positions, which this recording does not carry: the term models "
                "both"
            )
        else:
            text += ". " + note
        return text

    def restorable(self, params: dict[str, Any]) -> bool:
        """Return whether the Legendre coefficients are there (see :meth:`Effect.restorable`)."""
        return "legendre_nT" in params and "span_s" in params

    def restore_part(self, params: dict[str, Any]) -> DriftPart:
        """Return the drift for the restore (see :meth:`Effect.restore_part`)."""
        return DriftPart(np.asarray(params["legendre_nT"], dtype=float).reshape(-1, 3),
                         float(params["span_s"]))

    def sentence(self, params: dict[str, Any], sigma: dict[str, Any]) -> str:
        """Return the drift's size per ENU axis (see :meth:`Effect.sentence`)."""
        return (f"The background field drifted during the recording by "
                f"{vec(params['peak_to_peak_nT'])} nT peak to peak (east, north, up).")
