"""``axis_tilt``: the turntable's axis tilted from its nominal direction (``T``, (M2))."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from pipeline.core.geometry import skew, so3_exp
from pipeline.core.vocabulary import EffectKind
from pipeline.model.effects.base import (
    F64,
    Effect,
    FitView,
    Linearisation,
    Motion,
    register,
    standard_deviations,
)


def tilt_basis(axis_enu: F64 | None = None) -> F64:
    """Two unit vectors (3, 2) perpendicular to the nominal turntable axis in ENU (up)."""
    n = np.array([0.0, 0.0, 1.0]) if axis_enu is None else axis_enu / np.linalg.norm(axis_enu)
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(n, a)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    return np.stack([e1, e2], axis=-1)


@register
class AxisTilt(Effect):
    """The ``axis_tilt`` effect (see :class:`~pipeline.model.effects.base.Effect`)."""

    kind: ClassVar[EffectKind] = EffectKind.AXIS_TILT
    physics: ClassVar[str] = (
        "the turntable's rotation axis is not where its nominal axis says (mechanical tilt of "
        "the table), so the attitude derived from its angle is wrong (Tang et al. 2016)"
    )
    signature: ClassVar[str] = (
        "a once-per-turn residual that a known reference field exposes"
    )
    frame: ClassVar[str] = "enu"
    each_round: ClassVar[bool] = True
    turntable_only: ClassVar[bool] = True
    # With a known field only the angle between the axis and B is determined (Tang 2016):
    # a lean across the field's bearing turns B about the axis, which R_body_mag absorbs.
    identifiable_in_part: ClassVar[bool] = True
    n_fixed: ClassVar[int | None] = 2
    holds_frame: ClassVar[bool] = True

    def turn_frame(self, T_enu: F64, step: F64) -> F64:
        """Return ``exp([P step]x) T_enu``: the tilt turns the field on the left (Tang 2016)."""
        return so3_exp(tilt_basis() @ step) @ T_enu

    def columns(self, term: Any, value: F64, lin: Linearisation, kept: Any, out: F64) -> None:
        """Write ``d(T.T B)/dd = T.T [B]x`` on the tilt's basis (see :meth:`Effect.columns`).

        ``T.T <- T.T exp(-[d]x)`` with ``d = basis @ (2 params)``.
        """
        out[:] = np.matmul(np.matmul(lin.Gp, lin.TT), skew(lin.Bt)) @ tilt_basis()

    def motion_reason(self, motion: Motion, horizontal_fraction: float | None) -> str | None:
        """Return why a tilt needs a reference field (see :meth:`Effect.motion_reason`)."""
        if not motion.field_known:
            return (
                "a tilt of the rotation axis is absorbed exactly by the misalignment and the field "
                "while the field is estimated; give a reference field to determine it"
            )
        return None

    def params(self, term: Any, value: F64, fit: FitView) -> dict[str, Any]:
        """Return the CONVENTIONS params (see :meth:`Effect.params`)."""
        axis_true = fit.T_enu @ np.array([0.0, 0.0, 1.0])
        tilt = float(np.degrees(np.arccos(np.clip(axis_true[2], -1.0, 1.0))))
        az = float(np.degrees(np.arctan2(axis_true[0], axis_true[1])) % 360.0)
        return {"tilt_deg": tilt, "azimuth_deg": az}

    def sigma(self, term: Any, cov: F64, fit: FitView) -> dict[str, Any]:
        """Return their 1-sigma (see :meth:`Effect.sigma`)."""
        sd = standard_deviations(cov)
        return {"tilt_deg": float(np.degrees(np.max(sd)))}

    def remark(self, params: dict[str, Any], duration_s: float, note: str | None = None) -> str:
        """Return what the fitted values suggest (see :meth:`Effect.remark`)."""
        text = ""
        text += (
            f". The axis leans {params['tilt_deg']:.3g} deg towards bearing "
            f"{params['azimuth_deg']:.0f} deg. With the misalignment estimated, the readings fix "
            "only the angle between the rotation axis and the field: every axis on that cone "
            "around B fits equally (a lean across the field's bearing turns B about the axis, "
            "which the misalignment absorbs), and the one of least tilt, leaning along the "
            "field's bearing, is reported. The true tilt is at least this large; a mounting "
            "known from another calibration would determine its direction"
        )
        return text

    def sentence(self, params: dict[str, Any], sigma: dict[str, Any]) -> str:
        """Return the tilt and its azimuth (see :meth:`Effect.sentence`)."""
        return (f"The turntable's axis is tilted by {float(params['tilt_deg']):.3f}\u00b0 "
                f"towards azimuth {float(params['azimuth_deg']):.0f}\u00b0.")
