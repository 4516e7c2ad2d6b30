"""``lever_arm``: the sensor away from the point the attitude source positions (mag frame, m)."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from pipeline.core.vocabulary import EffectKind
from pipeline.core.words import pm_vec
from pipeline.model.effects.base import (
    CONFOUND_RATIO,
    EFFECTS,
    F64,
    Effect,
    FitView,
    Linearisation,
    Motion,
    register,
    standard_deviations,
)


@register
class LeverArm(Effect):
    """The ``lever_arm`` effect (see :class:`~pipeline.model.effects.base.Effect`)."""

    kind: ClassVar[EffectKind] = EffectKind.LEVER_ARM
    physics: ClassVar[str] = (
        "the magnetometer is not at the point whose position the attitude source reports "
        "(a motion-capture marker body, an INS's reference point): as the platform turns, "
        "the sensor swings around that point through a field that varies in space"
    )
    signature: ClassVar[str] = (
        "a residual that follows the attitude times the field's spatial gradient (strongest "
        "near a local source)"
    )
    frame: ClassVar[str] = "enu"
    each_round: ClassVar[bool] = True
    n_fixed: ClassVar[int | None] = 3
    acts_through: ClassVar[frozenset[EffectKind]] = frozenset(
        {EffectKind.FIELD_GRADIENT, EffectKind.LOCAL_SOURCE, EffectKind.FIELD_MAP})

    def columns(self, term: Any, value: F64, lin: Linearisation, kept: Any, out: F64) -> None:
        """Write ``dy/dl = G (dB/dr) C``, the spatial terms' gradients summed (see below).

        The sensor sits at ``p + C l`` (CONVENTIONS lever_arm), so each term whose field
        depends on the place (:meth:`Effect.gradient_enu`) moves with ``C l``.
        """
        if lin.lever_enu is None:
            return
        dBdr = np.zeros((len(lin.t_s), 3, 3))
        for t2, v2 in lin.terms:
            g = EFFECTS[t2.kind].gradient_enu(t2, v2, lin)
            if g is not None:
                dBdr += g
        out[:] = np.matmul(lin.G, np.matmul(dBdr, np.swapaxes(lin.Ct, 1, 2)))

    def undetermined(self, motion: Motion, efficiency: float,
                     horizontal_fraction: float | None = None) -> str | None:
        """Return why the lever arm cannot be determined: it acts only through a field in space.

        See :meth:`Effect.undetermined`; turning is not needed, a field varying along the path
        is.
        """
        if not motion.has_positions:
            return ("no positions in the recording: the sensor's offset from the tracked "
                    "point acts only through a field that varies in space")
        if efficiency < CONFOUND_RATIO:
            return (
                f"the field varies too little in space along this motion (only {efficiency:.1e} "
                "of the weakest lever-arm direction is independent of the other terms); turn "
                "the platform near a source or in a strong gradient to determine it"
            )
        return None

    def params(self, term: Any, value: F64, fit: FitView) -> dict[str, Any]:
        """Return the CONVENTIONS params (see :meth:`Effect.params`)."""
        return {"lever_arm_body_m": np.asarray(value, dtype=float).tolist()}

    def sigma(self, term: Any, cov: F64, fit: FitView) -> dict[str, Any]:
        """Return their 1-sigma (see :meth:`Effect.sigma`)."""
        sd = standard_deviations(cov)
        return {"lever_arm_body_m": sd.tolist()}

    def remark(self, params: dict[str, Any], duration_s: float, note: str | None = None) -> str:
        """Return what the fitted values suggest (see :meth:`Effect.remark`)."""
        text = ""
        lv = np.asarray(params["lever_arm_body_m"], dtype=float)
        text += (
            f". The magnetometer sits {100 * float(np.linalg.norm(lv)):.1f} cm from the tracked "
            "point, at (" + ", ".join(f"{100 * x:+.1f}" for x in lv) + ") cm in the body "
            "frame; set this offset in the survey's lever-arm configuration"
        )
        return text

    def model_fields(self, params: dict[str, Any]) -> dict[str, Any]:
        """Return the lever arm for the restore (see :meth:`Effect.model_fields`)."""
        return {"lever_arm_body_m": np.asarray(params["lever_arm_body_m"],
                                               dtype=np.float64).reshape(3)}

    def sentence(self, params: dict[str, Any], sigma: dict[str, Any]) -> str:
        """Return the lever arm in cm with its sigma (see :meth:`Effect.sentence`)."""
        lv = 100 * np.asarray(params["lever_arm_body_m"], float)
        sl = sigma.get("lever_arm_body_m")
        return (f"The magnetometer sits {np.linalg.norm(lv):.1f} cm from the tracked point: "
                f"{pm_vec(lv, None if sl is None else 100 * np.asarray(sl, float), 1)} cm "
                "along the body's x, y, z.")
