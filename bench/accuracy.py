"""Monte Carlo accuracy of the misalignment estimators against the Cramer-Rao bound.

Multi-axis manoeuvre (two heading turns with +-30 deg pitch and roll swings), 2000 samples at
50 Hz, field [10000, 30000, 20000] nT unknown to the estimators, the paper's sensor figures
(magnetometer 0.1 nT; INS heading 0.06 deg, pitch and roll 0.015 deg). For each misalignment
angle (rotation about body x, y, z): RMS error of li2020, dpi and ml, the Cramer-Rao bound
from the Fisher information at the truth, and ml's mean reported sigma.
Targets: ml RMS <= 1.1 x CRB; ml sigma within 20% of its actual spread.

Usage: python bench/accuracy.py [RUNS]   (default 200)
"""

from __future__ import annotations

import sys
import time

import numpy as np

from pipeline.geometry import so3_log
from stages.estimate import EstimatorKind, NoiseModel, fit_calibration
from stages.estimators.base import Problem
from stages.estimators.ml import fisher_rotation_crb_deg
from stages.estimators.synthetic import draw, small_rotation


def main(runs: int = 200) -> int:
    noise = NoiseModel.li2020()
    R = small_rotation([1.0, -2.0, 3.0])
    kinds = (EstimatorKind.LI2020, EstimatorKind.DPI, EstimatorKind.ML)
    errs = {k: [] for k in kinds}
    sig_ml = []
    crb = None
    t0 = time.time()
    for i in range(runs):
        s = draw(
            kind="multi",
            n=2000,
            rate_hz=50.0,
            R_body_mag=R,
            noise=noise,
            rng=np.random.default_rng(10_000 + i),
        )
        if crb is None:
            al = s.aligned
            p = Problem(al.t_ns, al.mag_nT, s.q_true, noise=noise)
            crb = fisher_rotation_crb_deg(p, R, s.B_enu_nT)
        for k in kinds:
            cal = fit_calibration(
                None, s.aligned, estimator=k, noise=noise if k is EstimatorKind.ML else None
            )
            errs[k].append(np.degrees(so3_log(cal.R_body_mag @ R.T)))
            if k is EstimatorKind.ML:
                sig_ml.append(cal.sigma_rotvec_deg)
    dt = time.time() - t0
    rms = {k: np.sqrt(np.mean(np.square(errs[k]), 0)) for k in kinds}
    spread = np.std(np.array(errs[EstimatorKind.ML]), 0)
    sig = np.mean(sig_ml, 0)
    print(f"{runs} runs, 2000 samples each, {dt:.0f} s")
    print("RMS error of the misalignment angles [deg] (rotation about body x, y, z)")
    print(
        f"{'axis':<5} {'li2020':>10} {'dpi':>10} {'ml':>10} {'CRB':>10} {'ml/CRB':>7} "
        f"{'ml sigma':>10} {'sigma/spread':>12}"
    )
    ok = True
    for a, name in enumerate("xyz"):
        ratio = rms[EstimatorKind.ML][a] / crb[a]
        sr = sig[a] / spread[a]
        ok &= ratio <= 1.1 and abs(sr - 1) <= 0.2
        print(
            f"{name:<5} {rms[EstimatorKind.LI2020][a]:10.5f} {rms[EstimatorKind.DPI][a]:10.5f} "
            f"{rms[EstimatorKind.ML][a]:10.5f} {crb[a]:10.5f} {ratio:7.3f} {sig[a]:10.5f} "
            f"{sr:12.3f}"
        )
    print("targets (ml <= 1.1 x CRB, sigma within 20% of spread):", "met" if ok else "NOT met")
    return 0


if __name__ == "__main__":
    sys.exit(main(int(sys.argv[1]) if len(sys.argv) > 1 else 200))
