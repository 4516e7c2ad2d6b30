"""Segment stage: known answers from attitude built with geometry helpers and from the simulator."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipeline.core.geometry import quat_conj, quat_mul, quat_rotate, rotvec_to_quat
from pipeline.core.recording import AlignedSeries, Segment, SegmentKind
from pipeline.core.stage import Pipeline
from pipeline.model.tang import axis_angle_quat
from stages.context import Context
from stages.segment import (
    MotionContext,
    SegmentMotion,
    absorb_short_runs,
    folds,
    segment_table,
    segment_windows,
)

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
SCEN = Path(__file__).resolve().parents[1] / "pipeline" / "scenarios"
DEMO = Path(__file__).resolve().parents[1] / "pipeline" / "demo"
T0 = 1_700_000_000_000_000_000
FS = 100.0
AX2 = np.array([1.0, 0.2, 0.3]) / np.linalg.norm([1.0, 0.2, 0.3])


def _ramp(t, a, b):
    return np.clip((t - a) / (b - a), 0.0, 1.0)


def _built(noise_deg: float = 0.0, seed: int = 0) -> AlignedSeries:
    """0-5 static, 5-25 400 deg about z(ENU), 25-30 static, 30-40 tumbling, 40-45 static,
    45-60 270 deg about AX2 (body), 60-65 static; optional white attitude noise."""
    t = np.arange(0.0, 65.0, 1.0 / FS)
    qz = axis_angle_quat([0.0, 0.0, 1.0], _ramp(t, 5, 25) * np.radians(400.0))
    tt = np.clip(t - 30.0, 0.0, 10.0)
    rv = np.stack(
        [0.8 * np.sin(1.3 * tt), 0.9 * np.sin(0.7 * tt), 0.7 * np.cos(1.1 * tt) - 0.7], -1
    )
    q2 = axis_angle_quat(AX2, _ramp(t, 45, 60) * np.radians(270.0))
    q = quat_mul(quat_mul(qz, rotvec_to_quat(rv)), q2)
    if noise_deg > 0:
        rng = np.random.default_rng(seed)
        q = quat_mul(rotvec_to_quat(np.radians(noise_deg) * rng.standard_normal((t.size, 3))), q)
    B = np.array([0.0, 20000.0, -40000.0])
    mag = quat_rotate(quat_conj(q), np.broadcast_to(B, (t.size, 3)))
    return AlignedSeries(T0 + np.round(t * 1e9).astype(np.int64), mag, q)


def _s(seg: Segment) -> tuple[float, float]:
    return (seg.start_ns - T0) * 1e-9, (seg.end_ns - T0) * 1e-9


def test_built_sequence_windows_axes_and_twist():
    al = _built()
    segs = SegmentMotion().segment(al)
    kinds = [s.kind for s in segs]
    assert kinds == [
        SegmentKind.STATIC, SegmentKind.ROTATION, SegmentKind.STATIC, SegmentKind.MANOEUVRE,
        SegmentKind.STATIC, SegmentKind.ROTATION, SegmentKind.STATIC,
    ]
    rot1, rot2 = segs[1], segs[5]
    # windows within the smoothing half-width (0.25 s) of the simulated ones
    np.testing.assert_allclose(_s(rot1), (5.0, 25.0), atol=0.3)
    np.testing.assert_allclose(_s(rot2), (45.0, 60.0), atol=0.3)
    np.testing.assert_allclose(_s(segs[3]), (30.0, 40.0), atol=0.3)
    assert rot1.twist_deg == pytest.approx(400.0, abs=1.0)
    assert rot2.twist_deg == pytest.approx(270.0, abs=1.0)
    np.testing.assert_allclose(rot1.axis_enu, [0, 0, 1], atol=1e-6)
    np.testing.assert_allclose(rot2.axis_body, AX2, atol=1e-6)
    assert rot1.swing_rms_deg < 0.01 and rot2.swing_rms_deg < 0.01
    assert segs[3].swing_rms_deg > 10.0  # the tumble is no single-axis rotation
    assert segs[3].coverage > rot1.coverage > segs[0].coverage
    # half-open windows in time order, not overlapping
    for a, b in zip(segs[:-1], segs[1:], strict=True):
        assert a.start_ns < a.end_ns <= b.start_ns
    assert segs[-1].end_ns == al.t_ns[-1] + 1


def test_min_twist_threshold_turns_rotations_into_manoeuvres():
    segs = SegmentMotion(min_twist_deg=300.0).segment(_built())
    rots = [s for s in segs if s.kind is SegmentKind.ROTATION]
    assert len(rots) == 1 and rots[0].twist_deg == pytest.approx(400.0, abs=1.0)
    assert sum(s.kind is SegmentKind.MANOEUVRE for s in segs) == 2


def test_stage_contract_and_pipeline():
    st = SegmentMotion()
    assert st.requires == frozenset({"aligned"}) and st.provides == frozenset({"segments"})
    Pipeline([st], initial=("aligned",))
    ctx = Context(aligned=_built())
    out = st.run(ctx)
    assert out is not ctx and ctx.segments is None
    assert isinstance(out.segments, tuple) and all(isinstance(s, Segment) for s in out.segments)


def test_windows_and_folds():
    segs = SegmentMotion().segment(_built())
    w = segment_windows(segs, [SegmentKind.ROTATION])
    assert len(w) == 2 and all(a < b for a, b in w)
    assert segment_windows(segs) == sorted((s.start_ns, s.end_ns) for s in segs)
    f = folds(segs)
    assert len(f) == 3  # two rotations and the manoeuvre
    for fold in f:
        assert len(fold.test_ns) == 1 and fold.test_ns[0] not in fold.train_ns
        assert len(fold.train_ns) == 2
    assert folds(segs, [SegmentKind.MANOEUVRE]) == []
    t = np.asarray(_built().t_ns)
    m = segs[1].contains(t)
    assert m.sum() > 0 and t[m].min() >= segs[1].start_ns and t[m].max() < segs[1].end_ns


def test_gaps_split_segments():
    al = _built()
    keep = ~((al.t_ns >= T0 + 14_000_000_000) & (al.t_ns < T0 + 15_000_000_000))
    # LAB: a rotation about the vertical stays a rotation (no turns)
    segs = SegmentMotion(min_twist_deg=100.0, context=MotionContext.LAB).segment(al.select(keep))
    rots = [s for s in segs if s.kind is SegmentKind.ROTATION]
    # the first rotation is cut in two by the 1 s hole, neither piece spans it
    assert len(rots) == 3
    for s in rots:
        assert not (s.start_ns < T0 + 14_000_000_000 and s.end_ns > T0 + 15_000_000_000)


# --------------------------------------------------------------------------- simulator


def _aligned_from_scenario(name: str):
    from pipeline.app.simulate import load_scenario, simulate
    from stages.resample import Resample
    from stages.turntable import TurntableAttitude

    sim = simulate(load_scenario(SCEN / f"{name}.toml"), seed=1)
    rec = sim.recording
    if rec.attitude is None:
        rec = TurntableAttitude().apply(rec)
    return sim, Resample().run(Context(recording=rec)).aligned


def test_simulated_turntable_is_one_rotation():
    sim, al = _aligned_from_scenario("turntable_tilt3")
    segs = SegmentMotion().segment(al)
    assert [s.kind for s in segs] == [SegmentKind.ROTATION]
    s = segs[0]
    assert (s.end_ns - s.start_ns) * 1e-9 == pytest.approx(sim.recording.duration_s, abs=0.1)
    np.testing.assert_allclose(s.axis_body, [0, 0, 1], atol=1e-6)
    assert s.twist_deg == pytest.approx(20.0 * 72.0, abs=2.0)  # 20 deg/s for 72 s
    # rate modulated by 30 %: CV = 0.3 / sqrt(2)
    assert s.rate_cv == pytest.approx(0.3 / np.sqrt(2), abs=0.01)


def test_simulated_survey_lines_and_turns():
    _, al = _aligned_from_scenario("survey_lines")
    segs = SegmentMotion().segment(al)  # defaults: no survey switch needed
    kinds = [s.kind for s in segs]
    L, T = SegmentKind.LINE, SegmentKind.TURN
    assert kinds == [L, T, L, T, L]
    t0 = al.t_ns[0]
    # 30 s lines joined by 12 s turns of 180 deg
    starts = [(s.start_ns - t0) * 1e-9 for s in segs]
    np.testing.assert_allclose(starts, [0, 30, 42, 72, 84], atol=1.0)
    for s in segs[1::2]:
        assert s.twist_deg == pytest.approx(180.0, abs=3.0)
        assert abs(s.axis_enu[2]) > 0.99
    # the old survey switch still works and gives the same windows
    sv = SegmentMotion(context=MotionContext.SURVEY).segment(al)
    assert [(s.start_ns, s.end_ns, s.kind) for s in sv] == [
        (s.start_ns, s.end_ns, s.kind) for s in segs
    ]
    # in a lab context there are neither lines nor turns
    lab = SegmentMotion(context=MotionContext.LAB).segment(al)
    assert lab and not any(s.kind in (L, T) for s in lab)


def _demo_aligned(name: str):
    from pipeline.app.simulate import load_scenario, simulate
    from stages.resample import Resample

    sim = simulate(load_scenario(DEMO / f"{name}.toml"), seed=3)
    return sim, Resample().run(Context(recording=sim.recording)).aligned


def test_demo_line_is_two_lines_and_a_turn():
    """The ~90 fragments of 1 s from the attitude wobble are gone (issue 4 follow-up)."""
    sim, al = _demo_aligned("line_01")
    st = SegmentMotion()
    segs = st.segment(al)
    assert [s.kind for s in segs] == [SegmentKind.LINE, SegmentKind.TURN, SegmentKind.LINE]
    # simulated: lines 0-50 s and 70-120 s, raised-cosine turn of 180 deg 50-70 s
    t0 = al.t_ns[0]
    win = np.array([[(x.start_ns - t0) * 1e-9, (x.end_ns - t0) * 1e-9] for x in segs])
    np.testing.assert_allclose(win[:, 0], [0.0, 50.0, 70.0], atol=1.0)
    np.testing.assert_allclose(win[:2, 1], [50.0, 70.0], atol=1.0)
    assert segs[-1].end_ns == al.t_ns[-1] + 1
    assert segs[1].twist_deg == pytest.approx(180.0, abs=3.0)
    assert abs(segs[1].axis_enu[2]) > 0.99
    for s in segs:
        assert (s.end_ns - s.start_ns) * 1e-9 >= st.min_segment_s


def test_demo_calibration_rotation_is_one_manoeuvre():
    sim, al = _demo_aligned("calibration_rotation")
    segs = SegmentMotion().segment(al)
    assert [s.kind for s in segs] == [SegmentKind.MANOEUVRE]
    assert (segs[0].end_ns - segs[0].start_ns) * 1e-9 == pytest.approx(
        sim.recording.duration_s, abs=0.1
    )


@pytest.mark.parametrize("noise_deg", [0.0, 0.05, 0.5])
def test_static_recording_is_one_static_segment(noise_deg):
    """Still attitude with white noise, up to 0.5 deg per sample at 100 Hz (a smoothed-rate
    noise of ~2.5 deg/s, above the fixed threshold: the noise floor is estimated)."""
    t = np.arange(0.0, 30.0, 1.0 / FS)
    q0 = rotvec_to_quat(np.array([0.1, -0.2, 1.0]))
    rng = np.random.default_rng(5)
    q = quat_mul(rotvec_to_quat(np.radians(noise_deg) * rng.standard_normal((t.size, 3))), q0)
    mag = quat_rotate(quat_conj(q), np.broadcast_to([0.0, 2e4, -4e4], (t.size, 3)))
    al = AlignedSeries(T0 + np.round(t * 1e9).astype(np.int64), mag, q)
    segs = SegmentMotion().segment(al)
    assert [s.kind for s in segs] == [SegmentKind.STATIC]
    assert segs[0].start_ns == al.t_ns[0] and segs[0].end_ns == al.t_ns[-1] + 1


def test_noise_does_not_change_the_built_sequence():
    segs = SegmentMotion().segment(_built(noise_deg=0.05, seed=2))
    assert [s.kind for s in segs] == [
        SegmentKind.STATIC, SegmentKind.ROTATION, SegmentKind.STATIC, SegmentKind.MANOEUVRE,
        SegmentKind.STATIC, SegmentKind.ROTATION, SegmentKind.STATIC,
    ]


def test_absorb_short_runs_shortest_first():
    lab = np.array([1, 1, 1, 2, 1, 1, 2, 2, 2, 2, 0, 1, 0, 2, 2, 2])
    out = absorb_short_runs(lab, np.ones(lab.size), 2.5)
    # the single 2 joins the 1s; the pair of 1s between 2s (2 < 2.5) joins the 2s, the lone 1
    # between gaps is dropped (becomes a gap), gaps stay
    np.testing.assert_array_equal(out, [1, 1, 1, 1, 1, 1, 2, 2, 2, 2, 0, 0, 0, 2, 2, 2])


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    rates=st.lists(st.floats(-60.0, 60.0), min_size=3, max_size=8),
    durs=st.lists(st.floats(0.3, 6.0), min_size=8, max_size=8),
    axes=st.lists(st.integers(0, 2), min_size=8, max_size=8),
    noise=st.floats(0.0, 0.2),
)
def test_property_no_segment_shorter_than_minimum(rates, durs, axes, noise):
    """Random piecewise-constant rotation rates: segments are ordered, disjoint, inside the
    recording and none is shorter than ``min_segment_s`` (whatever flickers)."""
    dt = 1.0 / 50.0
    w = np.concatenate(
        [
            np.outer(np.full(int(d / dt), np.radians(r)), np.eye(3)[a])
            for r, d, a in zip(rates, durs, axes, strict=False)
        ]
    )
    q = [np.array([0.0, 0.0, 0.0, 1.0])]
    inc = rotvec_to_quat(w * dt)
    qs = np.empty((w.shape[0] + 1, 4))
    qs[0] = q[0]
    for i in range(w.shape[0]):  # test data only
        qs[i + 1] = quat_mul(qs[i], inc[i])
    rng = np.random.default_rng(0)
    qs = quat_mul(rotvec_to_quat(np.radians(noise) * rng.standard_normal((qs.shape[0], 3))), qs)
    t = T0 + np.round(np.arange(qs.shape[0]) * dt * 1e9).astype(np.int64)
    mag = quat_rotate(quat_conj(qs), np.broadcast_to([0.0, 2e4, -4e4], (t.size, 3)))
    st_ = SegmentMotion()
    segs = st_.segment(AlignedSeries(t, mag, qs))
    total = (t[-1] - t[0]) * 1e-9
    for s in segs:
        assert (s.end_ns - s.start_ns) * 1e-9 >= min(st_.min_segment_s, total) - 1e-9
        assert t[0] <= s.start_ns < s.end_ns <= t[-1] + 1
    for a, b in zip(segs[:-1], segs[1:], strict=True):
        assert a.end_ns <= b.start_ns


def test_simulated_multiaxis_is_a_manoeuvre():
    sim, al = _aligned_from_scenario("multiaxis")
    segs = SegmentMotion().segment(al)
    man = [s for s in segs if s.kind is SegmentKind.MANOEUVRE]
    assert not any(s.kind is SegmentKind.ROTATION for s in segs)
    covered = sum(s.end_ns - s.start_ns for s in man) * 1e-9
    assert covered > 0.9 * sim.recording.duration_s
    assert max(s.coverage for s in man) > 0.15


# --------------------------------------------------------------------------- real data


@pytest.mark.skipif(not REAL.is_dir(), reason=f"real recordings not present ({REAL})")
def test_real_recordings_get_sensible_segments():
    from pipeline.io.mcap_read import read_recording
    from stages.resample import Resample

    files = sorted(REAL.glob("*.mcap"))
    if not files:
        pytest.skip(f"no .mcap files in {REAL}")
    for p in files:
        rec = read_recording(p)
        al = Resample().run(Context(recording=rec)).aligned
        segs = SegmentMotion().segment(al)
        print(f"\n{p.name}: {len(al)} aligned samples, {rec.duration_s:.0f} s")
        print(segment_table(segs, int(al.t_ns[0])))
        assert segs, p.name
        # the lab sessions start and end at rest and move in between
        assert segs[0].kind is SegmentKind.STATIC and segs[-1].kind is SegmentKind.STATIC
        assert any(s.kind in (SegmentKind.ROTATION, SegmentKind.MANOEUVRE) for s in segs)
        for a, b in zip(segs[:-1], segs[1:], strict=True):
            assert a.start_ns < a.end_ns <= b.start_ns
        for s in segs:
            assert al.t_ns[0] <= s.start_ns and s.end_ns <= al.t_ns[-1] + 1
            assert 0.0 < s.coverage <= 1.0
            assert (s.end_ns - s.start_ns) * 1e-9 >= SegmentMotion().min_segment_s
