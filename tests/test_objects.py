"""Located dipoles the data do not resolve apart are one object (one row of targets.csv).

Known answers for the resolution rule (closer together than the sensor came to either), a
property test that the grouping is a partition that does not depend on the order found, the
merged row's values against the dipoles' own field, and the words every output reads.
"""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.core.vocabulary import EffectKind
from pipeline.model.effects import EFFECTS
from pipeline.model.effects.local_source import objects, same_object
from stages.report_text import kin_sentences
from stages.write_survey import Source, dipole_field_nT, one_row_per_object, target_rows


def _p(x, closest=0.05, frame="attitude_source_local"):
    return {"position_m": list(x), "closest_approach_m": closest, "position_frame": frame}


def test_two_dipoles_closer_than_the_sensor_came_are_one_object():
    a = _p([0.0, 0.0, 0.0], 0.071)
    assert same_object(a, _p([0.04, 0.0, 0.0], 0.051))
    # farther apart than the nearest pass: resolved
    assert not same_object(a, _p([0.06, 0.0, 0.0], 0.051))
    # the resolution is the sharper look of the two
    assert not same_object(_p([0, 0, 0], 0.5), _p([0.3, 0, 0], 0.2))
    # another frame, or no pass known: never merged
    assert not same_object(a, _p([0.01, 0, 0], 0.05, frame="enu"))
    assert not same_object(a, _p([0.01, 0, 0], None))


def test_the_rule_is_the_width_of_a_dipoles_anomaly():
    """A vertical dipole's vertical field along a pass at distance d falls to half its peak
    0.50 d to either side: the width at half maximum is d, the rule's scale."""
    d = 0.3
    x = np.linspace(-3 * d, 3 * d, 60_001)
    p = np.stack([x, np.zeros_like(x), np.full_like(x, d)], axis=1)
    bz = dipole_field_nT(p, np.zeros(3), np.array([0.0, 0.0, 1.0]))[:, 2]
    above = x[bz >= 0.5 * bz.max()]
    assert math.isclose(above.max() - above.min(), d, rel_tol=2e-3)


def test_a_chain_of_close_dipoles_is_one_object_and_a_far_one_its_own():
    ps = [_p([0, 0, 0], 0.1), _p([5, 0, 0], 0.1), _p([0.08, 0, 0], 0.1), _p([0.16, 0, 0], 0.1)]
    assert objects(ps) == [[0, 2, 3], [1]]


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(0.01, 0.5)),
                min_size=1, max_size=7), st.randoms(use_true_random=False))
def test_grouping_is_a_partition_whatever_the_order(pts, rnd):
    ps = [_p([x, y, 0.0], c) for x, y, c in pts]
    groups = objects(ps)
    assert sorted(i for g in groups for i in g) == list(range(len(ps)))
    # every pair the rule links shares a group
    where = {i: k for k, g in enumerate(groups) for i in g}
    for i in range(len(ps)):
        for j in range(len(ps)):
            if same_object(ps[i], ps[j]):
                assert where[i] == where[j]
    order = list(range(len(ps)))
    rnd.shuffle(order)
    again = objects([ps[i] for i in order])
    assert sorted(sorted(order[i] for i in g) for g in again) == sorted(groups)


def _source(x, m, closest, s, dbic):
    return Source(np.asarray(x, float), np.array([0.004, 0.008, 0.001]), np.asarray(m, float),
                  closest, s, dbic, "attitude_source_local")


def test_one_row_per_object_sums_the_moments_and_reads_the_field_of_both():
    big = _source([0.49, -0.58, 1.21], [-0.018, 0.002, 0.050], 0.071, 126.8, -2725.5)
    small = _source([0.47, -0.57, 1.24], [-0.002, 0.008, -0.002], 0.051, 45.6, -125.0)
    far = _source([3.0, 2.0, 0.0], [0.0, 0.0, 1.0], 0.5, 10.0, -3000.0)
    rows = one_row_per_object([big, small, far])
    assert len(rows) == 2
    assert rows[0] is far  # the strongest evidence first
    obj = rows[1]
    np.testing.assert_allclose(obj.moment_Am2, big.moment_Am2 + small.moment_Am2)
    w = np.array([np.linalg.norm(big.moment_Am2), np.linalg.norm(small.moment_Am2)])
    np.testing.assert_allclose(obj.position_m, (w[0] * big.position_m + w[1] * small.position_m)
                               / w.sum())
    # the sigma holds the object's extent: at least the dipoles' weighted spread per axis
    spread = np.sqrt(w[0] * w[1]) / w.sum() * np.abs(big.position_m - small.position_m)
    assert np.all(obj.sigma_m >= spread) and np.all(obj.sigma_m >= 0.5 * big.sigma_m)
    assert obj.closest_approach_m == 0.051 and obj.closest_approach_s == 45.6
    assert obj.delta_bic == -2850.5
    # the row's peak is the field of both dipoles at the closest pass
    t0 = 1_600_000_000 * 10**9
    t = t0 + np.arange(0, 200_000_000_000, 10_000_000)
    path = np.stack([np.linspace(0.0, 1.0, len(t)), np.full(len(t), -0.58), np.full(len(t), 1.3)],
                    axis=1)
    (row,) = target_rows([obj], path, t, t0, None)
    j = int(np.argmin(np.abs(t - (t0 + int(45.6e9)))))
    want = np.linalg.norm(dipole_field_nT(path[j], big.position_m, big.moment_Am2)
                          + dipole_field_nT(path[j], small.position_m, small.moment_Am2))
    assert abs(float(row[17]) - want) <= 0.05 + 1e-6 * want
    assert row[0] == "T1"


def test_the_findings_of_one_object_say_so_in_the_report_and_the_explanation():
    f = [{"effect": "local_source", "params": {**_p([0.49, -0.58, 1.21], 0.071),
                                                "moment_Am2": [0, 0, 0.05]}},
         {"effect": "time_offset", "params": {"time_offset_s": 0.015}},
         {"effect": "local_source", "params": {**_p([0.47, -0.57, 1.24], 0.051),
                                                "moment_Am2": [0, 0.008, 0]}},
         {"effect": "local_source", "params": {**_p([2.0, 0.0, 1.0], 0.3),
                                                "moment_Am2": [0, 0, 0.1]}}]
    kin = kin_sentences(f)
    assert set(kin) == {0, 2}
    gap = 100 * np.linalg.norm(np.subtract([0.49, -0.58, 1.21], [0.47, -0.57, 1.24]))
    assert "one object" in kin[0] and f"{gap:.1f} cm away" in kin[0] and "(5.1 cm)" in kin[0]
    long = EFFECTS[EffectKind.LOCAL_SOURCE].beside_kin([f[i]["params"] for i in (0, 2, 3)])
    assert long[0].startswith(". With the local_source at") and "listed once" in long[0]
    assert long[2] == ""
    # effects with nothing to say about their kin say nothing
    assert EFFECTS[EffectKind.TIME_OFFSET].beside_kin([{}, {}]) == ["", ""]
