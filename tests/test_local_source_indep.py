"""``local_source`` and ``lever_arm`` against truths made outside the model.

The recordings come from the independent generator (``tests/indep_gen.py``: scipy and the
``mcap_ros2`` writer, no magalign model code) and from a real lab recording with a dipole
injected (``tests/semireal.py``). Each is read and diagnosed through the command's own path
(:func:`pipeline.app.commands.diagnose.diagnose_file`).
"""

from __future__ import annotations

import numpy as np
import pytest
import semireal
from indep_gen import Spec, effect_params, position_m, source_field_nT, truth, write

from pipeline.app.commands.diagnose import diagnose_file

pytestmark = pytest.mark.filterwarnings("ignore::pipeline.core.errors.RecoveredDataWarning")


def _found(ctx, effect):
    return [f for f in ctx.diagnosis.findings if f.effect == effect]


def _rot_err_deg(ctx, spec):
    return np.abs(np.asarray(ctx.calibration.rotvec_body_mag_deg)
                  - np.asarray(spec.rotvec_body_mag_deg))


BURIED = {"local_source": {"position_m": [2.0, 15.0, -1.0], "moment_Am2": [0.0, 20.0, -60.0]}}


@pytest.mark.parametrize(("att_type", "position_type"), [
    ("novatel_oem7_msgs/msg/INSPVA", "inspva"),
    ("sensor_msgs/msg/Imu", "navsatfix"),
])
def test_a_dipole_buried_under_a_survey_line_is_located(tmp_path, att_type, position_type):
    """A ground survey (lines 2 m apart, 20 Hz attitude and positions): a steel object 1 m
    under the ground of the second line, 2 m below the sensor, is found where it is."""
    spec = Spec("buried", seed=11, duration_s=110.0, mag_rate_hz=50.0, att_rate_hz=20.0,
                att_type=att_type, path="survey", position_type=position_type,
                survey_calibration_s=30.0, mag_noise_nT=1.0, att_noise_deg=0.002,
                effects=BURIED)
    tr = truth(spec)["effects"]["local_source"]
    ctx = diagnose_file(write(spec, tmp_path / "buried.mcap"))
    src = _found(ctx, "local_source")
    assert len(src) == 1, [f.effect for f in ctx.diagnosis.findings]
    p = src[0].params
    assert p["position_frame"] == "enu"
    # within 0.5 m (issue 29); the fit does far better on this quiet survey
    assert np.linalg.norm(np.subtract(p["position_m"], tr["position_m"])) < 0.05
    assert np.linalg.norm(np.subtract(p["moment_Am2"], tr["moment_Am2"])) < 1.0  # A m^2
    assert p["position_origin"] == pytest.approx(tr["position_origin"], abs=1e-7)
    assert p["closest_approach_m"] == pytest.approx(tr["closest_approach_m"], abs=0.05)
    assert p["closest_approach_s"] == pytest.approx(tr["closest_approach_s"], abs=0.5)
    # a finding about the surroundings: words that say so, and the evidence against the
    # look-alikes
    assert "surroundings" in src[0].explanation and "evidence" in src[0].explanation
    assert np.all(_rot_err_deg(ctx, spec) < 0.01)


def test_a_magnet_in_the_room_and_the_lever_arm_are_recovered(tmp_path):
    """A magnet beside a place the hand passes (closest 14 cm), the magnetometer 5 cm from
    the tracked point: the source within 1 cm, the lever arm within 1 cm (issue 29)."""
    s0 = Spec("lever", seed=13, duration_s=60.0, mag_noise_nT=2.0)
    c = position_m(s0, np.array([20.0]))[0] + np.array([0.0, 0.0, -0.10])
    lever = [0.03, -0.02, 0.04]
    spec = Spec("lever", seed=13, duration_s=60.0, mag_noise_nT=2.0, effects={
        "local_source": {"position_m": c.tolist(), "moment_Am2": [0.01, -0.004, 0.006]},
        "lever_arm": {"lever_arm_body_m": lever}})
    ctx = diagnose_file(write(spec, tmp_path / "lever.mcap"))
    src, arm = _found(ctx, "local_source"), _found(ctx, "lever_arm")
    assert len(src) == 1 and len(arm) == 1, [f.effect for f in ctx.diagnosis.findings]
    assert src[0].params["position_frame"] == "attitude_source_local"
    assert np.linalg.norm(np.subtract(src[0].params["position_m"], c)) < 0.01
    assert np.linalg.norm(np.subtract(arm[0].params["lever_arm_body_m"], lever)) < 0.01
    assert np.all(_rot_err_deg(ctx, spec) < 0.01)
    # the restored field keeps the source (CONVENTIONS "Sensor and surroundings"), and the
    # final model's residual is the noise
    assert ctx.calibration.residual_rms_nT < 3 * 2.0


@pytest.mark.parametrize(("case", "seed"), [("hard_iron_step", 21), ("disturbance", 22)])
def test_a_magnet_on_the_platform_and_a_passing_vehicle_keep_their_names(tmp_path, case, seed):
    """With positions in the recording, a step that turns with the platform stays a
    ``hard_iron_step`` and a field that changes in time stays a ``disturbance``."""
    _, p, _ = effect_params(case, np.random.default_rng(seed), 20.0, 60.0)
    spec = Spec(case, seed=seed, duration_s=60.0, mag_noise_nT=2.0, effects={case: p})
    ctx = diagnose_file(write(spec, tmp_path / f"{case}.mcap"))
    effects = [f.effect for f in ctx.diagnosis.findings]
    assert case in effects and "local_source" not in effects, effects
    (a, b), = p["windows_s"]
    w = _found(ctx, case)[0].params["windows_s"][0]
    assert abs(w[0] - a) < 1.0 and abs(w[1] - b) < 1.0


def test_a_sensor_that_mostly_translates_gets_no_confident_rotation(tmp_path):
    """Carried through a gradient while turning a few degrees: whatever R comes out, its
    sigma covers the truth (issue 29: confident wrong answers on translating recordings)."""
    G = [[1500.0, 300.0, -200.0], [300.0, -900.0, 400.0], [-200.0, 400.0, -600.0]]
    spec = Spec("translate", seed=15, duration_s=60.0, mag_noise_nT=20.0, path="translate",
                effects={"field_gradient": {"G_nT_per_m": G}})
    ctx = diagnose_file(write(spec, tmp_path / "translate.mcap"))
    err = _rot_err_deg(ctx, spec)
    sig = np.asarray(ctx.calibration.sigma_rotvec_deg)
    assert np.all(err < 3 * sig), (err, sig)
    assert ctx.calibration.verdict.status.value != "OK"


LAB5 = semireal.REAL_DIR / "lab_05.mcap"


@pytest.mark.real
@pytest.mark.skipif(not LAB5.exists(), reason="real recordings absent: ../shared/data/real "
                    "not found")
def test_a_dipole_injected_into_a_real_recording_is_found_and_changes_nothing_else(tmp_path):
    """A 0.02 A m^2 magnet 8 cm beside a place the real sensor crosses twice (lab_05, first
    60 s): named ``local_source`` where it was put, no other new finding, R within its
    sigmas of the recording's own."""
    base = semireal.read_real(LAB5, max_duration_s=60.0)
    rec, reported, tr = semireal.inject(base, "local_source", 0.02, seed=1)
    assert reported == "local_source"
    c0 = diagnose_file(semireal.write_real(base, tmp_path / "base.mcap"))
    c1 = diagnose_file(semireal.write_real(rec, tmp_path / "src.mcap"))
    e0 = [f.effect for f in c0.diagnosis.findings]
    e1 = [f.effect for f in c1.diagnosis.findings]
    assert semireal.new_findings(e0, e1) == (["local_source"] if "local_source" not in e0
                                             else [])
    src = [f for f in _found(c1, "local_source")
           if np.linalg.norm(np.subtract(f.params["position_m"], tr["position_m"])) < 0.02]
    assert len(src) == 1, [f.params["position_m"] for f in _found(c1, "local_source")]
    assert src[0].params["closest_approach_m"] == pytest.approx(tr["closest_approach_m"],
                                                                abs=0.01)
    d = np.abs(np.subtract(c1.calibration.rotvec_body_mag_deg,
                           c0.calibration.rotvec_body_mag_deg))
    assert np.all(d < 3 * np.hypot(c0.calibration.sigma_rotvec_deg,
                                   c1.calibration.sigma_rotvec_deg))


LAB4 = semireal.REAL_DIR / "lab_04.mcap"


@pytest.mark.real
@pytest.mark.skipif(not LAB4.exists(), reason="real recordings absent: ../shared/data/real "
                    "not found")
def test_the_magnet_in_lab_04s_room_is_located_alike_from_each_half(real_outputs):
    """lab_04's transients (45, 84, 126 s) are the sensor passing an object fixed in the
    room: each half of the recording, analysed on its own, names a ``local_source`` and puts
    it at the same place, within 5 cm (measured: 3.0 cm; near a finite magnet at 7-9 cm the
    point dipole's own error moves the place with the passes each half holds). The whole
    recording's stated sigma covers that: each half has about sqrt(2) times the whole's
    sigma, so their difference has about twice it, and lies within three of those. The whole
    recording's place and sigma are those this code gives (``process`` of the real
    recordings, run once for the suite: tests/real_campaign.py)."""
    import dataclasses

    from pipeline.io.mcap_read import read_recording
    from pipeline.run.runner import ProcessOptions, analyse

    rec = read_recording(LAB4)
    ta, tb = int(rec.mag.t_ns[0]), int(rec.mag.t_ns[-1]) + 1
    mid, pad = (ta + tb) // 2, 1_000_000_000
    places = []
    for a, b in ((ta, mid), (mid, tb)):
        half = dataclasses.replace(
            rec, mag=rec.mag.window(a, b), attitude=rec.attitude.window(a - pad, b + pad),
            position=rec.position.window(a - pad, b + pad))
        ctx = analyse(half, ProcessOptions(write_rerun=False, write_report=False))
        src = _found(ctx, "local_source")
        assert len(src) == 1, [f.effect for f in ctx.diagnosis.findings]
        assert src[0].params["closest_approach_m"] < 0.15
        places.append(np.asarray(src[0].params["position_m"]))
    assert np.linalg.norm(places[0] - places[1]) < 0.05, places
    whole = [f for f in real_outputs.json("lab_04", "diagnosis.json")["findings"]
             if f["effect"] == "local_source"]
    main = max(whole, key=lambda f: np.linalg.norm(f["params"]["moment_Am2"]))
    sigma = np.asarray(main["sigma"]["position_m"])
    assert np.all(np.abs(places[0] - places[1]) < 3 * 2 * sigma), (places, sigma)


def _road_survey(speed_m_s: float, moment_Am2: float, att_type: str, position_type: str,
                 x_m: float) -> Spec:
    """Six 200 m lines 5 m apart at ``speed_m_s``, a 1 nT fluxgate at 200 Hz, attitude and
    positions at 20 Hz, an object 1 m under the line at ``x_m`` (2 m below the sensor)."""
    return Spec("road", seed=5, duration_s=300.0, mag_rate_hz=200.0, att_rate_hz=20.0,
                att_type=att_type, path="survey", position_type=position_type,
                survey_calibration_s=30.0, survey_line_m=200.0, survey_spacing_m=5.0,
                survey_speed_m_s=speed_m_s, mag_noise_nT=1.0, att_noise_deg=0.002,
                effects={} if moment_Am2 == 0 else {"local_source": {
                    "position_m": [x_m, 100.0, -1.0],
                    "moment_Am2": [0.0, 0.3 * moment_Am2, -moment_Am2]}})


@pytest.mark.parametrize(("speed", "moment", "att_type", "position_type", "x_m", "peak_nT"), [
    (5.0, 1.2, "novatel_oem7_msgs/msg/INSPVA", "inspva", 10.0, 31.0),
    (5.0, 4.0, "sensor_msgs/msg/Imu", "navsatfix", 10.0, 102.0),
    (1.2, 2.5, "novatel_oem7_msgs/msg/INSPVA", "inspva", 0.0, 64.0),
])
def test_an_object_under_one_line_is_located_from_a_single_pass(
        tmp_path, speed, moment, att_type, position_type, x_m, peak_nT):
    """An object buried under one survey line, passed once: 30-100 nT over 1 nT noise for
    about a second at vehicle speed (5 m/s), a few seconds at walking speed. Its three
    components along the tracked path locate it; a step or a disturbance in its window fits
    worse, which is what names it (not a count of passes)."""
    spec = _road_survey(speed, moment, att_type, position_type, x_m)
    src_truth = spec.effects["local_source"]
    t = np.arange(0.0, spec.duration_s, 1.0 / spec.mag_rate_hz)
    peak = np.linalg.norm(source_field_nT(spec, t), axis=1)
    # the strength a user meets, checked on the generator itself
    assert peak.max() == pytest.approx(peak_nT, rel=0.05)
    assert np.count_nonzero(peak > 0.1 * peak.max()) / spec.mag_rate_hz < (2.0 if speed > 2
                                                                         else 8.0)
    tr = truth(spec)["effects"]["local_source"]
    ctx = diagnose_file(write(spec, tmp_path / "road.mcap"))
    assert [f.effect for f in ctx.diagnosis.findings] == ["local_source"]
    p = ctx.diagnosis.findings[0].params
    assert np.linalg.norm(np.subtract(p["position_m"], tr["position_m"])) < 0.5
    assert p["closest_approach_m"] == pytest.approx(tr["closest_approach_m"], abs=0.2)
    assert np.linalg.norm(np.subtract(p["moment_Am2"], src_truth["moment_Am2"])) < (
        0.2 * np.linalg.norm(src_truth["moment_Am2"]))
    assert np.all(_rot_err_deg(ctx, spec) < 0.05)


def test_a_road_survey_without_an_object_names_nothing(tmp_path):
    """The same survey at vehicle speed with nothing buried: no finding."""
    spec = _road_survey(5.0, 0.0, "novatel_oem7_msgs/msg/INSPVA", "inspva", 10.0)
    ctx = diagnose_file(write(spec, tmp_path / "null.mcap"))
    assert [f.effect for f in ctx.diagnosis.findings] == []


def test_an_object_passed_for_a_second_in_a_two_hour_survey_is_located(tmp_path):
    """Two hours at 5 m/s (180 lines of 200 m, a 1 nT sensor at 50 Hz): the diagnosis fits a
    sample of every 30th reading, which keeps one or two of the 64 nT pass over an object
    1 m under one line. The pass is found in every sample and kept at full rate; the
    object is located, and nothing else is named in the two hours."""
    spec = Spec("long", seed=5, duration_s=7200.0, mag_rate_hz=50.0, att_rate_hz=20.0,
                att_type="novatel_oem7_msgs/msg/INSPVA", path="survey", position_type="inspva",
                survey_calibration_s=30.0, survey_line_m=200.0, survey_spacing_m=5.0,
                survey_speed_m_s=5.0, mag_noise_nT=1.0, att_noise_deg=0.002,
                effects={"local_source": {"position_m": [450.0, 100.0, -1.0],
                                          "moment_Am2": [0.0, 0.75, -2.5]}})
    tr = truth(spec)["effects"]["local_source"]
    ctx = diagnose_file(write(spec, tmp_path / "long.mcap"))
    fs = ctx.calibration.checks["fit_samples"]
    assert fs["stride"] >= 20  # decimated: the pass would hold one or two samples
    assert [f.effect for f in ctx.diagnosis.findings] == ["local_source"]
    p = ctx.diagnosis.findings[0].params
    assert np.linalg.norm(np.subtract(p["position_m"], tr["position_m"])) < 0.5
    assert p["closest_approach_s"] == pytest.approx(tr["closest_approach_s"], abs=1.0)
    assert np.all(_rot_err_deg(ctx, spec) < 0.05)
