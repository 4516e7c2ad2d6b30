"""``sample_hold``: repeated conversions stamped late (handled on the data, not a model term)."""

from __future__ import annotations

from typing import Any, ClassVar

from pipeline.core.vocabulary import EffectKind
from pipeline.model.effects.base import Effect, register


@register
class SampleHold(Effect):
    """The ``sample_hold`` effect (see :class:`~pipeline.model.effects.base.Effect`)."""

    kind: ClassVar[EffectKind] = EffectKind.SAMPLE_HOLD
    physics: ClassVar[str] = (
        "the sensor converts slower than its messages are sent: a message repeats the last "
        "conversion, stamped up to one native period after the field was sensed"
    )
    signature: ClassVar[str] = (
        "exact repeats of the reading, and a residual that grows with the rate of change of "
        "the reading (the repeats are late)"
    )
    frame: ClassVar[str] = "mag"

    def sentence(self, params: dict[str, Any], sigma: dict[str, Any]) -> str:
        """Return the native rate and the share of repeats (see :meth:`Effect.sentence`)."""
        return (f"The sensor samples at {float(params['native_rate_hz']):.1f} Hz, slower than "
                f"its messages: {100 * float(params['repeated_fraction']):.1f} % of them repeat "
                "a sample.")
