"""``hard_iron``: a permanent field fixed to the sensor (mag frame offset ``o``, (M5))."""

from __future__ import annotations

from typing import ClassVar

from pipeline.core.vocabulary import EffectKind
from pipeline.model.effects.base import Effect, register


@register
class HardIron(Effect):
    """The ``hard_iron`` effect (see :class:`~pipeline.model.effects.base.Effect`)."""

    kind: ClassVar[EffectKind] = EffectKind.HARD_IRON
    physics: ClassVar[str] = (
        "a permanent field fixed to the sensor: magnetised steel or a battery near the "
        "magnetometer, or the sensor's own bias; it turns with the platform"
    )
    signature: ClassVar[str] = (
        "a constant residual in the mag frame, the same whatever the heading"
    )
    frame: ClassVar[str] = "mag"
    n_fixed: ClassVar[int | None] = 3
