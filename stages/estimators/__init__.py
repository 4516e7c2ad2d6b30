"""Estimators of the misalignment, one module per method, behind the :class:`Estimator` protocol.

- :mod:`.ml`: joint maximum likelihood (default).
- :mod:`.li2020`: Li et al. 2020, Section 3.
- :mod:`.ellipsoid`: magnetometer-only hard/soft iron fit, then Wahba (two-step baseline).
- :mod:`.dpi`: dot-product invariance with the vertical implied by the attitude.

The names the options use (``EstimatorKind``, ``EstimateTerm``, ``RobustLoss``) are the
framework's: :mod:`pipeline.core.vocabulary`.
"""

from stages.estimators.base import (
    RELATIVE_INFO_THRESHOLD,
    EstimationProblem,
    Estimator,
    NoiseModel,
)

__all__ = [
    "RELATIVE_INFO_THRESHOLD",
    "Estimator",
    "NoiseModel",
    "EstimationProblem",
]
