"""``eddy_current``: currents induced in the airframe by the rotating field (``E_s``, (M5))."""

from __future__ import annotations

from typing import Any, ClassVar

from pipeline.core.vocabulary import EffectKind
from pipeline.model.effects.base import F64, Effect, FitView, register, standard_deviations


@register
class EddyCurrent(Effect):
    """The ``eddy_current`` effect (see :class:`~pipeline.model.effects.base.Effect`)."""

    kind: ClassVar[EffectKind] = EffectKind.EDDY_CURRENT
    physics: ClassVar[str] = (
        "currents induced in conducting parts of the airframe by the changing field as it "
        "rotates; their field lags and differs per axis (a time offset is the isotropic case)"
    )
    signature: ClassVar[str] = (
        "a residual linear in the rate of change of the reading, with different gains per axis"
    )
    frame: ClassVar[str] = "mag"
    n_fixed: ClassVar[int | None] = 9

    def params(self, term: Any, value: F64, fit: FitView) -> dict[str, Any]:
        """Return the CONVENTIONS params (see :meth:`Effect.params`)."""
        return {"E_s": value.reshape(3, 3).tolist()}

    def sigma(self, term: Any, cov: F64, fit: FitView) -> dict[str, Any]:
        """Return their 1-sigma (see :meth:`Effect.sigma`)."""
        sd = standard_deviations(cov)
        return {"E_s": sd.reshape(3, 3).tolist()}
