"""``hard_iron_step``: a magnetised object near the sensor for a while (windowed offset, (M5))."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from pipeline.core.vocabulary import EffectKind
from pipeline.model.effects.base import (
    F64,
    Effect,
    FitView,
    Linearisation,
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

    def offset_nT(self, term: Any, value: F64, t_s: F64) -> F64:
        """Return ``o_step s(t) + phi(t) c`` of (M5), mag frame, (N, 3)."""
        s, phi = term.step_profile(t_s)
        return s[:, None] * value[:3] + phi @ np.asarray(value[3:]).reshape(-1, 3)

    def columns(self, term: Any, value: F64, lin: Linearisation, kept: Any, out: F64) -> None:
        """Write the plateau's and each transition mode's columns (see :meth:`Effect.columns`)."""
        s_step, phi = term.step_profile(lin.t_s)
        # component r_ of the plateau's offset and of each transition mode's (3 each)
        for r_ in range(3):
            out[:, r_, r_] = s_step
            out[:, r_, 3 + r_ : 3 + 3 * phi.shape[1] : 3] = phi
