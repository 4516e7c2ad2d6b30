"""``heading_drift``: the attitude source's heading error growing in time (turn about Up, (M1h))."""

from __future__ import annotations

from typing import ClassVar

from pipeline.core.vocabulary import EffectKind
from pipeline.model.effects.base import Effect, register
from pipeline.model.forward import HEADING_DEGREE


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
