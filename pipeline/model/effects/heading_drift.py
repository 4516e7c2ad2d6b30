"""``heading_drift``: the attitude source's heading error growing in time (turn about Up, (M1h))."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from pipeline.core.vocabulary import EffectKind
from pipeline.model.effects.base import F64, Effect, FitView, register, standard_deviations
from pipeline.model.forward import HEADING_DEGREE, heading_basis


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
    n_fixed: ClassVar[int | None] = HEADING_DEGREE

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
