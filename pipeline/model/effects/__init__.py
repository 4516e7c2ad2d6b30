"""The effects as plug-ins: one module per effect, each registered under its kind.

Importing this package imports every effect module once; each module's ``@register`` puts
its :class:`~pipeline.model.effects.base.Effect` into :data:`EFFECTS`. A new effect is one
module in this package and one line in the import list below (and its name in
:class:`~pipeline.core.vocabulary.EffectKind`, the CONVENTIONS vocabulary).
"""

from __future__ import annotations

from pipeline.core.vocabulary import EffectKind
from pipeline.model.effects import (  # noqa: F401  (imported for their registration)
    axis_tilt,
    disturbance,
    eddy_current,
    field_drift,
    field_gradient,
    field_map,
    hard_iron,
    hard_iron_step,
    heading_drift,
    lever_arm,
    local_source,
    sample_hold,
    soft_iron,
    time_offset,
)
from pipeline.model.effects.base import EFFECTS, Effect, TermShape

# Every CONVENTIONS name has exactly one module: a missing or extra one fails at import,
# not at the first recording that needs it.
if set(EFFECTS) != set(EffectKind):
    raise ImportError(f"effect modules do not match EffectKind: {set(EffectKind) ^ set(EFFECTS)}")

#: Prior sizes of the sensor iron a recording's motion cannot determine, or determines only
#: in part, by CONVENTIONS name in EffectKind's order (``hard_iron`` before ``soft_iron``,
#: the order the outputs list them in; not the modules' import order): each module's
#: ``held_prior``, where it states and justifies its size.
IRON_PRIOR: dict[str, float] = {
    k.value: p for k in EffectKind if (p := EFFECTS[k].held_prior) is not None}



def kin_words(effects: list[str], params: list[dict], short: bool = False) -> list[str]:
    """Return what each finding says about the others of its effect (``Effect.beside_kin``).

    ``effects`` and ``params``: the findings' names and CONVENTIONS values, in the order
    found; one text per finding (empty: nothing to add). The explanation and the report's
    sentence (``short``) both take them from here.
    """
    out = [""] * len(effects)
    for k in EffectKind:
        idx = [i for i, e in enumerate(effects) if e == k.value]
        if len(idx) > 1:
            for i, w in zip(idx, EFFECTS[k].beside_kin([params[i] for i in idx], short),
                            strict=True):
                out[i] = w
    return out


__all__ = ["EFFECTS", "IRON_PRIOR", "Effect", "TermShape", "kin_words"]
