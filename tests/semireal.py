"""Semi-real recordings (issue 15 B): effects injected into the real lab recordings.

Each real recording (``../shared/data/real/lab_0*.mcap``: a MEMS magnetometer at 285.7 Hz,
motion-capture ``PoseStamped`` with positions) is read with the ``mcap_ros2`` reader, changed
here and written again with ``tests/indep_gen.write_streams`` (the ``mcap_ros2`` writer); no
magalign model code is used. The base recording is rewritten the same way without an
injection, so that base and injected files differ by the injection only.

How each effect is injected (``y`` the recorded readings in the mag frame, nT; ``C(t)`` the
recorded attitude, SLERP-interpolated at the magnetometer stamps; ``R`` the misalignment and
``B`` the mean field, both from a Wahba fit made here, :func:`wahba`):

- ``time_offset``: the magnetometer stamps are moved by ``+tau`` (CONVENTIONS: the sample
  stamped ``t`` was sensed at ``t - tau``). Exact, whatever the sensor's own errors.
- ``eddy_current``: ``y += E_s dy/dt``, ``dy/dt`` a Savitzky-Golay derivative (cubic, 51 ms)
  of the recorded readings (CONVENTIONS ``eddy_current``).
- ``heading_drift``: the attitude becomes ``Rz(h(t)) C(t)`` with ``h`` linear in time (the
  attitude source's heading error). Exact.
- ``field_drift``, ``disturbance``, ``field_gradient``: an ENU field ``F(t)`` added as
  ``y += R.T C(t).T F(t)`` (the gradient from the recorded positions; none where they are
  lost).
- ``hard_iron``, ``hard_iron_step``: ``y += o`` (inside the window for the step, 10 s unless
  ``window_s`` says otherwise: a clean rectangle in the mag frame). Exact.
- ``soft_iron``: ``y <- D y`` (about the recorded reading, offsets included).
- ``local_source``: a point dipole fixed in the room, ``B = 100 nT (3 (m.u) u - m) / r^3``
  at the recorded positions (the room frame taken as ENU), added as ``y += R.T C(t).T B``; it
  sits 8 cm from a place the sensor passes twice, at least 5 s apart (:func:`revisited`),
  on the side the rest of the path keeps farthest from (:func:`beside`).

A semi-real recording is scored against its base: a finding counts only if the base did not
have that effect (:func:`new_findings`).

Stability (``bench/stability.py``, ``tests/test_stability.py``): bases are excerpts of
the lab recordings (:func:`excerpt`) chosen by how they move (:func:`motion`,
:func:`translating_segments`: measured from the poses) or independent recordings
(:func:`from_indep`); :func:`check_injection` proves each injection by plain arithmetic on
the files written, and :func:`compare` scores an injected diagnosis against its base's
(:func:`summary`): the injected effect found, nothing else added or lost, the other
parameters and R where they were.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from indep_gen import write_streams
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from scipy.signal import savgol_filter
from scipy.spatial.transform import Rotation, Slerp

REAL_DIR = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"


@dataclass
class Real:
    """The streams of one real recording.

    Attributes
    ----------
    t_mag_s : ndarray (N,)
        Magnetometer stamps, s from the first one.
    mag_nT : ndarray (N, 3)
    t_att_s : ndarray (M,)
    att : Rotation (M,)
        ``q_enu_body``.
    pos_m : ndarray (M, 3)
        Positions (NaN where lost).
    t0_ns : int
        Stamp of the first magnetometer sample.

    """

    t_mag_s: np.ndarray
    mag_nT: np.ndarray
    t_att_s: np.ndarray
    att: Rotation
    pos_m: np.ndarray
    t0_ns: int


def read_real(path: Path, max_duration_s: float | None = None) -> Real:
    """Read a lab recording (``/imu/mag`` and ``/mocap/pose``), optionally its first part."""
    tm, ym, ta, qa, pa = [], [], [], [], []
    with open(path, "rb") as fh:
        decoded = list(make_reader(fh, decoder_factories=[DecoderFactory()])
                       .iter_decoded_messages())
    for _, channel, _, msg in decoded:
        t = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        if channel.topic == "/imu/mag":
            v = msg.magnetic_field
            tm.append(t)
            ym.append((v.x * 1e9, v.y * 1e9, v.z * 1e9))
        elif channel.topic == "/mocap/pose":
            o, p = msg.pose.orientation, msg.pose.position
            ta.append(t)
            qa.append((o.x, o.y, o.z, o.w))
            pa.append((p.x, p.y, p.z))
    tm_a, ta_a = np.asarray(tm, dtype=np.int64), np.asarray(ta, dtype=np.int64)
    i, j = np.argsort(tm_a, kind="stable"), np.argsort(ta_a, kind="stable")
    t0 = int(tm_a[i[0]])
    r = Real((tm_a[i] - t0) * 1e-9, np.asarray(ym)[i], (ta_a[j] - t0) * 1e-9,
             Rotation.from_quat(np.asarray(qa)[j]), np.asarray(pa)[j], t0)
    if max_duration_s is not None:
        km, ka = r.t_mag_s < max_duration_s, r.t_att_s < max_duration_s + 0.1
        r = Real(r.t_mag_s[km], r.mag_nT[km], r.t_att_s[ka], r.att[ka], r.pos_m[ka], t0)
    return r


def attitude_at(r: Real, t_s: np.ndarray) -> Rotation:
    """Recorded attitude at ``t_s`` by SLERP (held at the ends)."""
    t = np.clip(t_s, r.t_att_s[0], r.t_att_s[-1])
    return Slerp(r.t_att_s, r.att)(t)


def wahba(r: Real, n_iter: int = 8) -> tuple[Rotation, np.ndarray]:
    """``R_body_mag`` and the mean ENU field by alternating Kabsch and averaging."""
    C = attitude_at(r, r.t_mag_s)
    y = r.mag_nT - np.mean(r.mag_nT, axis=0) * 0.0
    R = Rotation.identity()
    for _ in range(n_iter):
        B = np.mean(C.apply(R.apply(y)), axis=0)
        R, _ = Rotation.align_vectors(C.inv().apply(np.tile(B, (len(y), 1))), y)
    return R, B


#: Effects injected and their three sizes (small, medium, large).
SIZES: dict[str, tuple[Any, ...]] = {
    "time_offset": (0.005, 0.025, 0.06),
    "eddy_current": (0.001, 0.002, 0.004),   # E_s = diag(+e, -e, 0), s
    "eddy_iso": (0.002, 0.005, 0.01),        # E_s = e I: a time offset of -e
    "heading_drift": (0.03, 0.1, 0.3),       # deg over the recording
    "field_drift": (50.0, 150.0, 500.0),     # nT peak to peak along (0.3, 0.5, -0.8)
    "disturbance": (100.0, 300.0, 1000.0),   # nT peak
    "hard_iron_step": (50.0, 150.0, 500.0),  # nT
    "hard_iron": (30.0, 100.0, 300.0),       # nT
    "field_gradient": (300.0, 1000.0, 3000.0),  # nT/m, Frobenius norm
    "soft_iron": (0.005, 0.01, 0.03),        # Frobenius norm of D - I
    "local_source": (0.005, 0.02, 0.08),     # A m^2: ~1, 4, 16 uT at 8 cm
}
#: The name a correct diagnosis reports for each injection.
REPORTED = {"eddy_iso": "time_offset"}


def inject(r: Real, case: str, size: float, seed: int = 0, window_s: float = 10.0
           ) -> tuple[Real, str, dict[str, Any]]:
    """Return the recording with ``case`` injected at ``size``, the name to report, params.

    ``time_offset`` takes a signed lag (s); the others the amplitudes of :data:`SIZES`.
    ``window_s``: how long the ``hard_iron_step`` offset stays switched on.
    """
    rng = np.random.default_rng(seed)
    t, y, dur = r.t_mag_s, r.mag_nT.copy(), float(r.t_mag_s[-1])
    tm, att = t, r.att
    rep = REPORTED.get(case, case)
    if case == "time_offset":
        tm = t + size
        p: dict[str, Any] = {"time_offset_s": float(size)}
    elif case in ("eddy_current", "eddy_iso"):
        dt = float(np.median(np.diff(t)))
        w = max(5, int(round(0.051 / dt)) | 1)
        ydot = savgol_filter(y, w, 3, deriv=1, delta=dt, axis=0)
        E = size * (np.eye(3) if case == "eddy_iso" else np.diag([1.0, -1.0, 0.0]))
        y = y + ydot @ E.T
        p = {"time_offset_s": -float(size)} if case == "eddy_iso" else {"E_s": E.tolist()}
    elif case == "heading_drift":
        h = np.radians(size) * r.t_att_s / dur
        att = Rotation.from_rotvec(np.stack([0 * h, 0 * h, h], -1)) * r.att
        p = {"rate_deg_per_h": size / dur * 3600.0, "peak_to_peak_deg": float(size)}
    elif case in ("field_drift", "disturbance", "field_gradient"):
        R, _ = wahba(r)
        C = attitude_at(r, t)
        if case == "field_drift":
            d = np.array([0.3, 0.5, -0.8])
            F = np.outer(0.5 * size * np.sin(np.pi * (t / dur - 0.5)), d / np.linalg.norm(d))
            p = {"peak_to_peak_nT": (size * np.abs(d / np.linalg.norm(d))).tolist()}
        elif case == "disturbance":
            a = float(rng.uniform(0.3, 0.6) * dur)
            x = np.clip((t - a) / 6.0, 0.0, 1.0)
            F = size * np.sin(np.pi * x)[:, None] ** 2 * np.array([0.6, -0.3, 0.74])
            p = {"windows_s": [[a, a + 6.0]], "peak_nT": float(size)}
        else:
            A = rng.normal(size=(3, 3))
            G = 0.5 * (A + A.T)
            G -= np.trace(G) / 3 * np.eye(3)
            G *= size / np.linalg.norm(G)
            ok = np.all(np.isfinite(r.pos_m), axis=1)
            pos = np.stack([np.interp(t, r.t_att_s[ok], r.pos_m[ok, k]) for k in range(3)], -1)
            F = (pos - pos.mean(axis=0)) @ G.T
            p = {"G_nT_per_m": G.tolist()}
        y = y + R.inv().apply(C.inv().apply(F))
    elif case == "hard_iron":
        o = rng.normal(size=3)
        o *= size / np.linalg.norm(o)
        y = y + o
        p = {"offset_nT": o.tolist()}
    elif case == "hard_iron_step":
        o = rng.normal(size=3)
        o *= size / np.linalg.norm(o)
        a = float(rng.uniform(0.3, 0.6) * dur)
        y = y + ((t >= a) & (t < a + window_s))[:, None] * o
        p = {"windows_s": [[a, a + window_s]], "offset_nT": o.tolist()}
    elif case == "local_source":
        R, _ = wahba(r)
        C = attitude_at(r, t)
        ok = np.all(np.isfinite(r.pos_m), axis=1)
        pos = np.stack([np.interp(t, r.t_att_s[ok], r.pos_m[ok, k]) for k in range(3)], -1)
        c = beside(revisited(t, pos, rng), pos, 0.08)
        u = rng.normal(size=3)
        m = size * u / np.linalg.norm(u)
        d = pos - c
        dist = np.linalg.norm(d, axis=1)
        uu = d / dist[:, None]
        F = 100.0 * (3.0 * (uu @ m)[:, None] * uu - m) / dist[:, None] ** 3
        y = y + R.inv().apply(C.inv().apply(F))
        j = int(np.argmin(dist))
        p = {"position_m": c.tolist(), "moment_Am2": m.tolist(),
             "closest_approach_m": float(dist[j]), "closest_approach_s": float(t[j])}
    elif case == "soft_iron":
        A = rng.normal(size=(3, 3))
        S = 0.5 * (A + A.T)
        S -= np.trace(S) / 3 * np.eye(3)
        D = np.eye(3) + size * S / np.linalg.norm(S)
        y = y @ D.T
        p = {"D": D.tolist()}
    else:
        raise ValueError(case)
    return Real(tm, y, r.t_att_s, att, r.pos_m, r.t0_ns), rep, p


def revisited(t_s: np.ndarray, pos_m: np.ndarray, rng: np.random.Generator,
              gap_s: float = 5.0, away_m: float = 0.3) -> np.ndarray:
    """A place the path passes twice: a pair of close points of two passes, (2, 3).

    The two points are ``gap_s`` apart in time and the path goes more than ``away_m`` from
    the place between them (two passes, not one rest: a source beside a place where the
    sensor rests is a constant field there). Searched over a 0.1 s grid of the path among
    the pairs closer than 5 cm where the path crosses the place (it leaves it by 15 cm
    within a second on both sides), or the closest pair; one is drawn with ``rng``.
    """
    idx = np.arange(0, len(t_s), max(1, int(round(0.1 / float(np.median(np.diff(t_s)))))))
    P, T = pos_m[idx], t_s[idx]
    dd = np.linalg.norm(P[:, None, :] - P[None, :, :], axis=-1)
    far = dd > away_m  # far[i, k]: the path at k is away from the place at i
    cum = np.cumsum(far, axis=1)
    i_, j_ = np.meshgrid(np.arange(len(T)), np.arange(len(T)), indexing="ij")
    left = np.where(j_ > i_, cum[i_, np.maximum(j_ - 1, 0)] - cum[i_, i_], 0)
    dd[(np.abs(T[:, None] - T[None, :]) < gap_s) | (left <= 0)] = np.inf
    cand = np.argwhere(dd < 0.05)

    def transit(k: int) -> bool:  # the path leaves the point within 1 s on both sides
        near = np.abs(T - T[k]) <= 1.0
        before, after = near & (T < T[k]), near & (T > T[k])
        d = np.linalg.norm(P - P[k], axis=1)
        return bool(before.any() and after.any() and d[before].max() > 0.15
                    and d[after].max() > 0.15)

    cand = np.array([c for c in cand if transit(int(c[0])) and transit(int(c[1]))]
                    ).reshape(-1, 2)
    i, j = cand[rng.integers(len(cand))] if len(cand) else np.unravel_index(
        int(np.argmin(dd)), dd.shape)
    return np.stack([P[i], P[j]])


def beside(passes: np.ndarray, pos_m: np.ndarray, dist_m: float) -> np.ndarray:
    """A point ``dist_m`` from the middle of two passes, seen about as close from both.

    Of the 26 directions to a cube's corners, edges and faces, those from which both pass
    points are within 1.3 times the path's closest distance (two approaches of similar
    strength); among them the one the whole path keeps farthest from.
    """
    g = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)
                  if (i, j, k) != (0, 0, 0)], dtype=float)
    cands = passes.mean(axis=0) + dist_m * g / np.linalg.norm(g, axis=1)[:, None]
    ok = pos_m[np.all(np.isfinite(pos_m), axis=1)]
    best, score = cands[0], -np.inf
    for c in cands:
        closest = float(np.min(np.linalg.norm(ok - c, axis=1)))
        both = float(np.max(np.linalg.norm(passes - c, axis=1)))
        s = closest if both <= 1.3 * closest else closest - 10.0  # balanced passes first
        if s > score:
            best, score = c, s
    return best


def write_real(r: Real, path: Path) -> Path:
    """Write the streams (magnetometer, PoseStamped with positions) as an MCAP."""
    return write_streams(path, r.t_mag_s, r.mag_nT, r.t_att_s, r.att,
                         "geometry_msgs/msg/PoseStamped", r.pos_m, att_topic="/mocap/pose")


def new_findings(base: list[str], injected: list[str]) -> list[str]:
    """Findings of the injected recording that its base did not have."""
    return [e for e in injected if e not in set(base)]


def cases(sizes: tuple[int, ...] = (0, 1, 2)) -> list[tuple[str, float]]:
    """Every (case, size) of the corpus: lags +-5, +-25, +-60 ms and the sized effects."""
    out = [("time_offset", s * v) for v in SIZES["time_offset"] for s in (1.0, -1.0)]
    for c, v in SIZES.items():
        if c != "time_offset":
            out += [(c, v[i]) for i in sizes]
    return out


# ----------------------------------------------------------------------------- stability


def excerpt(r: Real, start_s: float, duration_s: float) -> Real:
    """The part ``[start_s, start_s + duration_s)`` of ``r``, times from its first sample.

    The attitude keeps 0.1 s beyond both ends (as :func:`read_real` does at the end), so
    that every magnetometer sample has an attitude on both sides.
    """
    km = (r.t_mag_s >= start_s) & (r.t_mag_s < start_s + duration_s)
    ka = (r.t_att_s >= start_s - 0.1) & (r.t_att_s < start_s + duration_s + 0.1)
    t0 = float(r.t_mag_s[km][0])
    return Real(r.t_mag_s[km] - t0, r.mag_nT[km], r.t_att_s[ka] - t0, r.att[ka],
                r.pos_m[ka], r.t0_ns + int(round(t0 * 1e9)))


def motion(r: Real, start_s: float = 0.0, end_s: float = np.inf) -> dict[str, float]:
    """How much the sensor turns and moves in ``[start_s, end_s)``, from the poses.

    ``rot_rms_deg``: RMS angle of the attitudes from their mean rotation; ``pos_rms_m``: RMS
    distance of the positions from their mean; ``turned_deg`` and ``path_m``: the angle
    turned and the distance travelled, summed over 0.1 s steps (coarser than the pose rate so
    that the motion-capture noise does not add up); ``m_per_rad``: ``pos_rms_m`` per radian
    of ``rot_rms_deg``, large where the sensor mostly translates.
    """
    k = (r.t_att_s >= start_s) & (r.t_att_s < end_s)
    t, att, pos = r.t_att_s[k], r.att[k], r.pos_m[k]
    rot_rms = float(np.sqrt(np.mean(np.sum((att * att.mean().inv()).as_rotvec() ** 2, 1))))
    ok = np.all(np.isfinite(pos), axis=1)
    p = pos[ok]
    pos_rms = float(np.sqrt(np.mean(np.sum((p - p.mean(axis=0)) ** 2, 1)))) if len(p) else 0.0
    step = max(1, int(round(0.1 / float(np.median(np.diff(t))))))
    turned = float(np.sum(np.linalg.norm((att[step::step] * att[:-step:step].inv())
                                         .as_rotvec(), axis=1)))
    path = float(np.nansum(np.linalg.norm(np.diff(pos[::step], axis=0), axis=1)))
    return {"rot_rms_deg": float(np.degrees(rot_rms)), "pos_rms_m": pos_rms,
            "turned_deg": float(np.degrees(turned)), "path_m": path,
            "m_per_rad": pos_rms / max(rot_rms, 1e-6)}


def translating_segments(r: Real, length_s: float = 60.0, step_s: float = 5.0,
                         min_pos_rms_m: float = 0.1) -> list[dict[str, float]]:
    """Segments of ``length_s`` that move at least ``min_pos_rms_m``, most translating first.

    Each is :func:`motion` of the segment with its ``start_s``; sorted by ``m_per_rad``.
    """
    out = []
    for a in np.arange(0.0, float(r.t_mag_s[-1]) - length_s + 1e-9, step_s):
        m = motion(r, float(a), float(a) + length_s)
        if m["pos_rms_m"] >= min_pos_rms_m:
            out.append({"start_s": float(a), **m})
    return sorted(out, key=lambda d: -d["m_per_rad"])


def from_indep(spec: Any) -> Real:
    """The streams of an independent recording (``indep_gen.Spec``) as a :class:`Real`."""
    from indep_gen import T0_NS, readings

    d = readings(spec)
    return Real(d["t_mag_s"], d["mag_nT"], d["t_att_s"], d["att"], d["pos_m"], T0_NS)


def _abs_ns(r: Real, t_s: np.ndarray) -> np.ndarray:
    return r.t0_ns + np.round(np.asarray(t_s) * 1e9).astype(np.int64)


def check_injection(base_path: Path, injected_path: Path, reported: str,
                    params: dict[str, Any]) -> float:
    """Prove by plain arithmetic that the written files differ by the injection only.

    For ``time_offset`` the magnetometer stamps move by the lag (to the nanosecond the files
    carry) and nothing else changes; for ``hard_iron`` every reading moves by the offset;
    for ``hard_iron_step`` the readings inside the window move by the offset and the others
    not at all. Attitude stamps and quaternions never change. Raises ``AssertionError``;
    returns the largest deviation of a reading from its expected value, nT.
    """
    b, j = read_real(base_path), read_real(injected_path)
    tb_m, tj_m = _abs_ns(b, b.t_mag_s), _abs_ns(j, j.t_mag_s)
    assert len(tb_m) == len(tj_m), "sample counts differ"
    assert np.array_equal(_abs_ns(b, b.t_att_s), _abs_ns(j, j.t_att_s)), "attitude stamps"
    assert np.allclose(b.att.as_quat(), j.att.as_quat(), rtol=0, atol=1e-15), "attitude"
    expect = np.zeros_like(b.mag_nT)
    lag_ns = 0
    if reported == "time_offset":
        lag_ns = int(round(params["time_offset_s"] * 1e9))
    elif reported == "hard_iron":
        expect[:] = params["offset_nT"]
    elif reported == "hard_iron_step":
        (a, e), = params["windows_s"]
        t = (tb_m - tb_m[0]) * 1e-9
        expect[(t >= a) & (t < e)] = params["offset_nT"]
    else:
        raise ValueError(reported)
    # the stamps: the lag to the nanosecond (each stamp rounded once when written)
    assert np.max(np.abs(tj_m - tb_m - lag_ns)) <= 1, "magnetometer stamps"
    dev = float(np.max(np.abs(j.mag_nT - b.mag_nT - expect)))
    assert dev <= 1e-6, f"readings differ from the injection by {dev:g} nT"
    return dev


#: The parameter compared for each effect.
PARAM_KEYS = {"hard_iron": "offset_nT", "hard_iron_step": "offset_nT", "soft_iron": "D",
              "time_offset": "time_offset_s", "eddy_current": "E_s",
              "field_drift": "peak_to_peak_nT", "disturbance": "peak_nT",
              "field_gradient": "G_nT_per_m", "heading_drift": "rate_deg_per_h",
              "sample_hold": "native_rate_hz", "local_source": "moment_Am2",
              "lever_arm": "lever_arm_body_m", "axis_tilt": "tilt_deg"}
#: Effects that happen in windows: each window is an item of its own.
WINDOWED = ("hard_iron_step", "disturbance")


def summary(ctx: Any) -> dict[str, Any]:
    """What :func:`compare` needs of a diagnosis (a JSON-able dict): findings and R."""
    cal = ctx.need_calibration()
    return {"findings": [{"effect": f.effect, "params": f.params, "sigma": f.sigma}
                         for f in ctx.diagnosis.findings],
            "not_identifiable": [k for k, _ in ctx.diagnosis.not_identifiable],
            "rotvec_deg": [float(x) for x in cal.rotvec_body_mag_deg],
            "sigma_rotvec_deg": [float(x) for x in cal.sigma_rotvec_deg]}


def _items(s: dict[str, Any]) -> list[dict[str, Any]]:
    """Findings as items: one per window for :data:`WINDOWED` effects, else one each."""
    out = []
    for f in s["findings"]:
        ws = f["params"].get("windows_s") if f["effect"] in WINDOWED else None
        for w in (ws or [None]):
            out.append({**f, "window": w})
    return out


def _overlap(a: list[float] | None, b: list[float] | None) -> float:
    """Length of the overlap of two windows over the shorter one's (0 when either is None)."""
    if a is None or b is None:
        return 0.0
    inter = min(a[1], b[1]) - max(a[0], b[0])
    return max(0.0, inter) / max(min(a[1] - a[0], b[1] - b[0]), 1e-9)


def _arr(x: Any) -> np.ndarray:
    return np.asarray([np.nan if v is None else v for v in np.ravel(np.asarray(x, dtype=object))],
                      dtype=float)


def _shift(f0: dict[str, Any], f1: dict[str, Any]) -> float:
    """Largest change of a finding's parameter in units of the combined sigma (NaN: none)."""
    k = PARAM_KEYS.get(f0["effect"])
    if k is None or k not in f0["params"] or k not in f1["params"]:
        return float("nan")
    d = _arr(f1["params"][k]) - _arr(f0["params"][k])
    s = np.hypot(_arr(f0["sigma"].get(k, np.nan)), _arr(f1["sigma"].get(k, np.nan)))
    if d.shape != s.shape:
        return float("nan")
    return float(np.nanmax(np.abs(d) / np.maximum(s, 1e-300))) if np.any(np.isfinite(s)) \
        else float("nan")


def _label(f: dict[str, Any]) -> str:
    e, p = f["effect"], f["params"]
    k = PARAM_KEYS.get(e)
    v = p.get(k) if k else None
    txt = e
    if f.get("window") is not None:
        txt += f"[{f['window'][0]:.1f}-{f['window'][1]:.1f}s]"
    if v is not None:
        a = _arr(v)
        txt += " " + (f"{a[0]:.4g}" if a.size == 1 else "(" + ", ".join(f"{x:.3g}" for x in a)
                      + ")")
    return txt


def compare(base: dict[str, Any], injected: dict[str, Any], reported: str,
            truth: dict[str, Any]) -> dict[str, Any]:
    """Score an injected recording's diagnosis against its base's (both :func:`summary`).

    - ``found``: the injected effect is there with its parameter within 3 sigma or 10 % of
      the truth: a constant effect the base had already (a lag, an offset) by the change of
      its value; a step by the window that overlaps the injected one most.
    - ``extra`` / ``lost``: findings (windows of windowed effects, matched by overlap) the
      injected recording has and the base had not, and the reverse; the injected effect's
      own item is neither.
    - ``shifts``: the other findings' parameters, change over combined sigma (base and
      injected share their noise, so a change beyond one combined sigma is the model's
      doing); ``r_shift``: the same for R's rotation vector.
    """
    b_items, j_items = _items(base), _items(injected)
    own = None
    if reported in WINDOWED:
        w = truth["windows_s"][0]
        cand = [x for x in j_items if x["effect"] == reported and _overlap(x["window"], w) > 0]
        own = max(cand, key=lambda x: _overlap(x["window"], w), default=None)
    else:
        own = next((x for x in j_items if x["effect"] == reported), None)
    base_own = None
    if own is not None and reported not in WINDOWED:
        base_own = next((x for x in b_items if x["effect"] == reported), None)
    found, param_err = False, float("nan")
    if own is not None:
        k = PARAM_KEYS[reported]
        est, sig = _arr(own["params"][k]), _arr(own["sigma"].get(k, np.nan))
        if base_own is not None:  # the base's own lag or offset is subtracted
            est = est - _arr(base_own["params"][k])
            sig = np.hypot(sig, _arr(base_own["sigma"].get(k, np.nan)))
        t = _arr(truth[k])
        tol = np.maximum(3.0 * np.nan_to_num(sig), 0.1 * float(np.max(np.abs(t))))
        param_err = float(np.max(np.abs(est - t) / tol))
        found = bool(param_err <= 1.0)
    rest_j = [x for x in j_items if x is not own]
    rest_b = [x for x in b_items if x is not base_own]
    pairs, extra = [], []
    for x in rest_j:
        m = [y for y in rest_b if y["effect"] == x["effect"]
             and (x["window"] is None or _overlap(x["window"], y["window"]) > 0)]
        if m:
            y = max(m, key=lambda y: _overlap(x["window"], y["window"]))
            rest_b.remove(y)
            pairs.append((y, x))
        else:
            extra.append(x)
    lost = rest_b
    shifts = {_label(y): _shift(y, x) for y, x in pairs}
    d = np.asarray(injected["rotvec_deg"]) - np.asarray(base["rotvec_deg"])
    s = np.hypot(base["sigma_rotvec_deg"], injected["sigma_rotvec_deg"])
    r_shift = float(np.max(np.abs(d) / np.maximum(s, 1e-300)))
    return {"found": found, "own": None if own is None else _label(own),
            "not_identifiable": reported in injected.get("not_identifiable", []),
            "param_err_x_tol": param_err, "extra": [_label(x) for x in extra],
            "lost": [_label(x) for x in lost], "shifts": shifts,
            "max_shift": max([v for v in shifts.values() if np.isfinite(v)], default=0.0),
            "r_shift": r_shift, "r_change_deg": d.tolist()}


#: Stability bases (``bench/stability.py``, ``tests/test_stability.py``): name -> a lab
#: recording and which excerpt (``rotating``: the fewest metres per radian of
#: :func:`translating_segments`; ``translating``: the most; ``translating2``: the most of
#: those that do not overlap the first), or ``indep`` and the ``indep_gen.Spec`` options.
STABILITY_BASES: dict[str, tuple[str, Any]] = {
    "lab_03_rot": ("lab_03", "rotating"),
    "lab_05_rot": ("lab_05", "rotating"),
    "lab_01_tr": ("lab_01", "translating"),
    "lab_01_tr2": ("lab_01", "translating2"),
    "indep_rot": ("indep", {"seed": 101, "mag_rate_hz": 100.0, "att_rate_hz": 100.0,
                            "mag_noise_nT": 5.0}),
    "indep_tr": ("indep", {"seed": 102, "path": "translate", "mag_rate_hz": 100.0,
                           "att_rate_hz": 100.0, "mag_noise_nT": 5.0,
                           "swing_deg": (2.0, 3.0, 3.0)}),
    "indep_tr_fast": ("indep", {"seed": 103, "path": "translate", "mag_rate_hz": 200.0,
                                "att_rate_hz": 100.0, "mag_noise_nT": 20.0,
                                "swing_deg": (5.0, 4.0, 4.0), "freqs_hz": (0.2, 0.3, 0.25),
                                "translate_amp_m": 0.3}),
    "indep_survey": ("indep", {"seed": 104, "path": "survey", "mag_rate_hz": 100.0,
                               "att_rate_hz": 50.0, "mag_noise_nT": 5.0,
                               "swing_deg": (3.0, 3.0, 3.0), "survey_calibration_s": 20.0}),
}

#: Stability injections by group: (label, case of :func:`inject`, size, seed, step window s).
STABILITY_CASES: dict[str, list[tuple[str, str, float, int, float]]] = {
    "lag": [("lag+25ms", "time_offset", 0.025, 0, 0.0),
            ("lag-25ms", "time_offset", -0.025, 0, 0.0)],
    "offset": [(f"offset3000#{k}", "hard_iron", 3000.0, k, 0.0) for k in range(3)],
    "step": [("step1000x3s", "hard_iron_step", 1000.0, 0, 3.0),
             ("step2000x5s", "hard_iron_step", 2000.0, 1, 5.0),
             ("step3000x7s", "hard_iron_step", 3000.0, 2, 7.0)],
}


@functools.lru_cache(maxsize=2)
def read_real_cached(stem: str) -> Real:
    """:func:`read_real` of ``REAL_DIR/<stem>.mcap``, kept for the next caller (read-only)."""
    return read_real(REAL_DIR / f"{stem}.mcap")


def stability_base(name: str, seconds: float = 60.0) -> tuple[Real, str]:
    """The base ``name`` of :data:`STABILITY_BASES`, ``seconds`` long, and how it moves."""
    src, how = STABILITY_BASES[name]
    if src == "indep":
        from indep_gen import Spec

        spec = Spec(name=name, duration_s=seconds, **how)
        r = from_indep(spec)
        m = motion(r)
        what = f"indep {spec.path} mag {spec.mag_rate_hz:g} Hz att {spec.att_rate_hz:g} Hz"
    else:
        full = read_real_cached(src)
        segs = translating_segments(full, seconds, 10.0)
        if how == "rotating":
            a = segs[-1]["start_s"]
        elif how == "translating":
            a = segs[0]["start_s"]
        else:
            a = next(s["start_s"] for s in segs if abs(s["start_s"] - segs[0]["start_s"])
                     >= seconds)
        m = motion(full, a, a + seconds)
        r = excerpt(full, a, seconds)
        what = f"{src} [{a:.0f}, {a + seconds:.0f}) s"
    return r, (f"{what}: rot rms {m['rot_rms_deg']:.0f} deg, pos rms {m['pos_rms_m']:.2f} m, "
               f"{m['m_per_rad']:.2f} m/rad")
