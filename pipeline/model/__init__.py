"""The one measurement model of magalign (CONVENTIONS, "Measurement model").

More in docs/modules.md, ``pipeline.model``.
"""

from pipeline.model.attitude import AttitudeInterpolator, auto_max_gap_s, interpolate_attitude
from pipeline.model.forward import (
    ForwardModel,
    Restoration,
    evaluate,
    jacobian,
    predict,
    reading,
    restore,
)
from pipeline.model.solve import levenberg_marquardt, minimise

__all__ = [
    "AttitudeInterpolator",
    "ForwardModel",
    "Restoration",
    "auto_max_gap_s",
    "evaluate",
    "interpolate_attitude",
    "jacobian",
    "levenberg_marquardt",
    "minimise",
    "predict",
    "reading",
    "restore",
]
