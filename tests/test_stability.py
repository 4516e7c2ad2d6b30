"""Stability under injections: an injected effect changes only its finding.

CI-sized part of ``bench/stability.py``: a few of its bases (``semireal.STABILITY_BASES``,
60 s each, diagnosed once per module) and injections (``semireal.STABILITY_CASES``). Each
injection must (``semireal.compare``): be found with its parameter within 3 sigma or 10 %;
add and lose no other finding; leave the other findings' parameters and R within their
combined sigma. Cases that fail today are marked ``xfail(strict=True)`` with the measured
cause, so that a fix turns them into failures to unmark.
"""

from __future__ import annotations

import numpy as np
import pytest
from indep_gen import Spec
from semireal import (
    REAL_DIR,
    STABILITY_CASES,
    check_injection,
    compare,
    excerpt,
    from_indep,
    inject,
    motion,
    read_real_cached,
    stability_base,
    summary,
    translating_segments,
    write_real,
)

from pipeline.app.commands.diagnose import diagnose_file

HAVE_REAL = (REAL_DIR / "lab_01.mcap").exists()
REAL = [pytest.mark.real,
        pytest.mark.skipif(not HAVE_REAL,
                           reason="real recordings absent: ../shared/data/real not found")]
CASE = {c[0]: c for group in STABILITY_CASES.values() for c in group}


@pytest.fixture(scope="module")
def bases(tmp_path_factory):
    """Base name -> (recording, written path, diagnosis summary); each diagnosed once."""
    cache: dict = {}
    root = tmp_path_factory.mktemp("stability")

    def get(name):
        if name not in cache:
            rec, _ = stability_base(name)
            path = write_real(rec, root / f"{name}.mcap")
            cache[name] = (rec, path, summary(diagnose_file(path)))
        return cache[name]
    return get


def _xfail(reason: str):
    return pytest.mark.xfail(strict=True, reason=reason)


#: (base, injection label); the lab bases need the real recordings. The causes named in the
#: xfail reasons were measured with bench/stability.py (docs/testing.md, "Stability").
CI_CASES = [
    pytest.param("indep_rot", "offset3000#1"),
    pytest.param("indep_tr", "step2000x5s"),
    pytest.param("indep_tr", "lag+25ms"),
    pytest.param("lab_03_rot", "lag+25ms", marks=REAL),
    pytest.param("lab_03_rot", "offset3000#0", marks=[*REAL, _xfail(
        "field_gradient moves 6 combined sigma with the same terms in the model: the "
        "gradient's bearing is held from the round that named it, 45.5 deg on the base "
        "(798.61 nT RMS) and 346.7 deg with the offset named first; at 350 deg the base fits "
        "to 797.36 nT")]),

]


@pytest.mark.parametrize(("base", "label"), CI_CASES)
def test_injection_changes_only_its_finding(bases, tmp_path, base, label):
    rec, base_path, before = bases(base)
    _, case, size, seed, win = CASE[label]
    inj, rep, truth = inject(rec, case, size, seed=seed, window_s=win or 10.0)
    path = write_real(inj, tmp_path / f"{label}.mcap")
    check_injection(base_path, path, rep, truth)
    c = compare(before, summary(diagnose_file(path)), rep, truth)
    assert c["extra"] == [], f"findings added: {c['extra']}"
    assert c["lost"] == [], f"findings lost: {c['lost']}"
    assert c["found"], f"{rep} not found right: {c['own']} ({c['param_err_x_tol']:.2f} x tol)"
    moved = {k: v for k, v in c["shifts"].items() if v > 1.0}
    assert not moved, f"parameters moved (combined sigmas): {moved}"
    assert c["r_shift"] <= 1.0, f"R moved {c['r_shift']:.2f} combined sigma"


@pytest.mark.real
@pytest.mark.skipif(not HAVE_REAL, reason="real recordings absent: ../shared/data/real not found")
@pytest.mark.parametrize("base", ["lab_01_tr", "lab_01_tr2"])
def test_a_long_magnet_on_a_translating_base_is_one_step(bases, tmp_path, base):
    """3000 nT for 7 s on the translating lab bases: one step, nothing added, nothing lost.

    On lab_01_tr the search once stopped at its sixth term with the magnet in three pieces, a
    drift and no map; with room for the map, the backward step and the merge leave one step.
    On lab_01_tr2 a drift named first kept its margin beside the step by trading with its
    offset; held against the step fitted without it, it no longer does. lab_01_tr's field
    gradient still moves about 6 combined sigma (docs/testing.md), not asserted here.
    """
    rec, base_path, before = bases(base)
    _, case, size, seed, win = CASE["step3000x7s"]
    inj, rep, truth = inject(rec, case, size, seed=seed, window_s=win)
    path = write_real(inj, tmp_path / "step.mcap")
    check_injection(base_path, path, rep, truth)
    c = compare(before, summary(diagnose_file(path)), rep, truth)
    assert c["extra"] == [] and c["lost"] == [], (c["extra"], c["lost"])
    assert c["found"], f"{rep} not found right: {c['own']} ({c['param_err_x_tol']:.2f} x tol)"


@pytest.fixture(scope="module")
def offset_on_translating_base(bases, tmp_path_factory):
    """``compare`` of lab_01_tr with 3000 nT of offset injected, diagnosed once."""
    rec, base_path, before = bases("lab_01_tr")
    _, case, size, seed, win = CASE["offset3000#0"]
    inj, rep, truth = inject(rec, case, size, seed=seed, window_s=win or 10.0)
    path = write_real(inj, tmp_path_factory.mktemp("offset") / "offset.mcap")
    check_injection(base_path, path, rep, truth)
    return compare(before, summary(diagnose_file(path)), rep, truth)


@REAL[0]
@REAL[1]
def test_an_undetermined_offset_on_a_translating_base_adds_nothing(offset_on_translating_base):
    """3000 nT of offset on lab_01_tr, whose 6 deg RMS of rotation cannot determine it.

    The offset is declared not identifiable, no finding comes or goes, and R stays within
    its combined sigma. The map's complexity may flip with the injection: a transient the
    finer map explains as well stays the field (nested.explained_by_refinement).
    """
    c = offset_on_translating_base
    assert c["extra"] == [] and c["lost"] == [], (c["extra"], c["lost"])
    assert c["not_identifiable"], "the offset should be declared not identifiable"
    assert c["r_shift"] <= 1.0, f"R moved {c['r_shift']:.2f} combined sigma"


@REAL[0]
@REAL[1]
@_xfail(
    "field_gradient moves 3.5 combined sigma: the field map's complexity flips from 4 modes "
    "(48 functions) to 3 (27) on a held-out near-tie (786.61 against 788.27 nT on the base, "
    "795.95 against 795.68 with the offset), and the gradient, which trades with the map's "
    "first-order content, follows its prior's length scale (docs/testing.md, the stability "
    "corpus after the covariance was scaled)")
def test_an_undetermined_offset_on_a_translating_base_moves_no_other_parameter(
        offset_on_translating_base):
    """The same injection: every other finding's parameters stay within combined sigma."""
    c = offset_on_translating_base
    moved = {k: v for k, v in c["shifts"].items() if v > 1.0}
    assert not moved, f"parameters moved (combined sigmas): {moved}"


@pytest.mark.parametrize("label", ["lag-25ms", "offset3000#1", "step1000x3s"])
def test_injection_is_exact_in_the_files(tmp_path, label):
    """The written recordings differ by the injection only, to the nanosecond and the nT."""
    rec = from_indep(Spec(name="b", seed=3, duration_s=20.0, path="translate"))
    base = write_real(rec, tmp_path / "base.mcap")
    _, case, size, seed, win = CASE[label]
    inj, rep, truth = inject(rec, case, size, seed=seed, window_s=win or 10.0)
    assert check_injection(base, write_real(inj, tmp_path / "inj.mcap"), rep, truth) <= 1e-6
    # and the check sees a difference that is not the injection: the step one sample longer
    if rep == "hard_iron_step":
        (a, b), = truth["windows_s"]
        wrong = {**truth, "windows_s": [[a, b + 0.011]]}
        with pytest.raises(AssertionError):
            check_injection(base, tmp_path / "inj.mcap", rep, wrong)


def test_excerpt_keeps_the_streams():
    r = from_indep(Spec(name="b", seed=4, duration_s=20.0))
    e = excerpt(r, 5.0, 10.0)
    k = (r.t_mag_s >= 5.0) & (r.t_mag_s < 15.0)
    assert np.array_equal(e.mag_nT, r.mag_nT[k])
    assert e.t_mag_s[0] == 0.0 and e.t0_ns == r.t0_ns + int(round(r.t_mag_s[k][0] * 1e9))
    assert e.t_att_s[0] < 0.0 < e.t_att_s[-1] - e.t_mag_s[-1]  # attitude on both sides


@REAL[0]
@REAL[1]
def test_translating_base_is_measured_from_the_poses():
    """lab_01 translates most per radian turned; lab_03's rotating excerpt the least."""
    r1 = read_real_cached("lab_01")
    lab1 = translating_segments(r1, 60.0, 10.0)[0]
    lab3 = translating_segments(read_real_cached("lab_03"), 60.0, 10.0)[-1]
    assert lab1["m_per_rad"] > 5 * lab3["m_per_rad"]
    assert lab1["rot_rms_deg"] < 15.0 < lab3["rot_rms_deg"]
    m = motion(r1, lab1["start_s"], lab1["start_s"] + 60.0)
    assert m["pos_rms_m"] == pytest.approx(lab1["pos_rms_m"])
