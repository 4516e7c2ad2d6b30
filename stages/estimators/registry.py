"""The estimator registry: kind -> the class that implements it (``module:Class``).

Adding an estimator is one new module in this package (a class with ``fit(problem) ->
Calibration``, its hyperparameters as constructor fields with defaults) plus one line here.
The command-line choices, the campaign validation, the ``EstimatorKind`` enum and the docs are
made from this table; an unknown kind is an error, never a silent fall-back.
"""

from __future__ import annotations

#: kind (CONVENTIONS ``--estimator`` value) -> "module:Class", in the order shown to users.
ESTIMATORS: dict[str, str] = {
    "ml": "stages.estimators.ml:MLEstimator",
    "li2020": "stages.estimators.li2020:Li2020Estimator",
    "ellipsoid": "stages.estimators.ellipsoid:EllipsoidEstimator",
    "dpi": "stages.estimators.dpi:DpiEstimator",
}

#: One line per kind for help texts and docs.
DESCRIPTIONS: dict[str, str] = {
    "ml": "joint maximum likelihood of rotation, field and the requested terms (default), "
    "with global checks",
    "li2020": "Li et al. 2020, virtual auxiliary vector (Section 3)",
    "ellipsoid": "magnetometer-only hard/soft-iron ellipsoid, then Wahba (two-step baseline)",
    "dpi": "dot-product invariance with the vertical implied by the attitude",
}
