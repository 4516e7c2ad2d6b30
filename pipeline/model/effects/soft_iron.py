"""``soft_iron``: induced magnetisation and unequal axis gains (``D = I + S``, (M4))."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from pipeline.core.vocabulary import EffectKind
from pipeline.core.words import vec
from pipeline.model.effects.base import F64, Effect, FitView, Linearisation, register
from pipeline.model.forward import soft_iron_jacobian

#: Symmetric traceless basis of the soft-iron deviation S (5 matrices, ``S = sum_k s_k S_k``):
#: the trace of D is the field magnitude's job when B_enu is free (D = s I and B/s predict the
#: same readings).
SOFT_BASIS = np.zeros((5, 3, 3))
SOFT_BASIS[0] = np.diag([1.0, -1.0, 0.0])
SOFT_BASIS[1] = np.diag([1.0, 1.0, -2.0]) / np.sqrt(3.0)
for _k, (_i, _j) in enumerate([(0, 1), (0, 2), (1, 2)]):
    SOFT_BASIS[2 + _k, _i, _j] = SOFT_BASIS[2 + _k, _j, _i] = 1.0


@register
class SoftIron(Effect):
    """The ``soft_iron`` effect (see :class:`~pipeline.model.effects.base.Effect`)."""

    kind: ClassVar[EffectKind] = EffectKind.SOFT_IRON
    physics: ClassVar[str] = (
        "induced magnetisation of soft-magnetic parts near the sensor and unequal axis "
        "gains or non-orthogonal axes of the sensor: the sphere of readings becomes an ellipsoid"
    )
    signature: ClassVar[str] = (
        "a residual that grows with the field component along some mag axes and flips sign "
        "with it (twice per turn)"
    )
    frame: ClassVar[str] = "mag"
    each_round: ClassVar[bool] = True
    n_fixed: ClassVar[int | None] = 5
    confounded_with: ClassVar[str] = "the field magnitude and the misalignment"
    # Each traceless parameter (scale differences and cross-axis coupling, dimensionless):
    # typical of MEMS magnetometers, and of the lab sensor, whose full recordings determine
    # D - I up to 0.02.
    held_prior: ClassVar[float | None] = 0.01

    def params(self, term: Any, value: F64, fit: FitView) -> dict[str, Any]:
        """Return the CONVENTIONS params (see :meth:`Effect.params`)."""
        return {"D": fit.D.tolist()}

    def sigma(self, term: Any, cov: F64, fit: FitView) -> dict[str, Any]:
        """Return their 1-sigma (see :meth:`Effect.sigma`)."""
        # Var(D_ij) = sum_kl B_k,ij B_l,ij cov_kl
        var = np.einsum("kij,kl,lij->ij", SOFT_BASIS, cov, SOFT_BASIS)
        return {"D": np.sqrt(np.clip(var, 0, None)).tolist()}

    def columns(self, term: Any, value: F64, lin: Linearisation, kept: Any, out: F64) -> None:
        """Write ``dy/ds_k = S_k m + E S_k mdot``, (J4) (see :meth:`Effect.columns`)."""
        out[:] = soft_iron_jacobian(SOFT_BASIS, lin.m, lin.mdot, lin.E)

    def model_fields(self, params: dict[str, Any]) -> dict[str, Any]:
        """Return ``D`` for the restore (see :meth:`Effect.model_fields`)."""
        return {"D": np.asarray(params["D"], dtype=np.float64).reshape(3, 3)}

    def sentence(self, params: dict[str, Any], sigma: dict[str, Any]) -> str:
        """Return the gains and the largest coupling in % (see :meth:`Effect.sentence`)."""
        d = np.asarray(params["D"], float)
        gains = 100 * (np.diag(d) - 1)
        off = d[~np.eye(3, dtype=bool)]
        return (f"Soft iron or unequal axis gains: the gains differ from 1 by "
                f"{vec(gains, 2)} % (x, y, z) and the axes couple by up to "
                f"{100 * np.max(np.abs(off)):.2f} %.")
