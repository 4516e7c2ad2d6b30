"""``lever_arm``: the sensor away from the point the attitude source positions (mag frame, m)."""

from __future__ import annotations

from typing import ClassVar

from pipeline.core.vocabulary import EffectKind
from pipeline.model.effects.base import Effect, register


@register
class LeverArm(Effect):
    """The ``lever_arm`` effect (see :class:`~pipeline.model.effects.base.Effect`)."""

    kind: ClassVar[EffectKind] = EffectKind.LEVER_ARM
    physics: ClassVar[str] = (
        "the magnetometer is not at the point whose position the attitude source reports "
        "(a motion-capture marker body, an INS's reference point): as the platform turns, "
        "the sensor swings around that point through a field that varies in space"
    )
    signature: ClassVar[str] = (
        "a residual that follows the attitude times the field's spatial gradient (strongest "
        "near a local source)"
    )
    frame: ClassVar[str] = "enu"
    n_fixed: ClassVar[int | None] = 3
