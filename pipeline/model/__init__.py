"""The one measurement model of magalign (CONVENTIONS, "Measurement model").

- :mod:`pipeline.model.attitude`: THE attitude interpolator (C1 cubic on SO(3) with the gap
  rule).
- :mod:`pipeline.model.forward`: prediction ((M1)-(M5); ``reading`` computes (M2)-(M5) for
  every caller), Jacobian ((J1)-(J5)) and restore ((M6), the inverse).
- :mod:`pipeline.model.solve`: THE damped Gauss-Newton core (``minimise``), run by the
  diagnosis, the ML and the streaming estimators.
- :mod:`pipeline.model.calibration`: ``Calibration``, the fitted value (predicts and restores
  through the forward model); :mod:`pipeline.model.tang`, :mod:`pipeline.model.sample_hold`,
  :mod:`pipeline.model.igrf`: the rest of the physics.

The physics layer: imports ``pipeline.core`` only (docs/architecture.md,
``tests/test_layers.py``).
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
