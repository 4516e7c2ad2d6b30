"""``field_gradient``: a field varying linearly with position (``G (p - p_ref)``, ``F(t)``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from pipeline.core.geometry import each_times_rows, rot_z
from pipeline.core.vocabulary import EffectKind
from pipeline.core.words import per_metre
from pipeline.model.effects.base import (
    F64,
    Effect,
    FitView,
    Linearisation,
    Motion,
    RestorePart,
    Samples,
    register,
)
from pipeline.model.effects.soft_iron import SOFT_BASIS

#: A gradient needs the sensor to move at least this far (RMS about its mean position), m.
MIN_POSITION_SPREAD_M = 0.02

#: ... and at least this fraction of that movement not to be a smooth function of time.
MIN_POSITION_INDEPENDENT = 0.05


def gradient_matrix(value: F64, yaw_rad: float = 0.0) -> F64:
    """``G_enu @ Q`` (3, 3), nT/m: ENU field change per metre along the position axes.

    ``G_enu = sum_k value_k S_k`` with ``S_k`` the symmetric traceless basis (a field in free
    space is curl-free, ``G = G.T``, and divergence-free, ``trace G = 0``: 5 parameters),
    ``Q = rot_z(yaw_rad)`` the rotation from the position frame to ENU.
    """
    return np.tensordot(value, SOFT_BASIS, axes=1) @ rot_z(yaw_rad)


def _per_metre(g_nT_per_m: float) -> str:
    """Words for a gradient: uT/m indoors (steel: thousands of nT/m), nT/m in a survey."""
    # a regional gradient of 2 nT/m would read 0.00 uT/m
    if g_nT_per_m >= 1000.0:
        return f"{g_nT_per_m / 1e3:.2f} uT/m"
    return f"{g_nT_per_m:.2g} nT/m" if g_nT_per_m < 10.0 else f"{g_nT_per_m:.0f} nT/m"


def yaw_of_gradient(M: F64) -> float:
    """Rotation about Up (rad) that makes ``M Q^T`` symmetric: the position frame's yaw.

    For ``M = G_enu Rz(a)`` with ``G_enu`` symmetric, ``M Rz(a)^T`` is symmetric; the
    antisymmetric part of ``M Rz(b)^T`` is checked on a fine grid of ``b`` (defined up to
    half a turn when G has no vertical-horizontal coupling).
    """
    b = np.radians(np.arange(0.0, 360.0, 0.5))
    asym = [np.linalg.norm(M @ rot_z(x).T - (M @ rot_z(x).T).T) for x in b]
    return float(b[int(np.argmin(asym))])



@dataclass(frozen=True, eq=False)
class GradientPart(RestorePart):
    """A fitted ``field_gradient`` in the restore: ``F = M (p - p_ref)`` (+ ``G_enu C l``).

    ``M = G_enu Rz(yaw)`` for positions in a frame turned by ``yaw`` from ENU.
    """

    needs_positions: ClassVar[bool] = True
    M_nT_per_m: F64
    reference_m: F64
    yaw_rad: float

    def field_enu(self, t_s: F64, p_m: F64 | None, lever_enu: F64 | None) -> F64 | None:
        """Return the gradient's field (see :meth:`RestorePart.field_enu`)."""
        if p_m is None:
            return None
        f = (p_m - self.reference_m) @ self.M_nT_per_m.T
        if lever_enu is not None:  # G_enu C l, G_enu = M Rz(yaw).T
            f += lever_enu @ (self.M_nT_per_m @ rot_z(self.yaw_rad).T).T
        return np.asarray(f)


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
    each_round: ClassVar[bool] = True
    n_fixed: ClassVar[int | None] = 5

    def undetermined(self, motion: Motion, efficiency: float,
                     horizontal_fraction: float | None = None) -> str | None:
        """Return why the path cannot determine a gradient (see :meth:`Effect.undetermined`).

        It needs positions that spread and that are not a slow function of time (which a
        field drift would mimic); turning is not needed.
        """
        if not motion.has_positions:
            return "no positions in the recording (the attitude messages carry none)"
        spread, indep = motion.position_confounding()
        if spread < MIN_POSITION_SPREAD_M:
            return (
                f"the sensor hardly moved through space ({spread * 100:.1f} cm RMS about its "
                "mean position): a field gradient has nothing to act on"
            )
        if indep < MIN_POSITION_INDEPENDENT:
            return (
                f"the sensor's path is a slow function of time (only {100 * indep:.1f} % of "
                "the position variance is left after a quartic in time): a gradient along it "
                "cannot be told from a field drift; revisit places at different times"
            )
        if efficiency < 1e-3:
            return (
                "the path through space leaves the gradient confounded with terms already in "
                f"the model (only {efficiency:.1e} of its weakest combination is independent)"
            )
        return None

    def add_field(self, term: Any, value: F64, at: Samples, B_enu: F64) -> Any:
        """Add ``G_enu Q (p - p_ref)``, and ``G_enu C l`` with a lever arm (CONVENTIONS).

        See :meth:`Effect.add_field`.
        """
        B_enu += at.dp_m @ gradient_matrix(value, term.yaw_rad).T
        if at.lever_enu is not None:
            B_enu += at.lever_enu @ gradient_matrix(value, 0.0).T
        return None

    def gradient_enu(self, term: Any, value: F64, at: Samples) -> F64:
        """Return ``G_enu`` (1, 3, 3) (see :meth:`Effect.gradient_enu`)."""
        return gradient_matrix(value, 0.0)[None]

    def columns(self, term: Any, value: F64, lin: Linearisation, kept: Any, out: F64) -> None:
        """Write ``dy/dg_k = G S_k (Q (p - p_ref) + C l)`` (see :meth:`Effect.columns`)."""
        dpq = lin.dp_m @ rot_z(term.yaw_rad).T  # Q (p - p_ref) per row
        if lin.lever_enu is not None:
            dpq = dpq + lin.lever_enu
        dB = each_times_rows(SOFT_BASIS, dpq)  # (N, 3, 5)
        np.matmul(lin.G, dB, out=out)

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

    def remark(self, params: dict[str, Any], duration_s: float, note: str | None = None) -> str:
        """Return what the fitted values suggest (see :meth:`Effect.remark`)."""
        text = ""
        G = np.asarray(params["G_nT_per_m"], dtype=float)
        size = float(np.linalg.norm(G))
        text += (
            f". The fitted gradient is {_per_metre(size)} in all (the root sum of squares of "
            f"G's nine components), {_per_metre(float(np.max(np.abs(G))))} at most in one "
            "component, about the mean position"
        )
        if params.get("position_frame") == "attitude_source_local":
            Q = yaw_of_gradient(G)
            text += (
                "; the positions are in the attitude source's own frame (third axis up, "
                "horizontal axes of unknown bearing), so G is G_enu Q with Q a rotation about "
                f"Up, found at {np.degrees(Q):.0f} deg (where G_enu Q^T is most nearly "
                "symmetric)"
            )
        text += (
            ". Calibrate where the field is uniform (away from steel, or with the sensor kept "
            "at one place while it turns), or keep the positions and this term in the model"
        )
        return text

    def restore_part(self, params: dict[str, Any]) -> GradientPart:
        """Return the gradient for the restore (see :meth:`Effect.restore_part`)."""
        return GradientPart(np.asarray(params["G_nT_per_m"], dtype=float).reshape(3, 3),
                            np.asarray(params.get("reference_position_m") or [0, 0, 0],
                                       dtype=float),
                            float(np.radians(params.get("frame_yaw_deg") or 0.0)))

    def sentence(self, params: dict[str, Any], sigma: dict[str, Any]) -> str:
        """Return the gradient's size and the positions' frame (see :meth:`Effect.sentence`)."""
        g = float(np.linalg.norm(np.asarray(params["G_nT_per_m"], float)))
        frame = ("the attitude source's own frame" if params.get("position_frame")
                 == "attitude_source_local" else "local east, north, up")
        return (f"The field varies from place to place: a gradient of {per_metre(g)} (all "
                f"directions together) as the sensor moves (positions in {frame}).")
