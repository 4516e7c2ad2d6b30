"""``field_map``: a smooth field over the area (Laplace eigenfunctions, GP prior, ``F(t)``)."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from pipeline.core.vocabulary import EffectKind
from pipeline.model.effects.base import F64, Effect, FitView, TermShape, register


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

    def params(self, term: Any, value: F64, fit: FitView) -> dict[str, Any]:
        """Return the CONVENTIONS params (see :meth:`Effect.params`)."""
        return fit.map_params(term, value)

    def sigma(self, term: Any, cov: F64, fit: FitView) -> dict[str, Any]:
        """Return their 1-sigma (see :meth:`Effect.sigma`)."""
        sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        return {"weights": sd.tolist(), "peak_to_peak_nT": fit.map_range_sigma(term, cov)}
