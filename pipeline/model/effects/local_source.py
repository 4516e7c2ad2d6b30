"""``local_source``: a compact magnetised object fixed in the surroundings (a dipole, ``F(t)``)."""

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
class LocalSource(Effect):
    """The ``local_source`` effect (see :class:`~pipeline.model.effects.base.Effect`)."""

    kind: ClassVar[EffectKind] = EffectKind.LOCAL_SOURCE
    physics: ClassVar[str] = (
        "a compact magnetised object fixed in the surroundings (a magnet or a tool on a "
        "table, buried steel, a parked vehicle): it stays where it is while the sensor moves"
    )
    signature: ClassVar[str] = (
        "an ENU residual that grows steeply (as the cube of the inverse distance) wherever "
        "the sensor comes near one place, whenever that is"
    )
    frame: ClassVar[str] = "enu"
    # tested at zero moment, where the position has no gradient: the moment carries the
    # evidence (the position is fitted once the moment is there)
    identifiable_in_part: ClassVar[bool] = True

    def n_params(self, term: TermShape) -> int:
        """Return position (3) and moment (3), plus the bearing of the position frame."""
        return 7 if term.fit_yaw else 6

    def params(self, term: Any, value: F64, fit: FitView) -> dict[str, Any]:
        """Return the CONVENTIONS params (see :meth:`Effect.params`)."""
        return fit.source_params(term, value)

    def sigma(self, term: Any, cov: F64, fit: FitView) -> dict[str, Any]:
        """Return their 1-sigma (see :meth:`Effect.sigma`)."""
        sd = standard_deviations(cov)
        return {"position_m": sd[0:3].tolist(), "moment_Am2": sd[3:6].tolist(),
                "closest_approach_m": float(np.linalg.norm(sd[0:3]))}

    def remark(self, params: dict[str, Any], duration_s: float, note: str | None = None) -> str:
        """Return what the fitted values suggest (see :meth:`Effect.remark`)."""
        text = ""
        pos = ", ".join(f"{x:.2f}" for x in params["position_m"])
        m = float(np.linalg.norm(params["moment_Am2"]))
        frame = ("the attitude source's own frame (the motion-capture room)"
                 if params.get("position_frame") == "attitude_source_local" else "local ENU")
        text += f". Located at ({pos}) m in {frame}, moment {m:.3g} A m^2"
        if params.get("closest_approach_m") is not None:
            text += (f"; the sensor came closest, {100 * params['closest_approach_m']:.0f} cm, "
                     f"at {params['closest_approach_s']:.1f} s")
        text += (
            ". It belongs to the surroundings, not to the sensor: the restored field keeps it "
            "(a survey maps it); calibrate away from it, or keep it in the model"
        )
        return text
