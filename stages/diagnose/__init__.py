"""The Diagnose stage and the effect library it draws on.

``model`` (the terms, the model state, ``evaluate``), ``catalogue`` (names, explanations,
identifiability), ``fit`` (the fit of a model state), ``statistics`` (score tests, the evidence,
held-out blocks), ``search`` (the loop that adds terms), ``result`` (``Diagnosis``,
``DiagnoseConfig``) and ``stage`` (the ``Diagnose`` stage, its calibration and figures).
"""
