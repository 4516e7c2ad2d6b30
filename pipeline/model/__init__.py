"""The one measurement model of magalign (CONVENTIONS, "Measurement model").

- :mod:`pipeline.model.attitude`: THE attitude interpolator (SLERP with the gap rule).
- :mod:`pipeline.model.forward`: prediction, Jacobian and restore (inverse).
- :mod:`pipeline.model.solve`: THE damped Gauss-Newton core.
- :mod:`pipeline.model.calibration`: ``Calibration``, the fitted value (predicts and restores
  through the forward model); :mod:`pipeline.model.tang`, :mod:`pipeline.model.sample_hold`,
  :mod:`pipeline.model.igrf`: the rest of the physics.

The physics layer: imports ``pipeline.core`` only (docs/architecture.md,
``tests/test_layers.py``).
"""

from pipeline.model.attitude import AttitudeInterpolator, auto_max_gap_s, interpolate_attitude
from pipeline.model.forward import ForwardModel, Restoration, evaluate, jacobian, predict, restore
from pipeline.model.solve import levenberg_marquardt

__all__ = [
    "AttitudeInterpolator",
    "ForwardModel",
    "Restoration",
    "auto_max_gap_s",
    "evaluate",
    "interpolate_attitude",
    "jacobian",
    "levenberg_marquardt",
    "predict",
    "restore",
]
