"""``disturbance``: a transient external field inside a time window (ENU hats, ``F(t)``)."""

from __future__ import annotations

from typing import ClassVar

from pipeline.core.vocabulary import EffectKind
from pipeline.model.effects.base import Effect, TermShape, register


@register
class Disturbance(Effect):
    """The ``disturbance`` effect (see :class:`~pipeline.model.effects.base.Effect`)."""

    kind: ClassVar[EffectKind] = EffectKind.DISTURBANCE
    physics: ClassVar[str] = (
        "a transient external field: a vehicle or a person with steel passing, a lift, "
        "power cables switched on near the survey"
    )
    signature: ClassVar[str] = (
        "a bump in the residual confined to a time window, fixed in ENU"
    )
    frame: ClassVar[str] = "enu"

    def n_params(self, term: TermShape) -> int:
        """Return 3 field components per knot of every window (linear B-spline hats)."""
        return 3 * sum(len(kn) for kn in term.knots())
