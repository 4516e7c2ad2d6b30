"""``hard_iron_step``: a magnetised object near the sensor for a while (windowed offset, (M5))."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from pipeline.core.vocabulary import EffectKind
from pipeline.model.effects.base import (
    F64,
    Effect,
    FitView,
    TermShape,
    register,
    standard_deviations,
)


@register
class HardIronStep(Effect):
    """The ``hard_iron_step`` effect (see :class:`~pipeline.model.effects.base.Effect`)."""

    kind: ClassVar[EffectKind] = EffectKind.HARD_IRON_STEP
    physics: ClassVar[str] = (
        "a magnetised object moved close to the sensor for a while (a tool, a phone, a "
        "payload switched on): an offset that turns with the platform, present only then"
    )
    signature: ClassVar[str] = (
        "a constant mag-frame residual inside a time window"
    )
    frame: ClassVar[str] = "mag"

    def n_params(self, term: TermShape) -> int:
        """Return 3 for the plateau's offset plus 3 per mode of the transitions."""
        return 3 + 3 * term.step_profile(np.zeros(1))[1].shape[1]

    def params(self, term: Any, value: F64, fit: FitView) -> dict[str, Any]:
        """Return the CONVENTIONS params (see :meth:`Effect.params`)."""
        return {"windows_s": [[float(a), float(b)] for a, b in term.windows_s],
                "offset_nT": np.asarray(value[:3], dtype=float).tolist()}

    def sigma(self, term: Any, cov: F64, fit: FitView) -> dict[str, Any]:
        """Return their 1-sigma (see :meth:`Effect.sigma`)."""
        sd = standard_deviations(cov)
        return {"offset_nT": sd[:3].tolist()}
