"""``axis_tilt``: the turntable's axis tilted from its nominal direction (``T``, (M2))."""

from __future__ import annotations

from typing import ClassVar

from pipeline.core.vocabulary import EffectKind
from pipeline.model.effects.base import Effect, register


@register
class AxisTilt(Effect):
    """The ``axis_tilt`` effect (see :class:`~pipeline.model.effects.base.Effect`)."""

    kind: ClassVar[EffectKind] = EffectKind.AXIS_TILT
    physics: ClassVar[str] = (
        "the turntable's rotation axis is not where its nominal axis says (mechanical tilt of "
        "the table), so the attitude derived from its angle is wrong (Tang et al. 2016)"
    )
    signature: ClassVar[str] = (
        "a once-per-turn residual that a known reference field exposes"
    )
    frame: ClassVar[str] = "enu"
    # With a known field only the angle between the axis and B is determined (Tang 2016):
    # a lean across the field's bearing turns B about the axis, which R_body_mag absorbs.
    identifiable_in_part: ClassVar[bool] = True
    n_fixed: ClassVar[int | None] = 2
