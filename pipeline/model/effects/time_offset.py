"""``time_offset``: a delay between the magnetometer's and the attitude's clocks (``tau``, (M1))."""

from __future__ import annotations

import math
from typing import Any, ClassVar

from pipeline.core.vocabulary import EffectKind
from pipeline.core.words import num
from pipeline.model.effects.base import (
    F64,
    SINGLE_AXIS_SPREAD,
    Effect,
    FitView,
    Linearisation,
    Motion,
    register,
    standard_deviations,
)
from pipeline.model.forward import time_offset_jacobian

#: A rotation rate varying by less than this fraction (coefficient of variation) is steady.
STEADY_RATE_CV = 0.05


def steady_turn_reason(motion: Motion) -> str | None:
    """Return why a steady turn about one axis hides a lag of the readings, or None.

    A time offset (and the eddy term, its anisotropic relative) then looks the same as a
    fixed turn of the heading, which the misalignment absorbs.
    """
    if motion.axis_spread < SINGLE_AXIS_SPREAD and motion.rate_cv < STEADY_RATE_CV:
        return (
            "the sensor turned at a steady rate about one axis: a time offset then looks the "
            "same as a fixed turn of the heading, which the misalignment absorbs; vary the "
            "rate or turn about more than one axis"
        )
    return None


@register
class TimeOffset(Effect):
    """The ``time_offset`` effect (see :class:`~pipeline.model.effects.base.Effect`)."""

    kind: ClassVar[EffectKind] = EffectKind.TIME_OFFSET
    physics: ClassVar[str] = (
        "unsynchronised clocks or a transport/filter delay between the magnetometer and the "
        "attitude source: the reading is stamped later (or earlier) than it was sensed"
    )
    signature: ClassVar[str] = (
        "a residual proportional to the rate of change of the field in the sensor frame"
    )
    frame: ClassVar[str] = "mag"
    each_round: ClassVar[bool] = True
    rate_signature: ClassVar[bool] = True
    n_fixed: ClassVar[int | None] = 1

    def motion_reason(self, motion: Motion, horizontal_fraction: float | None) -> str | None:
        """Return :func:`steady_turn_reason` (see :meth:`Effect.motion_reason`)."""
        return steady_turn_reason(motion)

    def params(self, term: Any, value: F64, fit: FitView) -> dict[str, Any]:
        """Return the CONVENTIONS params (see :meth:`Effect.params`)."""
        return {"time_offset_s": float(value[0])}

    def sigma(self, term: Any, cov: F64, fit: FitView) -> dict[str, Any]:
        """Return their 1-sigma (see :meth:`Effect.sigma`)."""
        sd = standard_deviations(cov)
        return {"time_offset_s": float(sd[0])}

    def columns(self, term: Any, value: F64, lin: Linearisation, kept: Any, out: F64) -> None:
        """Write ``dy/dtau``, (J5) (see :meth:`Effect.columns`).

        ``b(t - tau)`` with the attitude re-interpolated at ``t - tau``: ``db/dtau = omega x
        b`` with ``omega`` the exact interpolated rate there; ``dbdot/dtau = -bddot`` for the
        eddy regressor.
        """
        out[:, :, 0] = time_offset_jacobian(lin.omega_body, lin.b, lin.bddot, lin.R, lin.D, lin.E)

    def model_fields(self, params: dict[str, Any]) -> dict[str, Any]:
        """Return ``tau`` for the restore (see :meth:`Effect.model_fields`)."""
        tau = params.get("time_offset_s")
        return {} if tau is None else {"time_offset_s": float(tau)}

    def sentence(self, params: dict[str, Any], sigma: dict[str, Any]) -> str:
        """Return the lag in ms with its sigma (see :meth:`Effect.sentence`)."""
        tau = 1e3 * float(params["time_offset_s"])
        st = sigma.get("time_offset_s")
        # the digits of the calibration table and the verdict line: one value everywhere
        sig = f" \u00b1 {1e3 * float(st):.2f}" if st is not None and math.isfinite(st) else ""
        late = "late" if tau > 0 else "early"
        return (f"The magnetometer's time stamps are {late} by {abs(tau):.2f}{sig} ms against "
                f"the attitude (\u03c4 = {num(tau, 2)} ms).")
