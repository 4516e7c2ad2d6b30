"""The estimator registry: the framework's kinds, each with its class; they feed the CLI and the
campaign validation."""

from __future__ import annotations

import argparse
import enum
import importlib.util

import pytest

import pipeline.core.vocabulary as vocabulary
from pipeline.core.errors import UsageError
from pipeline.core.vocabulary import EstimatorKind
from stages.estimate import make_estimator
from stages.estimators import registry
from stages.estimators.base import Estimator
from stages.estimators.registry import DESCRIPTIONS, ESTIMATORS


def test_every_registered_estimator_is_built_and_fits():
    import numpy as np

    from pipeline.core.geometry import matrix_to_quat, quat_to_rotvec
    from stages.estimate import fit_calibration
    from stages.estimators.base import NoiseModel
    from stages.estimators.synthetic import draw, small_rotation

    assert set(DESCRIPTIONS) == set(ESTIMATORS)
    R = small_rotation(np.array([0.8, -0.5, 1.2]))
    s = draw(kind="multi", n=2000, R_body_mag=R, noise=NoiseModel(1.0),
             rng=np.random.default_rng(0))
    for kind in EstimatorKind:
        est = make_estimator(kind)
        assert isinstance(est, Estimator)
        assert make_estimator(kind.value).__class__ is est.__class__
        # each kind reaches its own class and recovers a 1.5 deg misalignment: 1 nT of
        # noise on a ~37,000 nT field tumbled over 2000 samples fixes it to about 1e-4 deg;
        # 0.01 deg leaves room for the two-step estimators' extra noise
        cal = fit_calibration(None, s.aligned, estimator=kind)
        err = np.degrees(quat_to_rotvec(matrix_to_quat(cal.R_body_mag @ R.T)))
        assert np.all(np.abs(err) < 0.01), (kind.value, err)
        assert cal.estimator == kind.value


def test_unknown_kind_is_an_error_not_a_fall_back():
    with pytest.raises(UsageError, match="unknown estimator 'kalman'"):
        make_estimator("kalman")


def test_cli_and_campaign_choices_come_from_the_registry():
    from pipeline.app import campaign
    from pipeline.app.commands import calibrate

    ap = argparse.ArgumentParser()
    sub = ap.add_subparsers()
    calibrate.add_parser(sub)
    p = sub.choices["calibrate"]
    act = next(a for a in p._actions if a.dest == "estimator")
    assert list(act.choices) == list(ESTIMATORS)
    # the campaign validates against the framework's kinds, which are the registry's
    assert campaign.EstimatorKind is EstimatorKind
    assert [e.value for e in EstimatorKind] == list(ESTIMATORS)


def test_the_registry_implements_exactly_the_frameworks_kinds():
    """One list of names (core's EstimatorKind); the registry maps and describes each, in order."""
    kinds = [k.value for k in EstimatorKind]
    assert list(ESTIMATORS) == kinds
    assert list(DESCRIPTIONS) == kinds


def test_a_registry_that_disagrees_with_the_framework_does_not_load(monkeypatch):
    """A kind the options can spell but nothing implements stops the import, not a later run."""
    more = enum.Enum("EstimatorKind", {**{k.name: k.value for k in EstimatorKind},
                                       "KALMAN": "kalman"}, type=str)
    monkeypatch.setattr(vocabulary, "EstimatorKind", more)
    spec = importlib.util.spec_from_file_location("registry_copy", registry.__file__)
    assert spec is not None and spec.loader is not None
    copy = importlib.util.module_from_spec(spec)  # never put in sys.modules
    with pytest.raises(RuntimeError, match="kalman"):
        spec.loader.exec_module(copy)
