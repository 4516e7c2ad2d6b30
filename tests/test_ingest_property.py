"""Issue 9, item 4: ingest round trips for arbitrary valid messages (hypothesis).

Arbitrary stamps, field values, attitudes, message types, frame ids and log delays go through
the real writer and the real reader; the arrays that come back are the ones written.
"""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipeline.core.geometry import quat_normalize
from pipeline.io.mcap_read import read_recording
from pipeline.io.mcap_write import write_recording

MAG_TYPES = ["sensor_msgs/msg/MagneticField", "magalign.Magnetometer"]
ATT_TYPES = [
    "sensor_msgs/msg/Imu",
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/QuaternionStamped",
    "novatel_oem7_msgs/msg/INSPVA",
    "magalign.AttitudeQuaternion",
    "magalign.AttitudeEuler",
]


@st.composite
def recordings(draw):
    n = draw(st.integers(12, 80))
    m = draw(st.integers(3, 60))
    t0 = draw(st.integers(0, 2_000_000_000)) * 1_000_000_000
    dt_mag = draw(st.integers(1_000_000, 50_000_000))
    dt_att = draw(st.integers(1_000_000, 50_000_000))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    # Earth-like magnitudes so the reader's unit check passes; arbitrary directions.
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    mag_nT = direction * rng.uniform(20_000, 70_000, size=(n, 1))
    q = quat_normalize(rng.normal(size=(m, 4)))
    return dict(
        mag_t_ns=t0 + np.arange(n, dtype=np.int64) * dt_mag,
        mag_nT=mag_nT,
        attitude_t_ns=t0 + 3_000 + np.arange(m, dtype=np.int64) * dt_att,
        q_enu_body=q,
        mag_type=draw(st.sampled_from(MAG_TYPES)),
        attitude_type=draw(st.sampled_from(ATT_TYPES)),
        mag_frame_id=draw(st.text("abcxyz_/0123456789", min_size=0, max_size=12)),
        mag_log_delay_ns=draw(st.integers(0, 5_000_000)),
        attitude_log_delay_ns=draw(st.integers(0, 5_000_000)),
    )


@settings(max_examples=25, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(rec=recordings())
def test_any_valid_recording_round_trips(tmp_path_factory, rec):
    path = tmp_path_factory.mktemp("prop") / "r.mcap"
    write_recording(path, **rec)
    got = read_recording(path)
    np.testing.assert_array_equal(got.mag.t_ns, rec["mag_t_ns"])
    # tesla on the wire: nT -> T -> nT is exact to a few ulp.
    np.testing.assert_allclose(got.mag.values, rec["mag_nT"], rtol=1e-13, atol=1e-9)
    np.testing.assert_array_equal(got.attitude.t_ns, rec["attitude_t_ns"])
    dots = np.abs(np.sum(got.attitude.q_enu_body * rec["q_enu_body"], axis=1))
    # Euler-angle types (INSPVA, Li 2020) pass through degrees: agree to ~1e-12 rad.
    np.testing.assert_allclose(dots, 1.0, atol=1e-11)
    assert got.mag_frame_id == rec["mag_frame_id"]
