"""Segment stage: known answers from attitude built with geometry helpers and from the simulator."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipeline.geometry import quat_conj, quat_mul, quat_rotate, rotvec_to_quat
from pipeline.recording import AlignedSeries, Context, Segment, SegmentKind
from pipeline.stage import Pipeline
from pipeline.tang import axis_angle_quat
from stages.segment import (
    MotionContext,
    SegmentMotion,
    folds,
    segment_table,
    segment_windows,
)

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
SCEN = Path(__file__).resolve().parents[1] / "pipeline" / "scenarios"
T0 = 1_700_000_000_000_000_000
FS = 100.0
AX2 = np.array([1.0, 0.2, 0.3]) / np.linalg.norm([1.0, 0.2, 0.3])


def _ramp(t, a, b):
    return np.clip((t - a) / (b - a), 0.0, 1.0)


def _built() -> AlignedSeries:
    """0-5 static, 5-25 400 deg about z(ENU), 25-28 static, 28-38 tumbling, 38-40 static,
    40-55 270 deg about AX2 (body), 55-60 static."""
    t = np.arange(0.0, 60.0, 1.0 / FS)
    qz = axis_angle_quat([0.0, 0.0, 1.0], _ramp(t, 5, 25) * np.radians(400.0))
    tt = np.clip(t - 28.0, 0.0, 10.0)
    rv = np.stack(
        [0.8 * np.sin(1.3 * tt), 0.9 * np.sin(0.7 * tt), 0.7 * np.cos(1.1 * tt) - 0.7], -1
    )
    q2 = axis_angle_quat(AX2, _ramp(t, 40, 55) * np.radians(270.0))
    q = quat_mul(quat_mul(qz, rotvec_to_quat(rv)), q2)
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
    # windows within the smoothing width (0.25 s) of the simulated ones
    np.testing.assert_allclose(_s(rot1), (5.0, 25.0), atol=0.25)
    np.testing.assert_allclose(_s(rot2), (40.0, 55.0), atol=0.25)
    np.testing.assert_allclose(_s(segs[3]), (28.0, 38.0), atol=0.25)
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
    segs = SegmentMotion(min_twist_deg=100.0).segment(al.select(keep))
    rots = [s for s in segs if s.kind is SegmentKind.ROTATION]
    # the first rotation is cut in two by the 1 s hole, neither piece spans it
    assert len(rots) == 3
    for s in rots:
        assert not (s.start_ns < T0 + 14_000_000_000 and s.end_ns > T0 + 15_000_000_000)


# --------------------------------------------------------------------------- simulator


def _aligned_from_scenario(name: str):
    from pipeline.simulate import load_scenario, simulate
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
    segs = SegmentMotion(context=MotionContext.SURVEY).segment(al)
    kinds = [s.kind for s in segs]
    L, T = SegmentKind.LINE, SegmentKind.TURN
    assert kinds == [L, T, L, T, L]
    t0 = al.t_ns[0]
    # 30 s lines joined by 12 s turns of 180 deg
    starts = [(s.start_ns - t0) * 1e-9 for s in segs]
    np.testing.assert_allclose(starts, [0, 30, 42, 72, 84], atol=0.8)
    for s in segs[1::2]:
        assert s.twist_deg == pytest.approx(180.0, abs=2.0)
        assert abs(s.axis_enu[2]) > 0.99
    # in a lab context the same turns are rotations only if they reach 180 deg
    lab = SegmentMotion(min_twist_deg=170.0).segment(al)
    assert sum(s.kind is SegmentKind.ROTATION for s in lab) == 2


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
    from pipeline.mcap_read import read_recording
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
