"""``field_map``: a smooth field over the area (Laplace eigenfunctions, GP prior, ``F(t)``)."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from pipeline.core.vocabulary import EffectKind
from pipeline.model.effects.base import Effect, TermShape, register


@register
class FieldMap(Effect):
    """The ``field_map`` effect (see :class:`~pipeline.model.effects.base.Effect`)."""

    kind: ClassVar[EffectKind] = EffectKind.FIELD_MAP
    physics: ClassVar[str] = (
        "a field that varies smoothly but not linearly over the area the sensor covers "
        "(steel in the building's structure, a distant vehicle or pipe, a geological "
        "anomaly): the gradient is only its first order"
    )
    signature: ClassVar[str] = (
        "an ENU residual, left after the linear gradient, that follows the sensor's position "
        "and repeats wherever the sensor comes back, smooth over the whole area"
    )
    frame: ClassVar[str] = "enu"
    # a map along a path leaves combinations of its basis unobserved (the GP prior holds
    # them): admitted on its best-determined directions
    identifiable_in_part: ClassVar[bool] = True

    def n_params(self, term: TermShape) -> int:
        """Return one weight per basis function (the product of the modes per axis)."""
        return int(np.prod(term.n_axis))
