"""The estimator registry: one table feeds the enum, the CLI, the campaign validation."""

from __future__ import annotations

import argparse

import pytest

from pipeline.core.errors import UsageError
from stages.estimate import EstimatorKind, make_estimator
from stages.estimators.base import Estimator
from stages.estimators.registry import DESCRIPTIONS, ESTIMATORS


def test_every_registered_estimator_is_built_and_fits():
    assert list(ESTIMATORS) == [k.value for k in EstimatorKind]
    assert set(DESCRIPTIONS) == set(ESTIMATORS)
    for kind in EstimatorKind:
        est = make_estimator(kind)
        assert isinstance(est, Estimator)
        assert make_estimator(kind.value).__class__ is est.__class__


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
    assert [e.value for e in campaign.EstimatorName] == list(ESTIMATORS)
