"""Time offset nested in eddy currents: the simpler term wins.

A time offset is the isotropic eddy term ``E_s = -tau I`` to first order. When a time offset
explains the data it is reported as ``time_offset``; ``eddy_current`` only for what a time
offset cannot explain (its anisotropic, traceless part).

Tests named ``test_wiring_*`` are self-model tests: their data come from
``tests/_diag_sim.py``, which makes them with ``stages.diagnose.model.evaluate``, the model
the diagnosis fits. They check the wiring (search, fit, Jacobians, evidence, output),
not the physics: a sign or convention error shared by the model and the data passes
them. ``test_independent_*`` holds the same rule on recordings
written by ``tests/indep_gen.py``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import semireal
from _diag_sim import make_data
from indep_gen import Spec, effect_params, write

from pipeline.app.commands.diagnose import diagnose_file
from pipeline.core.vocabulary import EffectKind as K
from stages.diagnose.model import Term
from stages.diagnose.search import diagnose_data


def _close(est, true, sig, rel=0.1):
    est, true, sig = (np.asarray(x, dtype=float) for x in (est, true, sig))
    return bool(np.all(np.abs(est - true) <= np.maximum(3 * sig, rel * np.max(np.abs(true)))))


def test_wiring_time_offset_and_anisotropic_eddy_both_reported_split_canonically():
    E = np.diag([0.003, -0.003, 0.0])
    data, _ = make_data((Term(K.TIME_OFFSET), Term(K.EDDY_CURRENT)),
                        (np.array([0.01]), E.ravel()), duration_s=60.0, noise_nT=2.0, seed=11)
    diag, _ = diagnose_data(data)
    f = {x.effect: x for x in diag.findings}
    assert set(f) == {"time_offset", "eddy_current"}
    assert _close(f["time_offset"].params["time_offset_s"], 0.01,
                  f["time_offset"].sigma["time_offset_s"])
    Ef = np.asarray(f["eddy_current"].params["E_s"])
    assert abs(np.trace(Ef)) < 1e-9  # the isotropic part is the time offset's
    assert _close(Ef, E, f["eddy_current"].sigma["E_s"])


def test_wiring_purely_anisotropic_eddy_is_not_a_time_offset():
    E = np.diag([0.004, -0.004, 0.0])
    data, _ = make_data((Term(K.EDDY_CURRENT),), (E.ravel(),), duration_s=60.0, noise_nT=2.0,
                        seed=11)
    diag, _ = diagnose_data(data)
    assert [x.effect for x in diag.findings] == ["eddy_current"]


@pytest.mark.parametrize("tau_s", [-0.007, 0.04])
def test_wiring_time_offset_alone_is_not_eddy(tau_s):
    data, _ = make_data((Term(K.TIME_OFFSET),), (np.array([tau_s]),), duration_s=60.0,
                        noise_nT=2.0, seed=12)
    diag, _ = diagnose_data(data)
    assert [x.effect for x in diag.findings] == ["time_offset"]


@pytest.mark.parametrize("tau_s", [0.1, -0.1])
def test_independent_large_lag_fast_rotation(tmp_path: Path, tau_s):
    # +-100 ms at up to ~5 rad/s (swings of 25 deg at 1.2-1.5 Hz), mag 100 Hz, attitude 50 Hz:
    # one time_offset, nothing else (no step at the ends where t - tau leaves the track)
    s = Spec(name="lag", seed=41, duration_s=30.0, mag_rate_hz=100.0, att_rate_hz=50.0,
             att_phase_s=0.005, freqs_hz=(1.2, 1.5, 1.3), amps_deg=(25.0, 25.0, 25.0),
             effects={"time_offset": {"time_offset_s": tau_s}})
    ctx = diagnose_file(write(s, tmp_path / "lag.mcap"))
    f = {x.effect: x for x in ctx.diagnosis.findings}
    assert set(f) == {"time_offset"}
    assert _close(f["time_offset"].params["time_offset_s"], tau_s,
                  f["time_offset"].sigma["time_offset_s"])


# The seam between a lag and eddy currents on independent recordings. The attitude comes at
# twice or half the magnetometer's rate, so the magnetometer samples fall at one or two places
# between attitude samples, and its noise (0.03 deg) is large: a fit free to move where it
# reads the noisy attitude gains by it. A lag of 5-100 ms with 5 % soft iron under slow
# multi-axis swings must come out as a time offset within its sigma and nothing of eddy
# currents; an anisotropic, non-symmetric eddy term (traceless, or with a trace that is a
# lag only to first order) under 1.5-1.7 Hz vibration as eddy currents and no time offset.

_SOFT_D = effect_params("soft_iron", np.random.default_rng(4), 12.5, 20.0)[1]["D"]  # 5 %

_E_ANISO = np.array([[0.003, 0.002, -0.001], [-0.0015, -0.001, 0.0025],
                     [0.0005, -0.002, -0.002]])  # traceless, not symmetric
_E_TRACE = _E_ANISO + np.diag([0.002, 0.0, 0.001])  # tr/3 = 1 ms: a lag to first order


def _seam_spec(name: str, mag_hz: float, att_hz: float, **kw) -> Spec:
    return Spec(name=name, seed=kw.pop("seed"), duration_s=20.0, mag_rate_hz=mag_hz,
                att_rate_hz=att_hz, att_phase_s=0.003, att_noise_deg=0.03, mag_noise_nT=2.0,
                **kw)


@pytest.mark.parametrize("tau_s,att_ratio", [
    (0.005, 2.0), (-0.005, 0.5), (-0.025, 2.0), (0.025, 0.5),
    (0.045, 2.0), (-0.045, 0.5), (-0.1, 2.0), (0.1, 0.5)])
def test_independent_lag_with_soft_iron_is_no_eddy(tmp_path: Path, tau_s, att_ratio):
    # pose at 100 Hz, the magnetometer at 50 or 200 Hz
    s = _seam_spec("lag", 100.0 / att_ratio, 100.0, seed=61, freqs_hz=(0.17, 0.22, 0.15),
                   amps_deg=(30.0, 25.0, 20.0),
                   effects={"time_offset": {"time_offset_s": tau_s}, "soft_iron": {"D": _SOFT_D}})
    ctx = diagnose_file(write(s, tmp_path / "lag.mcap"))
    f = {x.effect: x for x in ctx.diagnosis.findings}
    assert set(f) in ({"time_offset", "soft_iron"}, {"time_offset"}), list(f)
    tau, sig = f["time_offset"].params["time_offset_s"], f["time_offset"].sigma["time_offset_s"]
    assert abs(tau - tau_s) <= 3 * sig, (tau, sig)


@pytest.mark.parametrize("E,att_ratio,vib_hz", [
    (_E_ANISO, 2.0, 1.5), (-_E_ANISO, 0.5, 1.7), (_E_TRACE, 0.5, 1.5), (-_E_TRACE, 2.0, 1.7)],
    ids=["traceless-att2x", "traceless-neg-att0.5x", "trace-att0.5x", "trace-neg-att2x"])
def test_independent_anisotropic_eddy_under_vibration_is_no_lag(tmp_path: Path, E, att_ratio,
                                                                vib_hz):
    mag_hz = 50.0 if att_ratio == 2.0 else 100.0
    s = _seam_spec("eddy", mag_hz, mag_hz * att_ratio, seed=62, vib_deg=5.0, vib_hz=vib_hz,
                   effects={"eddy_current": {"E_s": E.tolist()}})
    ctx = diagnose_file(write(s, tmp_path / "eddy.mcap"))
    f = {x.effect: x for x in ctx.diagnosis.findings}
    assert set(f) == {"eddy_current"}, list(f)
    # the eddy regressor is a rate over +-3 attitude samples: a few per cent low at 1.5 Hz
    assert _close(f["eddy_current"].params["E_s"], E, f["eddy_current"].sigma["E_s"])


@pytest.mark.parametrize("tau_s", [0.025, -0.025])
def test_independent_lag_on_a_sensor_that_barely_turns_is_no_eddy(tmp_path: Path, tau_s):
    # The stability corpus' indep_tr: swings of 2-3 deg while the platform translates,
    # attitude and magnetometer at 100 Hz with their noise, the lag injected by stamping
    # the readings late. db/dt is then perpendicular to b, where a traceless eddy term along
    # I/3 - b b.T reads as a third of a lag: the pair could trade along it. The lag stays one
    # time offset, not a shorter lag and the eddy term that makes up the rest
    rec, _ = semireal.stability_base("indep_tr")
    inj, _, _ = semireal.inject(rec, "time_offset", tau_s)
    semireal.write_real(inj, tmp_path / "lag.mcap")
    ctx = diagnose_file(tmp_path / "lag.mcap")
    f = {x.effect: x for x in ctx.diagnosis.findings}
    assert set(f) == {"time_offset"}, list(f)
    assert abs(f["time_offset"].params["time_offset_s"] - tau_s) <= 0.1 * abs(tau_s)


def test_a_term_another_acts_through_stays_while_that_one_does():
    """nested.REQUIRES: a map acts through the gradient, a lever arm through any spatial term.

    The backward step keeps the last term of a kind another term requires, and only that.
    """
    from stages.diagnose.nested import required

    g, m, h = Term(K.FIELD_GRADIENT), Term(K.FIELD_MAP), Term(K.HARD_IRON)
    lever = Term(K.LEVER_ARM)
    assert required(0, (g, m))  # the map's gradient
    assert not required(1, (g, m))  # nothing acts through the map
    assert not required(0, (g, h)) and not required(1, (g, h))
    assert required(0, (g, lever))  # the lever arm's only spatial term
    assert required(0, (g, m, lever))  # the map still needs the gradient
    src = Term(K.LOCAL_SOURCE)
    assert not required(1, (g, src, lever))  # the source still carries the lever arm's field
    assert required(0, (g, src, m, lever))  # ... but the map needs the gradient itself
