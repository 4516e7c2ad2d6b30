"""``disturbance``: a transient external field inside a time window (ENU hats, ``F(t)``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from pipeline.core.vocabulary import EffectKind
from pipeline.model.effects.base import (
    F64,
    Effect,
    FitView,
    Linearisation,
    RestorePart,
    Samples,
    TermShape,
    register,
    standard_deviations,
)
from pipeline.model.forward import hat_basis, window_rows


@dataclass(frozen=True, eq=False)
class DisturbancePart(RestorePart):
    """A fitted ``disturbance`` in the restore: its ENU field at the knots of each window."""

    #: per window, the knots (K,), s, and the field there (K, 3), nT, ENU
    pieces: tuple[tuple[F64, F64], ...]

    def field_enu(self, t_s: F64, p_m: F64 | None, lever_enu: F64 | None) -> F64:
        """Return the hats' field, zero outside the windows (see :meth:`RestorePart.field_enu`)."""
        return np.asarray(sum(hat_basis(t_s, knots) @ values for knots, values in self.pieces))


@register
class Disturbance(Effect):
    """The ``disturbance`` effect (see :class:`~pipeline.model.effects.base.Effect`)."""

    kind: ClassVar[EffectKind] = EffectKind.DISTURBANCE
    physics: ClassVar[str] = (
        "a transient external field: a vehicle or a person with steel passing, a lift, "
        "power cables switched on near the survey"
    )
    signature: ClassVar[str] = (
        "a bump in the residual confined to a time window, fixed in ENU"
    )
    frame: ClassVar[str] = "enu"
    event: ClassVar[bool] = True
    in_window: ClassVar[EffectKind | None] = EffectKind.HARD_IRON_STEP

    def n_params(self, term: TermShape) -> int:
        """Return 3 field components per knot of every window (linear B-spline hats)."""
        return 3 * sum(len(kn) for kn in term.knots())

    def params(self, term: Any, value: F64, fit: FitView) -> dict[str, Any]:
        """Return the CONVENTIONS params (see :meth:`Effect.params`)."""
        tt = np.concatenate([np.linspace(a, b, 200, endpoint=False) for a, b in term.windows_s])
        Phi = np.concatenate([hat_basis(tt, kn) for kn in term.knots()], axis=1)
        f = Phi @ value.reshape(-1, 3)
        return {
            "windows_s": [[float(a), float(b)] for a, b in term.windows_s],
            "peak_nT": float(np.max(np.linalg.norm(f, axis=1))),
        }

    def sigma(self, term: Any, cov: F64, fit: FitView) -> dict[str, Any]:
        """Return their 1-sigma (see :meth:`Effect.sigma`)."""
        sd = standard_deviations(cov)
        return {"peak_nT": float(np.sqrt(np.max(np.sum(sd.reshape(-1, 3) ** 2, axis=1))))}

    def add_field(self, term: Any, value: F64, at: Samples, B_enu: F64) -> Any:
        """Add the hats' field inside the windows, (M1) (see :meth:`Effect.add_field`)."""
        c = value.reshape(-1, 3)
        i = 0
        for kn in term.knots():  # each window on its own samples: the hats are zero elsewhere
            rows = window_rows(at.t_s, kn[0], kn[-1])
            B_enu[rows] += hat_basis(at.t_s[rows], kn) @ c[i : i + len(kn)]
            i += len(kn)
        return None

    def columns(self, term: Any, value: F64, lin: Linearisation, kept: Any, out: F64) -> None:
        """Write ``dy/dc_kd = G e_d phi_k(t)`` (see :meth:`Effect.columns`)."""
        i = 0
        for kn in term.knots():
            rows = window_rows(lin.t_s, kn[0], kn[-1])
            phi = hat_basis(lin.t_s[rows], kn)
            n, K = phi.shape
            out[rows, :, 3 * i : 3 * (i + K)] = (
                phi[:, :, None, None] * lin.G[rows][:, None, :, :]).transpose(0, 2, 1, 3).reshape(
                n, 3, 3 * K)
            i += K

    def column_windows(self, term: Any) -> tuple[tuple[int, int, float, float], ...]:
        """Return each hat's 3 columns over its two knot intervals (:meth:`Effect.column_windows`).

        Hat ``i`` of a window's knots ``k`` is zero outside ``[k[i-1], k[i+1])``, clipped to
        the window (``hat_basis``).
        """
        out = []
        i = 0
        for kn in term.knots():
            last = len(kn) - 1
            for h in range(len(kn)):
                out.append((i, i + 3, float(kn[max(h - 1, 0)]), float(kn[min(h + 1, last)])))
                i += 3
        return tuple(out)

    def restorable(self, params: dict[str, Any]) -> bool:
        """Return whether the knots' field is there (see :meth:`Effect.restorable`)."""
        return "knots_s" in params and "knot_field_nT" in params

    def restore_part(self, params: dict[str, Any]) -> DisturbancePart:
        """Return the disturbance for the restore (see :meth:`Effect.restore_part`)."""
        return DisturbancePart(tuple(
            (np.asarray(kn, dtype=float), np.asarray(fv, dtype=float).reshape(-1, 3))
            for kn, fv in zip(params["knots_s"], params["knot_field_nT"], strict=True)))
