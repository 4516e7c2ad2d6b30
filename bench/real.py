"""What magalign finds in the real lab recordings: the figures of docs/real-data.md.

For each of ``../shared/data/real/lab_0*.mcap`` (skipped when the folder is absent):

- ``calibrate --estimate offset,soft_iron,time_offset``: rotation vector and sigma, effective
  samples, terms not estimated, verdict;
- the split-half test: the first and second half of the recording calibrated on their own,
  their difference in combined sigmas per axis (target: below 3 on every recording);
- the diagnosis (as ``process`` runs it): findings, final held-out RMS against the sensor noise
  measured in still windows (target: within 10 %).

Run: ``.venv/bin/python bench/real.py [lab_01 ...]``.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT.parent / "shared" / "data" / "real"
sys.path.insert(0, str(ROOT))

from pipeline.core.geometry import matrix_to_quat, quat_to_rotvec  # noqa: E402
from pipeline.core.recording import Context  # noqa: E402
from pipeline.io.mcap_read import read_recording  # noqa: E402
from stages.estimate import Term, fit_calibration  # noqa: E402
from stages.resample import Resample  # noqa: E402

ALL = frozenset({Term.OFFSET, Term.SOFT_IRON, Term.TIME_OFFSET})


def _rv(R: np.ndarray) -> np.ndarray:
    return np.degrees(quat_to_rotvec(matrix_to_quat(R)))


def _vec(v: np.ndarray, nd: int = 2) -> str:
    return "(" + ", ".join(f"{x:+.{nd}f}" for x in v) + ")"


def one(name: str) -> None:
    """Print the figures of one recording."""
    path = REAL / f"{name}.mcap"
    rec = read_recording(path)
    al = Resample().run(Context(source=str(path), recording=rec)).aligned
    t0 = time.perf_counter()
    cal = fit_calibration(rec, al, terms=ALL)
    dt = time.perf_counter() - t0
    print(f"## {name}  ({dt:.1f} s)")
    print(f"calibrate: rotvec {_vec(cal.rotvec_body_mag_deg)} +- {_vec(cal.sigma_rotvec_deg)} deg,"
          f" n_eff {cal.n_eff:.0f} of {cal.n_samples}")
    if cal.time_offset_s is not None:
        print(f"  tau {cal.time_offset_s * 1e3:.2f} +- {cal.sigma_time_offset_s * 1e3:.2f} ms")
    ne = ", ".join(d["term"] for d in cal.not_estimated) or "none"
    print(f"  not estimated: {ne}")
    print(f"  verdict {cal.verdict.line()}")
    mid = al.t_ns[0] + (al.t_ns[-1] - al.t_ns[0]) // 2
    a = fit_calibration(rec, al.select(al.t_ns < mid), terms=ALL)
    b = fit_calibration(rec, al.select(al.t_ns >= mid), terms=ALL)
    d = _rv(a.R_body_mag @ b.R_body_mag.T)
    z = np.abs(d) / np.hypot(a.sigma_rotvec_deg, b.sigma_rotvec_deg)
    print(f"split halves: first {_vec(a.rotvec_body_mag_deg)} +- {_vec(a.sigma_rotvec_deg)}, "
          f"second {_vec(b.rotvec_body_mag_deg)} +- {_vec(b.sigma_rotvec_deg)}; "
          f"z {_vec(z, 1)} (max {np.max(z):.1f})")
    from stages.diagnose.stage import Diagnose

    ctx = Context(source=str(path), recording=rec, aligned=al, calibration=cal)
    t0 = time.perf_counter()
    out = Diagnose().run(ctx)
    dt = time.perf_counter() - t0
    dg = out.diagnosis.to_dict()
    noise = cal.verdict.sensor_noise_nT
    held = dg["final"]["heldout_rms_nT"]
    print(f"diagnose ({dt:.1f} s): baseline held-out {dg['baseline']['heldout_rms_nT']:.0f} nT -> "
          f"final {held:.0f} nT; still-window noise {noise:.0f} nT; final/noise "
          f"{held / noise:.2f}")
    for f in dg["findings"]:
        ev = f["evidence"]
        print(f"  {f['effect']}: held-out {ev['heldout_rms_before_nT']:.0f} -> "
              f"{ev['heldout_rms_after_nT']:.0f} nT")
    fc = out.calibration
    print(f"  final rotvec {_vec(fc.rotvec_body_mag_deg)} +- {_vec(fc.sigma_rotvec_deg)}")
    print()


def main(argv: list[str]) -> int:
    """Run the recordings named (default: all five)."""
    if not REAL.is_dir():
        print(f"real data folder absent ({REAL.name}); nothing to do")
        return 0
    names = argv or sorted(p.stem for p in REAL.glob("lab_*.mcap"))
    for n in names:
        one(n)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
