"""``field_gradient``: a field varying linearly with position (``G (p - p_ref)``, ``F(t)``)."""

from __future__ import annotations

from typing import ClassVar

from pipeline.core.vocabulary import EffectKind
from pipeline.model.effects.base import Effect, register


@register
class FieldGradient(Effect):
    """The ``field_gradient`` effect (see :class:`~pipeline.model.effects.base.Effect`)."""

    kind: ClassVar[EffectKind] = EffectKind.FIELD_GRADIENT
    physics: ClassVar[str] = (
        "a field that varies from place to place (steel in floors, walls, desks and "
        "equipment indoors; a regional anomaly outdoors), seen as the sensor moves through it"
    )
    signature: ClassVar[str] = (
        "a residual fixed in ENU that follows the sensor's position, not the time"
    )
    frame: ClassVar[str] = "enu"
    n_fixed: ClassVar[int | None] = 5
