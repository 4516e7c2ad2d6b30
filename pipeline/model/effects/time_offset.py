"""``time_offset``: a delay between the magnetometer's and the attitude's clocks (``tau``, (M1))."""

from __future__ import annotations

from typing import Any, ClassVar

from pipeline.core.vocabulary import EffectKind
from pipeline.model.effects.base import F64, Effect, FitView, register, standard_deviations


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
    n_fixed: ClassVar[int | None] = 1

    def params(self, term: Any, value: F64, fit: FitView) -> dict[str, Any]:
        """Return the CONVENTIONS params (see :meth:`Effect.params`)."""
        return {"time_offset_s": float(value[0])}

    def sigma(self, term: Any, cov: F64, fit: FitView) -> dict[str, Any]:
        """Return their 1-sigma (see :meth:`Effect.sigma`)."""
        sd = standard_deviations(cov)
        return {"time_offset_s": float(sd[0])}
