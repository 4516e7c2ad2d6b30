"""Diagnosis of the real lab recordings (MEMS magnetometer + motion capture, indoors).

What the physics of each recording demands is required, not whatever was found: the lag
between the two streams on every recording, the room's field gradient where the marker moves
through it, the magnet on lab_02 and the object lab_04 passes. Each parameter is held to a
second method computed here from the raw messages without the diagnosis' model, its
interpolator or its optimiser (scipy's ``Slerp``, least squares, counting), or to physics.
The same second methods are the outside checks of ``tests/golden/real/PROVENANCE.md``.

Decimated for runtime (3,000 samples, four findings). Run with ``-s`` to see the tables.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pytest

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
NAMES = ["lab_01", "lab_02", "lab_03", "lab_04", "lab_05"]

pytestmark = pytest.mark.real

#: What each recording must show. Every recording: the magnetometer's stamps lag the
#: attitude's by about 15 ms (both streams on one clock, the sensor's conversion and
#: transport delay), which at the hand's 1-5 rad/s on a 44,000 nT field is 600-3,000 nT,
#: above the 660 nT noise. The marker moves 0.2-1.6 m through the room's 1-7 uT/m gradient
#: (hundreds to thousands of nT) on lab_01 and lab_03-05; on lab_02 the 58,000 nT magnet
#: on the platform comes first. lab_04 passes within centimetres of a magnetised object.
REQUIRED = {
    "lab_01": {"time_offset", "field_gradient"},
    "lab_02": {"time_offset", "hard_iron_step"},
    "lab_03": {"time_offset", "field_gradient"},
    "lab_04": {"time_offset", "field_gradient", "local_source"},
    "lab_05": {"time_offset", "field_gradient"},
}


def _path(name: str) -> Path:
    p = REAL / f"{name}.mcap"
    if not p.exists():
        pytest.skip(f"real recordings absent: ../shared/data/real/{name}.mcap not found")
    return p


@functools.cache
def _recording(name: str):
    from pipeline.io.mcap_read import read_recording

    return read_recording(_path(name))


@functools.cache
def _diagnosis(name: str):
    from stages.context import Context
    from stages.diagnose.result import DiagnoseConfig
    from stages.diagnose.stage import Diagnose
    from stages.resample import Resample

    path = _path(name)
    ctx = Resample().run(Context(source=str(path), recording=_recording(name)))
    cfg = DiagnoseConfig(max_samples=3000, max_findings=4)
    diag = Diagnose(config=cfg).run(ctx.replace(calibration=None)).diagnosis
    print(f"\n{path.name}\n{diag.table()}")
    return diag


def _finding(diag, effect: str):
    found = [f for f in diag.findings if f.effect == effect]
    assert found, f"{effect} not found: {[f.effect for f in diag.findings]}"
    return found[0]


# ----------------------------------------------------------------- second methods (no model)

def _raw(name: str):
    """Seconds from the first magnetometer message, readings (nT), attitude stamps and q."""
    rec = _recording(name)
    t0 = rec.mag.t_ns[0]
    return ((rec.mag.t_ns - t0) * 1e-9, np.array(rec.mag.values, float),
            (rec.attitude.t_ns - t0) * 1e-9, np.array(rec.attitude.q_enu_body, float))


def _distinct(y: np.ndarray) -> np.ndarray:
    """The first message of each run of identical readings (the sensor's own conversions)."""
    return np.r_[True, np.any(np.diff(y, axis=0) != 0, axis=1)]


def lag_by_grid(t: np.ndarray, y: np.ndarray, t_att: np.ndarray, q: np.ndarray) -> float:
    """Time offset (s) by a grid search, without the diagnosis' model.

    A constant ENU field (the mean of the readings turned into ENU, R = I) is turned into
    the body frame by the attitude at ``t - tau`` (scipy's SLERP); the time derivatives of
    that prediction and of the readings are compared, so offsets and slow drifts drop out and
    one gain absorbs scale errors. The misalignment (about 1 deg) barely changes the lag.
    The 2 ms grid is refined by a parabola through the best three points.
    """
    from scipy.spatial.transform import Rotation, Slerp

    slerp = Slerp(t_att, Rotation.from_quat(q))
    i = np.clip(np.searchsorted(t_att, t) - 1, 0, len(t_att) - 2)
    keep = (t > t_att[0] + 0.2) & (t < t_att[-1] - 0.2) & (np.diff(t_att)[i] < 0.02)
    t, y = t[keep], y[keep]
    B = np.mean(slerp(t).apply(y), axis=0)
    dy = np.gradient(y, t, axis=0)
    taus = np.arange(-0.040, 0.0401, 0.002)
    cost = []
    for tau in taus:
        dp = np.gradient(slerp(t - tau).inv().apply(B), t, axis=0)
        g = np.sum(dy * dp) / np.sum(dp * dp)
        cost.append(np.mean((dy - g * dp) ** 2))
    k = int(np.argmin(cost))
    assert 0 < k < len(taus) - 1, "lag at the edge of the grid"
    c0, c1, c2 = cost[k - 1: k + 2]
    return float(taus[k] + 0.001 * (c0 - c2) / (c0 - 2 * c1 + c2))


@functools.cache
def _lag_model_free(name: str) -> tuple[float, float]:
    """The grid lag over the whole recording and the spread of its two halves (s)."""
    t, y, ta, q = _raw(name)
    d = _distinct(y)
    whole = lag_by_grid(t[d], y[d], ta, q)
    h = np.arange(len(t)) < len(t) // 2
    a = lag_by_grid(t[d & h], y[d & h], ta, q)
    b = lag_by_grid(t[d & ~h], y[d & ~h], ta, q)
    return whole, abs(a - b)


def _running_median(x: np.ndarray, n: int) -> np.ndarray:
    from scipy.ndimage import median_filter

    return median_filter(x, n, mode="nearest")


# ----------------------------------------------------------------------------- the tests

@pytest.mark.parametrize("name", NAMES)
def test_real_recording_has_what_its_physics_demands(name):
    diag = _diagnosis(name)
    found = {f.effect for f in diag.findings}
    assert REQUIRED[name] <= found, (name, [f.effect for f in diag.findings])
    for f in diag.findings:
        ev = f.evidence
        assert ev["heldout_rms_after_nT"] < ev["heldout_rms_before_nT"], f.effect
        assert ev["delta_bic"] < 0, f.effect
    # what is left is the sensor's noise (630-665 nT in still windows) and what the model
    # lacks. The required effects are each several times the noise (the gradient across the
    # marker's path, the 15 ms lag at the hand's turn rates, the 58 uT magnet), so with them
    # modelled the held-out error falls by at least a tenth and stays within 3 times the
    # noise (lab_02, whose magnet is also moved about, is the worst at 2.6)
    final, base = diag.final["heldout_rms_nT"], diag.baseline["heldout_rms_nT"]
    assert final < 0.9 * base, (final, base)
    assert final < 3.0 * 665.0, final


@pytest.mark.parametrize("name", ["lab_01", "lab_03", "lab_04", "lab_05"])
def test_real_time_offset_agrees_with_a_lag_found_without_the_model(name):
    """The diagnosis' tau against the grid search on the raw messages. Tolerance: 3 of the
    combined uncertainty (the diagnosis' sigma, half the spread of the grid's halves), never
    below 1 ms: the conversions are stamped with about 1.4 ms RMS of jitter, which the two
    methods weigh differently (the grid uses each run's first message)."""
    tau = float(_finding(_diagnosis(name), "time_offset").params["time_offset_s"])
    sig = float(_finding(_diagnosis(name), "time_offset").sigma["time_offset_s"])
    ref, spread = _lag_model_free(name)
    tol = max(3.0 * np.hypot(sig, spread / 2), 0.001)
    assert abs(tau - ref) < tol, (tau, ref, spread, sig)
    assert 0.005 < ref < 0.030, ref  # the grid itself finds a lag of the expected size


def test_real_lab_02_time_offset_is_the_sensors():
    """On lab_02 the magnet fills most of the motion, so no model-free lag is clean there:
    the lag of the same sensor on the same clock, the median of the other four recordings'
    grid lags, is the reference (3 of the diagnosis' sigmas, plus the 1 ms of jitter)."""
    if not all((REAL / f"{n}.mcap").exists() for n in NAMES):
        pytest.skip("real recordings absent: ../shared/data/real not complete")
    f = _finding(_diagnosis("lab_02"), "time_offset")
    ref = float(np.median([_lag_model_free(n)[0] for n in NAMES if n != "lab_02"]))
    tol = 3.0 * float(f.sigma["time_offset_s"]) + 0.001
    assert abs(float(f.params["time_offset_s"]) - ref) < tol, (f.params, f.sigma, ref)


@pytest.mark.parametrize("name", ["lab_01", "lab_03", "lab_04", "lab_05"])
def test_real_gradient_agrees_with_the_magnitude_regression(name):
    """The field magnitude does not depend on the attitude, so regressing the raw magnitude
    on the marker's position measures the gradient of |B|, ``G^T b`` (b the field's
    direction), without the model. Hard iron and timing errors are noise to it, so only the
    vertical component, the largest (1-6 uT/m), is compared: same sign, within a factor of
    two. A sign error, a doubled or a dropped gradient fails."""
    from scipy.spatial.transform import Rotation

    rec = _recording(name)
    t, y, ta, q = _raw(name)
    pos = rec.position
    assert pos is not None and pos.frame.value == "attitude_source_local"
    ok = np.all(np.isfinite(pos.p_m), axis=1)
    tp = (pos.t_ns[ok] - rec.mag.t_ns[0]) * 1e-9
    p = np.stack([np.interp(t, tp, pos.p_m[ok, i]) for i in range(3)], axis=1)
    m = np.linalg.norm(y, axis=1)
    A = np.c_[np.ones(len(m)), p - p.mean(axis=0)]
    grad_free = np.linalg.lstsq(A, m, rcond=None)[0][1:]
    # the field's direction in the room frame: readings turned by the attitude (R = I)
    i = np.clip(np.searchsorted(ta, t), 0, len(ta) - 1)
    b = np.mean(Rotation.from_quat(q[i]).apply(y), axis=0)
    b /= np.linalg.norm(b)
    G = np.asarray(_finding(_diagnosis(name), "field_gradient").params["G_nT_per_m"])
    grad_diag = G.T @ b
    ratio = grad_diag[2] / grad_free[2]
    assert abs(grad_free[2]) > 1000.0, grad_free  # nT/m: the room's gradient is there
    assert 0.5 < ratio < 2.0, (grad_diag, grad_free)


def test_real_lab_02_magnet_window_within_a_second():
    """The magnet put on the platform at about 38 s and taken away at about 95 s: the raw
    magnitude's one-second running median departs from its value at rest by more than
    10 uT between those moments (the magnet adds about 58 uT in the sensor frame). The
    diagnosis' steps must cover that span to within a second at each end, and the largest
    step must be a magnet's size (20-100 uT)."""
    t, y, _, _ = _raw("lab_02")
    m = _running_median(np.linalg.norm(y, axis=1), 285)
    rest = np.median(m[t < 30.0])  # the first half-minute lies still, no magnet
    away = np.flatnonzero(np.abs(m - rest) > 10_000.0)
    on, off = t[away[0]], t[away[-1]]
    steps = [f for f in _diagnosis("lab_02").findings if f.effect == "hard_iron_step"]
    assert steps
    edges = np.array([w for f in steps for w in f.params["windows_s"]])
    assert abs(edges[:, 0].min() - on) < 1.0, (edges, on)
    assert abs(edges[:, 1].max() - off) < 1.0, (edges, off)
    big = max(steps, key=lambda f: np.linalg.norm(f.params["offset_nT"]))
    (a, b), = big.params["windows_s"]
    assert abs(a - on) < 1.0 and abs(b - off) < 1.0, (big.params["windows_s"], on, off)
    assert 20_000.0 < np.linalg.norm(big.params["offset_nT"]) < 100_000.0


def test_real_lab_04_source_passed_closest_at_the_largest_transient():
    """A fixed object's field is seen as a transient in the raw magnitude when the sensor
    passes it (at 45, 84 and 127 s, up to 14 uT above the running level): the located
    source's closest approach must be the largest of them, within a second, and close
    (a dipole of 0.05 A m^2 gives 14 uT at about 9 cm)."""
    t, y, _, _ = _raw("lab_04")
    m = np.linalg.norm(y, axis=1)
    bump = np.abs(_running_median(m, 29) - _running_median(m, 857))  # 0.1 s against 3 s
    t_peak = t[int(np.argmax(bump))]
    src = _finding(_diagnosis("lab_04"), "local_source").params
    assert abs(src["closest_approach_s"] - t_peak) < 1.0, (src["closest_approach_s"], t_peak)
    assert src["closest_approach_m"] < 0.2, src["closest_approach_m"]


@pytest.mark.parametrize("name", NAMES)
def test_real_recordings_sample_hold_rate_and_repeats(name):
    """The lab magnetometer converts at about 202 Hz into 285.714 Hz messages: counted in
    the raw channel, 29 % of the messages repeat the one before; the detector must agree
    with the count to 0.5 % and give the native rate as the message rate times the
    fraction of distinct messages."""
    from pipeline.model.sample_hold import detect_sample_hold

    rec = _recording(name)
    _, y, _, _ = _raw(name)
    counted = 1.0 - float(np.mean(_distinct(y)))
    assert 0.28 < counted < 0.30, counted
    sh = detect_sample_hold(rec.mag.t_ns, rec.mag.values)
    assert sh is not None, name
    assert abs(sh.repeated_fraction - counted) < 0.005, (sh.repeated_fraction, counted)
    assert abs(sh.message_rate_hz - 285.714) < 0.1, sh.message_rate_hz
    assert abs(sh.native_rate_hz - 285.714 * (1.0 - counted)) < 1.0, sh.native_rate_hz
