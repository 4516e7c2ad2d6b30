"""The estimator registry: kind -> the class that implements it (``module:Class``).

The kinds are the framework's (:class:`pipeline.core.vocabulary.EstimatorKind`: the names the
command line, the campaign files and the runner spell); this table says only what implements
each. Adding an estimator is one new module in this package (a class with ``fit(problem) ->
Calibration``, its hyperparameters as constructor fields with defaults), one member of
``EstimatorKind`` and one line here. The command-line choices, the campaign validation and
the docs are made from these tables; an unknown kind is an error, never a silent fall-back.
"""

from __future__ import annotations

from pipeline.core.vocabulary import EstimatorKind

#: kind (CONVENTIONS ``--estimator`` value) -> "module:Class", in the order shown to users.
ESTIMATORS: dict[str, str] = {
    EstimatorKind.ML.value: "stages.estimators.ml:MLEstimator",
    EstimatorKind.LI2020.value: "stages.estimators.li2020:Li2020Estimator",
    EstimatorKind.ELLIPSOID.value: "stages.estimators.ellipsoid:EllipsoidEstimator",
    EstimatorKind.DPI.value: "stages.estimators.dpi:DpiEstimator",
}

#: One line per kind for help texts and docs.
DESCRIPTIONS: dict[str, str] = {
    EstimatorKind.ML.value: "joint maximum likelihood of rotation, field and the requested "
    "terms (default), with global checks",
    EstimatorKind.LI2020.value: "Li et al. 2020, virtual auxiliary vector (Section 3)",
    EstimatorKind.ELLIPSOID.value: "magnetometer-only hard/soft-iron ellipsoid, then Wahba "
    "(two-step baseline)",
    EstimatorKind.DPI.value: "dot-product invariance with the vertical implied by the attitude",
}

# One source of truth for the names: a kind the framework spells but nothing implements (or
# an implementation under a name the options cannot spell) would fail only when chosen, so
# the registry refuses to load unless it covers exactly the framework's kinds, in its order.
_KINDS = [k.value for k in EstimatorKind]
if list(ESTIMATORS) != _KINDS or list(DESCRIPTIONS) != _KINDS:
    raise RuntimeError(
        f"the estimator registry ({', '.join(ESTIMATORS)}; described: "
        f"{', '.join(DESCRIPTIONS)}) does not name exactly the kinds of "
        f"pipeline.core.vocabulary.EstimatorKind ({', '.join(_KINDS)}) in their order")
