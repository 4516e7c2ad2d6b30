"""Diagnosis challenges: recordings with concealed effects, and scoring against the key.

More in docs/modules.md, ``pipeline.app.challenge``.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.app.simulate import Truth, scenario_from_dict, simulate, write_simulated
from pipeline.core.atomic import write_text_atomic
from pipeline.core.errors import InputError
from pipeline.core.geometry import quat_mul, quat_to_matrix
from pipeline.core.validate import read_json_object
from pipeline.model.attitude import mean_interpolation_noise_factor
from stages.diagnose.model import AttitudeTrack, FitData, ModelState, evaluate

KINDS = (
    "hard_iron",
    "soft_iron",
    "time_offset",
    "eddy_current",
    "field_drift",
    "disturbance",
    "hard_iron_step",
    "field_gradient",
    "sample_hold",
    "heading_drift",
)
# field_gradient: 5 parameters and the searched yaw of the position frame; sample_hold: the
# native rate (the repeats follow from it)
_K = {"hard_iron": 3, "soft_iron": 5, "time_offset": 1, "eddy_current": 9, "field_drift": 12,
      "disturbance": 15, "hard_iron_step": 3, "field_gradient": 6, "sample_hold": 1,
      "heading_drift": 2}

DURATION_S = 60.0
RATE_HZ = 50.0


def key_path(challenge_dir: str | Path) -> Path:
    """Where the key of a challenge folder lives (a sibling folder, not inside it)."""
    d = Path(challenge_dir).resolve()
    return d.parent / f"{d.name}_key" / "key.json"


def _effect_params(kind: str, rng: np.random.Generator, scale: float) -> dict[str, Any]:
    """Random parameters of ``kind``; ``scale`` ~ 1 strong, ~0.1 near threshold."""
    u = rng.normal(size=3)
    u /= np.linalg.norm(u)
    if kind == "hard_iron":
        return {"offset_nT": (u * 60.0 * scale).tolist()}
    if kind == "soft_iron":
        A = rng.normal(size=(3, 3)) * 0.004 * scale
        D = np.eye(3) + 0.5 * (A + A.T)
        return {"D": D.tolist()}
    if kind == "time_offset":
        return {"time_offset_s": float(rng.choice([-1, 1]) * 0.002 * scale)}
    if kind == "eddy_current":
        E = np.diag(rng.uniform(0.5, 1.0, 3) * rng.choice([-1, 1], 3)) * 0.002 * scale
        return {"E_s": E.tolist()}
    if kind == "field_drift":
        return {"peak_to_peak_nT": (np.abs(u) * 120.0 * scale + 5.0 * scale).tolist(),
                "period_s": float(rng.uniform(1.0, 2.0) * DURATION_S)}
    if kind == "disturbance":
        a = float(rng.uniform(8.0, DURATION_S - 16.0))
        return {"windows_s": [[a, a + float(rng.uniform(4.0, 8.0))]],
                "peak_nT": float(300.0 * scale), "direction_enu": u.tolist()}
    if kind == "hard_iron_step":
        a = float(rng.uniform(8.0, DURATION_S - 20.0))
        return {"windows_s": [[a, a + float(rng.uniform(6.0, 12.0))]],
                "offset_nT": (u * 60.0 * scale).tolist()}
    if kind == "field_gradient":
        # symmetric traceless (free space), Frobenius norm 400 nT/m at scale 1 (about 120 nT
        # over the 0.3 m of the path)
        A = rng.normal(size=(3, 3))
        G = 0.5 * (A + A.T)
        G -= np.trace(G) / 3.0 * np.eye(3)
        G *= 400.0 * scale / np.linalg.norm(G)
        return {"G_nT_per_m": G.tolist()}
    if kind == "sample_hold":
        return {"native_rate_hz": float(RATE_HZ * rng.uniform(0.55, 0.85))}
    if kind == "heading_drift":
        # an INS gyro bias: the heading error grows linearly, 0.1 deg over the recording at
        # scale 1 (about 35 nT across a 20 uT horizontal field)
        ptp = 0.1 * scale
        rate = float(rng.choice([-1, 1])) * ptp / DURATION_S * 3600.0
        return {"rate_deg_per_h": rate, "peak_to_peak_deg": ptp}
    raise ValueError(kind)


def apply_heading_drift(sim: Any, rate_deg_per_h: float) -> Any:
    """Return ``sim`` with its attitude channel turned about Up by ``h(t) = rate t``.

    The attitude source reports ``Rz(h(t)) C_true(t)`` (CONVENTIONS ``heading_drift``), ``t``
    from the first magnetometer sample; the magnetometer and the truth are unchanged.
    """
    att = sim.recording.attitude
    t0 = int(sim.recording.mag.t_ns[0])
    h = np.radians(rate_deg_per_h / 3600.0) * (np.asarray(att.t_ns) - t0) * 1e-9
    qz = np.stack([0 * h, 0 * h, np.sin(h / 2), np.cos(h / 2)], axis=-1)
    q = quat_mul(qz, np.asarray(att.q_enu_body))
    rec = dataclasses.replace(sim.recording,
                              attitude=dataclasses.replace(att, q_enu_body=q))
    return dataclasses.replace(sim, recording=rec)


def _scenario(rng: np.random.Generator, effects: dict[str, dict[str, Any]], i: int) -> dict:
    return {
        "name": f"rec_{i:03d}",
        "seed": int(rng.integers(1 << 30)),
        "timing": {"start": "2026-01-01T00:00:00Z", "duration_s": DURATION_S,
                   "mag_rate_hz": RATE_HZ, "attitude_rate_hz": RATE_HZ,
                   "attitude_phase_s": float(rng.uniform(0.0, 0.5 / RATE_HZ))},
        "motion": {"profile": "multiaxis",
                   "yaw_rate_deg_s": float(rng.uniform(6.0, 15.0)),
                   "yaw_amplitude_deg": float(rng.uniform(10.0, 40.0)),
                   "yaw_period_s": float(rng.uniform(10.0, 20.0)),
                   "pitch_amplitude_deg": float(rng.uniform(10.0, 30.0)),
                   "pitch_period_s": float(rng.uniform(5.0, 9.0)),
                   "roll_amplitude_deg": float(rng.uniform(10.0, 30.0)),
                   "roll_period_s": float(rng.uniform(9.0, 13.0))},
        "field": {"enu_nT": [float(rng.uniform(-2000, 2000)), float(rng.uniform(15000, 25000)),
                             float(rng.uniform(-48000, -38000))]},
        "sensor": {"misalignment_rotvec_deg": rng.uniform(-2.0, 2.0, 3).tolist()},
        "effects": effects,
        "noise": {"mag_sigma_nT": 2.0, "heading_sigma_deg": 0.01, "pitch_roll_sigma_deg": 0.005},
        # every recording moves through space and writes its positions into the pose (in a
        # room frame of random bearing), so that nulls can show a gradient is not invented
        "trajectory": {"amplitude_m": rng.uniform(0.2, 0.4, 3).tolist(),
                       "period_s": rng.uniform(5.0, 13.0, 3).tolist(),
                       "phase_rad": rng.uniform(0.0, 2 * np.pi, 3).tolist(),
                       "frame_yaw_deg": float(rng.uniform(0.0, 360.0))},
        "output": {"attitude_type": "geometry_msgs/msg/PoseStamped"},
    }


def _strength(sim_full: Any, sim_without: Any, kind: str, noise: dict[str, float]) -> float:
    """Amplitude of an effect as a multiple of its detection threshold (see module doc)."""
    d = np.asarray(sim_full.truth.mag_clean_nT) - np.asarray(sim_without.truth.mag_clean_nT)
    return _strength_of(d, sim_full, kind, noise)


def _strength_of(d: np.ndarray, sim_full: Any, kind: str, noise: dict[str, float]) -> float:
    """Strength of a noise-free signature ``d`` (N, 3), mag frame nT (see the module doc)."""
    tr: Truth = sim_full.truth
    t_ns = np.asarray(tr.mag_t_ns)
    t_s = (t_ns - t_ns[0]) * 1e-9
    track = AttitudeTrack(t_s, np.asarray(tr.q_enu_body_true))
    data = FitData(t_s, np.zeros((len(t_s), 3)), track)
    st = ModelState(np.asarray(tr.R_body_mag), np.asarray(tr.B_enu_nT))
    J = evaluate(st, data).jac.reshape(-1, 6)
    dv = d.reshape(-1)
    coef, *_ = np.linalg.lstsq(J, dv, rcond=None)
    rem = dv - J @ coef
    B = float(np.linalg.norm(tr.B_enu_nT))
    att = np.radians(np.sqrt((noise["heading_sigma_deg"] ** 2
                              + 2 * noise["pitch_roll_sigma_deg"] ** 2) / 3.0))
    var = noise["mag_sigma_nT"] ** 2 + (B * att) ** 2 * mean_interpolation_noise_factor()
    lam = float(rem @ rem) / var
    lam_thr = _K[kind] * np.log(dv.size) + 20.0
    return float(np.sqrt(lam / lam_thr))


def _heading_strength(sim: Any, rate_deg_per_h: float, noise: dict[str, float]) -> float:
    """Strength of a heading drift (see the module doc).

    Its signature is the field turned about Up, ``h(t) (-B_N, B_E, 0)`` in ENU, seen through
    the true attitude.
    """
    tr = sim.truth
    t_ns = np.asarray(tr.mag_t_ns)
    t_s = (t_ns - t_ns[0]) * 1e-9
    B = np.asarray(tr.B_enu_nT, dtype=float)
    h = np.radians(rate_deg_per_h / 3600.0) * t_s
    dB = h[:, None] * np.array([-B[1], B[0], 0.0])
    C = quat_to_matrix(np.asarray(tr.q_enu_body_true))
    R = np.asarray(tr.R_body_mag)
    d = np.einsum("ji,njk,nk->ni", R, C, dB)  # R.T C.T dB
    return _strength_of(d, sim, "heading_drift", noise)


def generate(n: int, seed: int, out_dir: str | Path, *, null_fraction: float = 0.3,
             only: list[list[str]] | None = None) -> Path:
    """Write ``n`` challenge recordings to ``out_dir`` and the key beside it.

    Parameters
    ----------
    n : int
        Number of recordings.
    seed : int
        Random seed (the same seed gives the same challenge).
    out_dir : path
        Folder for ``rec_000.mcap ...``; the key goes to ``<out_dir>_key/key.json``.
    null_fraction : float
        Probability that a recording has no effect (the rest: 5/7 one effect, 2/7 a pair).
    only : list of list of str, optional
        The effects of each recording, at full strength, instead of random ones (``n`` is
        then ``len(only)``).

    Returns
    -------
    Path
        The key file.

    """
    rng = np.random.default_rng(seed)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    key: dict[str, Any] = {"format": "magalign.challenge_key/1", "seed": seed, "recordings": {}}
    for i in range(len(only) if only is not None else n):
        r = rng.uniform()
        count = 0 if r < null_fraction else (
            1 if r < null_fraction + (1.0 - null_fraction) * 5.0 / 7.0 else 2)
        kinds = list(rng.choice(KINDS, size=count, replace=False)) if count else []
        # local effects in one recording would share windows; keep pairs distinguishable
        if {"disturbance", "hard_iron_step"} <= set(kinds):
            kinds.remove("hard_iron_step")
        # a time offset is the isotropic case of eddy currents: together they are one term
        if {"eddy_current", "time_offset"} <= set(kinds):
            kinds.remove("eddy_current")
        if only is not None:
            kinds = list(only[i])
        effects = {}
        for k in kinds:
            scale = float(rng.choice([1.0, 1.0, 0.5, 0.1])) if only is None else 1.0
            effects[str(k)] = _effect_params(str(k), rng, scale)
        # heading_drift is an error of the attitude source, applied to the written attitude
        hd = effects.get("heading_drift")
        scen = _scenario(rng, {k: v for k, v in effects.items() if k != "heading_drift"}, i)
        sim = simulate(scenario_from_dict(scen, path=f"rec_{i:03d}"))
        strengths = {}
        for k in effects:
            if k == "heading_drift":
                continue
            rest = {kk: v for kk, v in scen["effects"].items() if kk != k}
            sim_wo = simulate(scenario_from_dict({**scen, "effects": rest}, path="x"))
            strengths[k] = _strength(sim, sim_wo, k, scen["noise"])
        if hd is not None:
            strengths["heading_drift"] = _heading_strength(sim, hd["rate_deg_per_h"],
                                                           scen["noise"])
            sim = apply_heading_drift(sim, hd["rate_deg_per_h"])
        name = f"rec_{i:03d}"
        write_simulated(sim, out / f"{name}.mcap")
        key["recordings"][name] = {
            "effects": {k: _public_params(k, v, scen, sim) for k, v in effects.items()},
            "strength_x_threshold": strengths,
            "truth": sim.truth.to_dict(),
        }
    kp = key_path(out)
    kp.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(kp, json.dumps(key, indent=1))
    return kp


def _public_params(kind: str, p: dict[str, Any], scen: dict | None = None, sim: Any = None
                   ) -> dict[str, Any]:
    if kind == "field_gradient" and scen is not None:
        # what a diagnosis reports: G_enu Q, Q the rotation from the written (room) frame
        a = np.radians(scen["trajectory"]["frame_yaw_deg"])
        Q = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0, 0, 1.0]])
        return {"G_nT_per_m": (np.asarray(p["G_nT_per_m"]) @ Q).tolist(),
                "position_frame": "attitude_source_local"}
    if kind == "sample_hold" and sim is not None:
        m = np.asarray(sim.recording.mag.values)
        rep = float(np.mean(np.all(m[1:] == m[:-1], axis=1))) if len(m) > 1 else 0.0
        return {"native_rate_hz": p["native_rate_hz"], "repeated_fraction": rep}
    keep = {"field_drift": ("peak_to_peak_nT",), "disturbance": ("windows_s", "peak_nT")}
    if kind in keep:
        return {k: p[k] for k in keep[kind]}
    return dict(p)


# ----------------------------------------------------------------------------- scoring


def _param_errors(kind: str, true: dict[str, Any], found: dict[str, Any],
                  sigma: dict[str, Any]) -> list[float]:
    """Errors in units of the reported sigma (|est - true| / sigma) of comparable params."""
    def z(a: Any, b: Any, s: Any) -> list[float]:
        a, b, s = (np.asarray(x, dtype=float).ravel() for x in (a, b, s))
        return (np.abs(a - b) / np.maximum(s, 1e-12)).tolist()

    if kind in ("hard_iron", "hard_iron_step"):
        return z(found["offset_nT"], true["offset_nT"], sigma.get("offset_nT", 1e-12))
    if kind == "time_offset":
        return z(found["time_offset_s"], true["time_offset_s"], sigma.get("time_offset_s", 1e-12))
    if kind == "soft_iron":
        Dt = np.asarray(true["D"])
        Dt = Dt / (np.trace(Dt) / 3.0)  # the isotropic scale belongs to |B_enu|
        return z(found["D"], Dt, sigma.get("D", 1e-12))
    if kind == "eddy_current":
        return z(found["E_s"], true["E_s"], sigma.get("E_s", 1e-12))
    if kind == "field_gradient":
        return z(found["G_nT_per_m"], true["G_nT_per_m"], sigma.get("G_nT_per_m", 1e-12))
    if kind == "sample_hold":
        return z(found["native_rate_hz"], true["native_rate_hz"],
                 sigma.get("native_rate_hz", 1e-12))
    if kind == "heading_drift":
        return z(found["rate_deg_per_h"], true["rate_deg_per_h"],
                 sigma.get("rate_deg_per_h", 1e-12))
    return []


def score(challenge_dir: str | Path, results_dir: str | Path,
          key_file: str | Path | None = None) -> dict[str, Any]:
    """Compare diagnoses with the key.

    Parameters
    ----------
    challenge_dir : path
        The folder ``generate`` wrote (its key is found beside it unless ``key_file``).
    results_dir : path
        Holds ``<stem>/diagnosis.json`` per recording (``magalign diagnose --out``).
    key_file : path, optional
        The key, when it is not in the default sibling folder.

    Returns
    -------
    dict
        ``confusion`` (true effect or ``none`` -> found effect or ``none`` -> count),
        ``n``, ``exact``, ``strong_n``, ``strong_exact``, ``null_n``, ``null_false``,
        ``param_within_3sigma`` (fraction), ``rows`` (per recording).

    """
    kp = Path(key_file) if key_file is not None else key_path(challenge_dir)
    key = read_json_object(kp, "a challenge key",
                           hint="give the key.json written by magalign simulate --challenge")
    if not isinstance(key.get("recordings"), dict):
        raise InputError("not a challenge key: no 'recordings' in it", path=kp,
                         hint="give the key.json written by magalign simulate --challenge")
    confusion: dict[str, dict[str, int]] = {}
    rows = []
    zs: list[float] = []
    n = exact = strong_n = strong_exact = null_n = null_false = 0
    for name, k in sorted(key["recordings"].items()):
        dpath = Path(results_dir) / name / "diagnosis.json"
        if dpath.exists():
            diag = read_json_object(dpath, "a diagnosis.json")
            if not isinstance(diag.get("findings"), list):
                raise InputError("not a diagnosis.json: no 'findings' list in it", path=dpath)
            found = [f["effect"] for f in diag["findings"]]
        else:
            diag, found = None, ["<missing>"]
        true = set(k["effects"])
        fs = set(found)
        ok = fs == true
        n += 1
        exact += ok
        strong = all(v >= 5.0 for v in k["strength_x_threshold"].values())
        if strong:
            strong_n += 1
            strong_exact += ok
        if not true:
            null_n += 1
            null_false += bool(fs)
        for t in (true or {"none"}):
            row = confusion.setdefault(t, {})
            for f in (fs or {"none"}):
                if t == f or t == "none" or f not in true:
                    row[f] = row.get(f, 0) + 1
        if diag is not None:
            for f in diag["findings"]:
                if f["effect"] in k["effects"]:
                    zs += _param_errors(f["effect"], k["effects"][f["effect"]], f["params"],
                                        f["sigma"])
        rows.append({"recording": name, "true": sorted(true), "found": found, "exact": ok,
                     "strength": k["strength_x_threshold"]})
    zs_a = np.asarray(zs)
    return {
        "n": n,
        "exact": exact,
        "strong_n": strong_n,
        "strong_exact": strong_exact,
        "null_n": null_n,
        "null_false": null_false,
        "param_within_3sigma": float(np.mean(zs_a <= 3.0)) if zs_a.size else None,
        "n_param_checks": int(zs_a.size),
        "confusion": confusion,
        "rows": rows,
    }


def confusion_text(result: dict[str, Any]) -> str:
    """Return the confusion table as text: rows true effect, columns found effect."""
    cols = sorted({c for r in result["confusion"].values() for c in r} | {"none"})
    head = f"{'true/found':<16}" + "".join(f"{c[:14]:>15}" for c in cols)
    lines = [head]
    for t in sorted(result["confusion"]):
        r = result["confusion"][t]
        lines.append(f"{t:<16}" + "".join(f"{r.get(c, 0):>15}" for c in cols))
    return "\n".join(lines)
