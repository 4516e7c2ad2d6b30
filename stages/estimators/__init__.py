"""Estimators of the misalignment, one module per method, behind the :class:`Estimator` protocol.

- :mod:`.ml`: joint maximum likelihood (default).
- :mod:`.li2020`: Li et al. 2020, Section 3.
- :mod:`.ellipsoid`: magnetometer-only hard/soft iron fit, then Wahba (two-step baseline).
- :mod:`.dpi`: dot-product invariance with the vertical implied by the attitude.
"""

from stages.estimators.base import (
    RELATIVE_INFO_THRESHOLD,
    EstimateTerm,
    EstimationProblem,
    Estimator,
    EstimatorKind,
    NoiseModel,
    RobustLoss,
)

__all__ = [
    "RELATIVE_INFO_THRESHOLD",
    "Estimator",
    "EstimatorKind",
    "NoiseModel",
    "EstimationProblem",
    "RobustLoss",
    "EstimateTerm",
]
