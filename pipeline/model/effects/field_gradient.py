"""``field_gradient``: a field varying linearly with position (``G (p - p_ref)``, ``F(t)``)."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from pipeline.core.geometry import rot_z
from pipeline.core.vocabulary import EffectKind
from pipeline.model.effects.base import F64, Effect, FitView, register
from pipeline.model.effects.soft_iron import SOFT_BASIS


def gradient_matrix(value: F64, yaw_rad: float = 0.0) -> F64:
    """``G_enu @ Q`` (3, 3), nT/m: ENU field change per metre along the position axes.

    ``G_enu = sum_k value_k S_k`` with ``S_k`` the symmetric traceless basis (a field in free
    space is curl-free, ``G = G.T``, and divergence-free, ``trace G = 0``: 5 parameters),
    ``Q = rot_z(yaw_rad)`` the rotation from the position frame to ENU.
    """
    return np.tensordot(value, SOFT_BASIS, axes=1) @ rot_z(yaw_rad)


@register
class FieldGradient(Effect):
    """The ``field_gradient`` effect (see :class:`~pipeline.model.effects.base.Effect`)."""

    kind: ClassVar[EffectKind] = EffectKind.FIELD_GRADIENT
    physics: ClassVar[str] = (
        "a field that varies from place to place (steel in floors, walls, desks and "
        "equipment indoors; a regional anomaly outdoors), seen as the sensor moves through it"
    )
    signature: ClassVar[str] = (
        "a residual fixed in ENU that follows the sensor's position, not the time"
    )
    frame: ClassVar[str] = "enu"
    n_fixed: ClassVar[int | None] = 5

    def params(self, term: Any, value: F64, fit: FitView) -> dict[str, Any]:
        """Return the CONVENTIONS params (see :meth:`Effect.params`)."""
        ref = np.zeros(3) if fit.p_ref_m is None else np.asarray(fit.p_ref_m, dtype=float)
        return {"G_nT_per_m": gradient_matrix(value, term.yaw_rad).tolist(),
                "position_frame": fit.position_frame or "enu",
                "reference_position_m": ref.tolist()}

    def sigma(self, term: Any, cov: F64, fit: FitView) -> dict[str, Any]:
        """Return their 1-sigma (see :meth:`Effect.sigma`)."""
        # M = sum_k g_k S_k Q: Var(M_ij) = sum_kl (S_k Q)_ij cov_kl (S_l Q)_ij
        SQ = SOFT_BASIS @ rot_z(term.yaw_rad)
        var = np.einsum("kij,kl,lij->ij", SQ, cov, SQ)
        return {"G_nT_per_m": np.sqrt(np.clip(var, 0, None)).tolist()}
