"""``heading_drift``: the attitude source's heading error growing in time (turn about Up, (M1h))."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from pipeline.core.vocabulary import EffectKind
from pipeline.core.words import num
from pipeline.model.effects.base import (
    F64,
    Effect,
    FitView,
    Linearisation,
    Motion,
    RestorePart,
    Samples,
    register,
    standard_deviations,
)
from pipeline.model.forward import HEADING_DEGREE, heading_basis, rotate_about_up

#: A heading drift needs a horizontal field: below this fraction of |B| a rotation about Up
#: changes the field by too little (near the magnetic poles).
MIN_HORIZONTAL_FRACTION = 0.05


def heading_drift_params(value: F64, span_s: float) -> dict[str, Any]:
    """CONVENTIONS params of ``heading_drift``: mean rate and range of ``h(t)``.

    ``h(t) = sum_k v_k P_k(x(t))`` (rad) is the heading error of the attitude source, positive
    counter-clockwise seen from above (the reported heading ahead of the true one, ENU yaw):
    ``rate_deg_per_h = (h(end) - h(start)) / T``, ``peak_to_peak_deg = max h - min h``; the
    polynomials run over ``span_s``, s.
    """
    tt = np.linspace(0.0, span_s, 512)
    h = np.degrees(heading_basis(tt, span_s) @ value)
    return {"rate_deg_per_h": float((h[-1] - h[0]) / max(span_s / 3600.0, 1e-12)),
            "peak_to_peak_deg": float(h.max() - h.min())}



@dataclass(frozen=True, eq=False)
class HeadingPart(RestorePart):
    """A fitted ``heading_drift`` in the restore: Legendre P1..P2 of ``h(t)`` over ``span_s``."""

    legendre_rad: F64
    span_s: float

    def heading_rad(self, t_s: F64) -> F64:
        """Return ``h(t)`` of (M1h), rad (see :meth:`RestorePart.heading_rad`)."""
        return np.asarray(heading_basis(np.asarray(t_s, dtype=float), self.span_s)
                          @ self.legendre_rad)


@register
class HeadingDrift(Effect):
    """The ``heading_drift`` effect (see :class:`~pipeline.model.effects.base.Effect`)."""

    kind: ClassVar[EffectKind] = EffectKind.HEADING_DRIFT
    physics: ClassVar[str] = (
        "the attitude source's heading error changes during the recording (an INS or AHRS "
        "integrating a gyro bias between heading fixes, a motion-capture frame creeping): the "
        "attitude is turned about Up by a slowly growing angle"
    )
    signature: ClassVar[str] = (
        "a slow ENU residual in which East and North change in the ratio -B_N : B_E while Up "
        "and |B| stay unchanged (the field turning about the vertical)"
    )
    frame: ClassVar[str] = "enu"
    each_round: ClassVar[bool] = True
    confounded_with: ClassVar[str] = "the field and the misalignment"
    # as a field drift: a transient in mid recording reads in part as a slow turn
    trades_with: ClassVar[frozenset[EffectKind]] = frozenset(
        {EffectKind.DISTURBANCE, EffectKind.HARD_IRON_STEP})
    n_fixed: ClassVar[int | None] = HEADING_DEGREE

    def motion_reason(self, motion: Motion, horizontal_fraction: float | None) -> str | None:
        """Return why a nearly vertical field hides a heading error (see the base class)."""
        if horizontal_fraction is not None and horizontal_fraction < MIN_HORIZONTAL_FRACTION:
            return (
                f"the field is nearly vertical (horizontal part {100 * horizontal_fraction:.1f} "
                "% of |B|): a heading error hardly changes it"
            )
        return None

    def turned_enu(self, term: Any, value: F64, at: Samples, B_enu: F64
                   ) -> tuple[F64, F64]:
        """Return ``Rz(h(t)) B``, (M1h), and ``h(t)`` (see :meth:`Effect.turned_enu`).

        The attitude source reports ``Rz(h) C_true``, so the reading is ``R.T C_rep.T Rz(h)
        B`` (CONVENTIONS heading_drift): the ENU field turned about Up by ``h``.
        """
        h = heading_basis(at.t_s, at.span_s) @ value
        return rotate_about_up(B_enu, h), h

    def columns(self, term: Any, value: F64, lin: Linearisation, kept: Any, out: F64) -> None:
        """Write ``dy/dv_k = G Rz(h + pi/2) B_h P_k(t)`` (see :meth:`Effect.columns`).

        ``d(Rz(h) B)/dh = Rz(h + pi/2) B`` with the vertical part removed; ``h = P v``.
        """
        assert lin.h_rad is not None and lin.Bt_unturned is not None  # the model has the term
        dB = rotate_about_up(lin.Bt_unturned, lin.h_rad + 0.5 * np.pi)
        dB[:, 2] = 0.0
        P = heading_basis(lin.t_s, lin.span_s)
        out[:] = np.matmul(lin.G, dB[:, :, None])[:, :, 0][:, :, None] * P[:, None, :]

    def params(self, term: Any, value: F64, fit: FitView) -> dict[str, Any]:
        """Return the CONVENTIONS params (see :meth:`Effect.params`)."""
        return heading_drift_params(value, fit.span_s)

    def sigma(self, term: Any, cov: F64, fit: FitView) -> dict[str, Any]:
        """Return their 1-sigma (see :meth:`Effect.sigma`)."""
        sd = standard_deviations(cov)
        # rate: h(end) - h(start) = 2 v1 (P1 runs from -1 to 1, P2 is 1 at both ends);
        # range: first order, as for field_drift (each polynomial swings by at most 2)
        T_h = max(fit.span_s, 1e-9) / 3600.0
        return {"rate_deg_per_h": float(np.degrees(2.0 * sd[0]) / T_h),
                "peak_to_peak_deg": float(np.degrees(2.0 * np.sqrt(np.sum(sd**2))))}

    def remark(self, params: dict[str, Any], duration_s: float, note: str | None = None) -> str:
        """Return what the fitted values suggest (see :meth:`Effect.remark`)."""
        text = ""
        text += (
            f". The attitude's heading error changes by {params['peak_to_peak_deg']:.3g} deg "
            f"over {duration_s:.0f} s (a mean rate of {params['rate_deg_per_h']:.3g} deg/h). "
            "A field that turns about Up without changing its magnitude would give the same "
            "readings; the field does not do that by itself (diurnal and storm variations "
            "change |B| and Up), an attitude source's heading does. Check the source's heading "
            "aiding (magnetometer, GNSS dual antenna, mocap frame) and its gyro bias"
        )
        return text

    def restorable(self, params: dict[str, Any]) -> bool:
        """Return whether the Legendre coefficients are there (see :meth:`Effect.restorable`)."""
        return "legendre_rad" in params and "span_s" in params

    def restore_part(self, params: dict[str, Any]) -> HeadingPart:
        """Return the heading drift for the restore (see :meth:`Effect.restore_part`)."""
        return HeadingPart(np.asarray(params["legendre_rad"], dtype=float).reshape(-1),
                           float(params["span_s"]))

    def sentence(self, params: dict[str, Any], sigma: dict[str, Any]) -> str:
        """Return the heading's drift rate and size (see :meth:`Effect.sentence`)."""
        return (f"The attitude source's heading drifts by "
                f"{num(float(params['rate_deg_per_h']), 2)}\u00b0/h "
                f"({float(params['peak_to_peak_deg']):.2f}\u00b0 peak to peak).")
