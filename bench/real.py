"""What magalign finds in the real lab recordings: the figures of docs/real-data.md.

For each of ``../shared/data/real/lab_0*.mcap`` (skipped when the folder is absent), through
the analysis stages that ``calibrate``, ``diagnose`` and ``process`` share
(:func:`pipeline.run.runner.analyse`):

- the answer: rotation vector and sigma, verdict, findings with their held-out RMS, the
  final held-out RMS against the sensor noise measured in still windows;
- the restricted model ``--estimate offset,soft_iron,time_offset``: its rotation, its sigma
  widened by the shift the terms it leaves out cause, and its distance from the answer in
  combined sigmas (target: within 3);
- time thirds: each third of the recording analysed on its own; the largest difference
  between two thirds in combined sigmas (target: within 3);
- at the end, every answer against the others: none more than 3 deg from the median of
  the rest with its largest sigma below a third of that distance ("no confident wrong R").

Run: ``.venv/bin/python bench/real.py [lab_01 ...] [--no-thirds]``.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT.parent / "shared" / "data" / "real"
sys.path.insert(0, str(ROOT))

from pipeline.core.geometry import matrix_to_quat, quat_to_rotvec  # noqa: E402
from pipeline.core.recording import Recording  # noqa: E402
from pipeline.core.vocabulary import EstimateTerm  # noqa: E402
from pipeline.model.calibration import Calibration  # noqa: E402
from pipeline.run.runner import ProcessOptions, analyse, analyse_recording  # noqa: E402

RESTRICTED = ProcessOptions(terms=frozenset({EstimateTerm.OFFSET, EstimateTerm.SOFT_IRON,
                                             EstimateTerm.TIME_OFFSET}),
                            write_rerun=False, write_report=False)
DEFAULT = ProcessOptions(write_rerun=False, write_report=False)


def _vec(v: np.ndarray, nd: int = 2) -> str:
    return "(" + ", ".join(f"{x:+.{nd}f}" for x in v) + ")"


def z_between(a: Calibration, b: Calibration) -> np.ndarray:
    """Per-axis difference of two rotations in combined sigmas (body frame)."""
    d = np.degrees(quat_to_rotvec(matrix_to_quat(np.asarray(a.R_body_mag)
                                                 @ np.asarray(b.R_body_mag).T)))
    return np.abs(d) / np.hypot(a.sigma_rotvec_deg, b.sigma_rotvec_deg)


def span(rec: Recording, a_ns: int, b_ns: int) -> Recording:
    """The recording between two stamps (half-open); the attitude 1 s wider on each side."""
    pad = 1_000_000_000
    return dataclasses.replace(
        rec, mag=rec.mag.window(a_ns, b_ns),
        attitude=None if rec.attitude is None else rec.attitude.window(a_ns - pad, b_ns + pad),
        position=None if rec.position is None else rec.position.window(a_ns - pad, b_ns + pad))


def one(name: str, thirds: bool) -> Calibration:
    """Print the figures of one recording; return its answer."""
    path = REAL / f"{name}.mcap"
    t0 = time.perf_counter()
    ctx = analyse_recording(path, DEFAULT)
    dt = time.perf_counter() - t0
    cal = ctx.need_calibration()
    dg = ctx.diagnosis.to_dict() if ctx.diagnosis is not None else None
    print(f"## {name}  ({dt:.0f} s)")
    print(f"answer: rotvec {_vec(cal.rotvec_body_mag_deg)} +- {_vec(cal.sigma_rotvec_deg)} deg; "
          f"{cal.verdict.status.value if cal.verdict else '-'}")
    if dg is not None:
        noise = cal.verdict.sensor_noise_nT if cal.verdict else None
        held = dg["final"]["heldout_rms_nT"]
        ratio = f"{held / noise:.2f}" if noise else "-"
        print(f"  held-out {dg['baseline']['heldout_rms_nT']:.0f} -> {held:.0f} nT; still-window "
              f"noise {noise or float('nan'):.0f} nT; final/noise {ratio}")
        for f in dg["findings"]:
            ev = f["evidence"]
            extra = ""
            if f["effect"] == "local_source":
                p = f["params"]
                extra = (f" at {_vec(np.asarray(p['position_m']))} m, |m| "
                         f"{np.linalg.norm(p['moment_Am2']):.3g} A m^2, closest "
                         f"{100 * p['closest_approach_m']:.0f} cm at "
                         f"{p['closest_approach_s']:.1f} s")
            print(f"  {f['effect']}: held-out {ev['heldout_rms_before_nT']:.0f} -> "
                  f"{ev['heldout_rms_after_nT']:.0f} nT{extra}")
    rec = analyse(ctx.need_recording(), RESTRICTED)
    rc = rec.need_calibration()
    z = z_between(cal, rc)
    print(f"restricted (offset, soft_iron, time_offset): {_vec(rc.rotvec_body_mag_deg)} +- "
          f"{_vec(rc.sigma_rotvec_deg)}; from the answer {_vec(z, 1)} sigma (max "
          f"{np.max(z):.1f})")
    if thirds:
        r = ctx.need_recording()
        ta, tb = int(r.mag.t_ns[0]), int(r.mag.t_ns[-1]) + 1
        cuts = [ta + (tb - ta) * k // 3 for k in range(4)]
        parts = []
        for k in range(3):
            sub = span(r, cuts[k], cuts[k + 1])
            try:
                c = analyse(sub, DEFAULT).need_calibration()
            except Exception as exc:  # a third may be refused: that is a result, not a crash
                print(f"  third {k + 1}: {type(exc).__name__}: {exc}")
                continue
            parts.append(c)
            print(f"  third {k + 1}: {_vec(c.rotvec_body_mag_deg)} +- "
                  f"{_vec(c.sigma_rotvec_deg)}")
        zs = [float(np.max(z_between(a, b))) for i, a in enumerate(parts) for b in parts[i + 1:]]
        if zs:
            print(f"thirds: largest difference {max(zs):.1f} combined sigmas")
    print()
    return cal


def main(argv: list[str]) -> int:
    """Run the recordings named (default: all five)."""
    if not REAL.is_dir():
        print(f"real data folder absent ({REAL.name}); nothing to do")
        return 0
    thirds = "--no-thirds" not in argv
    names = [a for a in argv if not a.startswith("--")] or sorted(
        p.stem for p in REAL.glob("lab_*.mcap"))
    answers = {n: one(n, thirds) for n in names}
    print("## no confident wrong R")
    for n, c in answers.items():
        others = [np.asarray(o.rotvec_body_mag_deg) for m, o in answers.items() if m != n]
        if not others:
            continue
        ref = np.median(np.stack(others), axis=0)
        dist = float(np.linalg.norm(np.asarray(c.rotvec_body_mag_deg) - ref))
        big = float(np.max(c.sigma_rotvec_deg))
        wrong = dist > 3.0 and big < dist / 3.0
        print(f"{n}: {dist:.2f} deg from the others' median, largest sigma {big:.2f} deg"
              + ("  CONFIDENT AND WRONG" if wrong else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
