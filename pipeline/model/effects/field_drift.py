"""``field_drift``: a slow change of the field in time (ENU polynomial, ``F(t)``)."""

from __future__ import annotations

from typing import ClassVar

from pipeline.core.vocabulary import EffectKind
from pipeline.model.effects.base import Effect, register
from pipeline.model.forward import DRIFT_DEGREE


@register
class FieldDrift(Effect):
    """The ``field_drift`` effect (see :class:`~pipeline.model.effects.base.Effect`)."""

    kind: ClassVar[EffectKind] = EffectKind.FIELD_DRIFT
    physics: ClassVar[str] = (
        "slow change of the field around the sensor during the recording. Outdoors: diurnal "
        "variation, a geomagnetic storm or another external drift of the background field. "
        "Indoors, or on a platform that moves through a non-uniform field (steel in floors "
        "and walls, a survey line crossing a regional gradient): the field varying with the "
        "sensor's position, which appears as a change in time as the sensor moves"
    )
    signature: ClassVar[str] = (
        "a slow trend common to all headings once rotated to ENU"
    )
    frame: ClassVar[str] = "enu"
    n_fixed: ClassVar[int | None] = 3 * DRIFT_DEGREE
