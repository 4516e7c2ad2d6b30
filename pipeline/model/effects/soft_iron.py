"""``soft_iron``: induced magnetisation and unequal axis gains (``D = I + S``, (M4))."""

from __future__ import annotations

from typing import ClassVar

from pipeline.core.vocabulary import EffectKind
from pipeline.model.effects.base import Effect, register


@register
class SoftIron(Effect):
    """The ``soft_iron`` effect (see :class:`~pipeline.model.effects.base.Effect`)."""

    kind: ClassVar[EffectKind] = EffectKind.SOFT_IRON
    physics: ClassVar[str] = (
        "induced magnetisation of soft-magnetic parts near the sensor and unequal axis "
        "gains or non-orthogonal axes of the sensor: the sphere of readings becomes an ellipsoid"
    )
    signature: ClassVar[str] = (
        "a residual that grows with the field component along some mag axes and flips sign "
        "with it (twice per turn)"
    )
    frame: ClassVar[str] = "mag"
    n_fixed: ClassVar[int | None] = 5
