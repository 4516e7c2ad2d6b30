"""``hard_iron``: a permanent field fixed to the sensor (mag frame offset ``o``, (M5))."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from pipeline.core.vocabulary import EffectKind
from pipeline.core.words import pm_vec
from pipeline.model.effects.base import (
    F64,
    SINGLE_AXIS_SPREAD,
    Effect,
    FitView,
    Linearisation,
    Motion,
    register,
    standard_deviations,
)


@register
class HardIron(Effect):
    """The ``hard_iron`` effect (see :class:`~pipeline.model.effects.base.Effect`)."""

    kind: ClassVar[EffectKind] = EffectKind.HARD_IRON
    physics: ClassVar[str] = (
        "a permanent field fixed to the sensor: magnetised steel or a battery near the "
        "magnetometer, or the sensor's own bias; it turns with the platform"
    )
    signature: ClassVar[str] = (
        "a constant residual in the mag frame, the same whatever the heading"
    )
    frame: ClassVar[str] = "mag"
    each_round: ClassVar[bool] = True
    n_fixed: ClassVar[int | None] = 3
    # Each offset component, nT: typical of MEMS magnetometers, and of the lab sensor, whose
    # full recordings determine offsets of 300-500 nT.
    held_prior: ClassVar[float | None] = 500.0

    def motion_reason(self, motion: Motion, horizontal_fraction: float | None) -> str | None:
        """Return why one axis of turning leaves part of it unknown (see the base class)."""
        if motion.axis_spread < SINGLE_AXIS_SPREAD and not motion.field_known:
            return (
                "the sensor turned about a single axis only: the part of the offset along that "
                "axis looks the same as the unknown field; turn it about a second axis or give a "
                "reference field"
            )
        return None

    def params(self, term: Any, value: F64, fit: FitView) -> dict[str, Any]:
        """Return the CONVENTIONS params (see :meth:`Effect.params`)."""
        return {"offset_nT": value.tolist()}

    def sigma(self, term: Any, cov: F64, fit: FitView) -> dict[str, Any]:
        """Return their 1-sigma (see :meth:`Effect.sigma`)."""
        sd = standard_deviations(cov)
        return {"offset_nT": sd[:3].tolist()}

    def offset_nT(self, term: Any, value: F64, t_s: F64) -> F64:
        """Return ``o`` of (M5), mag frame, (3,)."""
        return value

    def columns(self, term: Any, value: F64, lin: Linearisation, kept: Any, out: F64) -> None:
        """Write ``dy/do = I`` (see :meth:`Effect.columns`)."""
        out[:] = np.eye(3)

    def model_fields(self, params: dict[str, Any]) -> dict[str, Any]:
        """Return ``o`` for the restore (see :meth:`Effect.model_fields`)."""
        return {"offset_nT": np.asarray(params["offset_nT"], dtype=np.float64).reshape(3)}

    def sentence(self, params: dict[str, Any], sigma: dict[str, Any]) -> str:
        """Return the offset along each axis with its sigma (see :meth:`Effect.sentence`)."""
        o = np.asarray(params["offset_nT"], float)
        return (f"A constant offset (hard iron: magnetised parts near the sensor, or its own "
                f"bias) of {pm_vec(o, sigma.get('offset_nT'))} nT along the magnetometer's x, "
                f"y, z ({np.linalg.norm(o):.0f} nT in all).")
