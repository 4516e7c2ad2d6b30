"""``eddy_current``: currents induced in the airframe by the rotating field (``E_s``, (M5))."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from pipeline.core.geometry import right_times
from pipeline.core.vocabulary import EffectKind
from pipeline.core.words import vec
from pipeline.model.effects.base import (
    F64,
    Effect,
    FitView,
    Linearisation,
    Motion,
    register,
    standard_deviations,
)
from pipeline.model.effects.time_offset import steady_turn_reason

#: Projector (9, 9) of a row-major ``E_s`` onto its traceless part, ``E_s - tr(E_s)/3 I``.
#: Beside a time offset the eddy term has only these 8 directions: its isotropic part is the
#: time offset's (``E_s = -tau I`` to first order, (M5) against (M1) at ``t - tau``).
TRACELESS_PROJECTOR = np.eye(9) - np.outer(np.eye(3).ravel(), np.eye(3).ravel()) / 3.0

#: Orthonormal basis (8, 9) of the traceless 3x3 matrices, row-major: the part of ``E_s``
#: that a time offset (``E_s = -tau I``, CONVENTIONS eddy_current) cannot produce.
TRACELESS_BASIS = np.array(
    [np.eye(3)[i][:, None] @ np.eye(3)[j][None, :] for i in range(3) for j in range(3)
     if i != j]
    + [np.diag([1.0, -1.0, 0.0]) / np.sqrt(2.0), np.diag([1.0, 1.0, -2.0]) / np.sqrt(6.0)]
).reshape(8, 9)

#: The isotropic direction of ``E_s`` (row-major), unit length: the time offset's.
ISO_DIRECTION = np.eye(3).ravel() / np.sqrt(3.0)


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
    each_round: ClassVar[bool] = True
    rate_signature: ClassVar[bool] = True
    n_fixed: ClassVar[int | None] = 9
    confounded_with: ClassVar[str] = "the time offset and the misalignment"
    shares_with: ClassVar[EffectKind | None] = EffectKind.TIME_OFFSET
    contains: ClassVar[EffectKind | None] = EffectKind.TIME_OFFSET
    # where the sensor barely turns, db/dt is perpendicular to b and I/3 - b b' acts as a
    # third of the identity: a traceless term reads as a lag
    trades_with: ClassVar[frozenset[EffectKind]] = frozenset({EffectKind.TIME_OFFSET})

    def motion_reason(self, motion: Motion, horizontal_fraction: float | None) -> str | None:
        """Return the time offset's :func:`steady_turn_reason` (:meth:`Effect.motion_reason`)."""
        return steady_turn_reason(motion)

    def params(self, term: Any, value: F64, fit: FitView) -> dict[str, Any]:
        """Return the CONVENTIONS params (see :meth:`Effect.params`)."""
        return {"E_s": value.reshape(3, 3).tolist()}

    def sigma(self, term: Any, cov: F64, fit: FitView) -> dict[str, Any]:
        """Return their 1-sigma (see :meth:`Effect.sigma`)."""
        sd = standard_deviations(cov)
        return {"E_s": sd.reshape(3, 3).tolist()}

    def eddy_matrix(self, term: Any, value: F64, gauged: bool) -> F64:
        """Return ``E_s`` (3, 3): beside a time offset its traceless part only."""
        return np.asarray(TRACELESS_PROJECTOR @ value if gauged else value).reshape(3, 3)

    def gauge_projector(self) -> F64:
        """Return :data:`TRACELESS_PROJECTOR`: beside a time offset ``E_s`` is traceless.

        The lag is exact in the model ((M1) at ``t - tau``, the attitude re-interpolated)
        while the eddy term's regressor is a rate smoothed over neighbouring attitude
        samples; left free, the shared direction moves ``tau`` and ``tr(E_s)`` together so
        that the signal stays and only the point where the noisy attitude is read moves
        (towards where its interpolated noise is smallest).
        """
        return TRACELESS_PROJECTOR

    def kept_basis(self) -> F64:
        """Return :data:`TRACELESS_BASIS`, the 8 directions a time offset cannot produce."""
        return TRACELESS_BASIS

    def shared_basis(self) -> F64:
        """Return :data:`ISO_DIRECTION` (1, 9), the time offset's direction."""
        return ISO_DIRECTION[None, :]

    def fold_shared(self, own: F64, other: F64) -> tuple[F64, F64]:
        """Return ``E_s`` traceless and ``tau - tr(E_s)/3`` (``E_s = -tau I``, first order)."""
        iso = float(np.trace(np.asarray(own).reshape(3, 3))) / 3.0
        return TRACELESS_PROJECTOR @ own, other - iso

    def columns(self, term: Any, value: F64, lin: Linearisation, kept: Any, out: F64) -> None:
        """Write ``dy_i/dE_ij = ydot0_j`` (row-major ``E``) (see :meth:`Effect.columns`)."""
        for r_ in range(3):
            out[:, r_, 3 * r_ : 3 * r_ + 3] = lin.ydot0
        if self.kind in lin.gauged:  # beside a time offset only the traceless part
            out[:] = right_times(out, TRACELESS_PROJECTOR)

    def model_fields(self, params: dict[str, Any]) -> dict[str, Any]:
        """Return ``E_s`` for the restore (see :meth:`Effect.model_fields`)."""
        return {"E_s": np.asarray(params["E_s"], dtype=float).reshape(3, 3)}

    def sentence(self, params: dict[str, Any], sigma: dict[str, Any]) -> str:
        """Return the lag of each axis in ms (see :meth:`Effect.sentence`)."""
        ed = 1e3 * np.diag(np.asarray(params["E_s"], float))
        return (f"Eddy currents: the reading lags changes of the field by {vec(ed, 2)} ms "
                f"(x, y, z).")
