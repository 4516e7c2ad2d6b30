"""False alarms of the split-halves check, measured on null recordings.

Usage: ``python bench/halves_null.py [--n N] [--seed S] [--duration S] [--no-record]``.

Every calibration fits the two halves of its recording (halves of equal rotation
information) on their own and compares their rotations (``stages.estimators.checks``): halves
that disagree beyond the covariance of their difference make the verdict QUESTIONABLE. On a
null recording (white noise only, nothing the model leaves out) that happens by chance alone,
at the check's stated false-alarm rate ``SPLIT_FALSE_ALARM`` per test. This runs the whole
analysis the ``calibrate`` command runs (estimate, diagnosis, verdict) on ``N`` independent
nulls of the independent generator (``tests/indep_gen.py``, :func:`null_specs`: rates,
phases, jitter, the four attitude message types, multi- and single-axis motion, vibration,
attitude noise 0.001-0.05 deg and magnetometer noise 0.1-20 nT) and counts:

- ``estimate``: nulls whose estimate's halves fail the check;
- ``final``: nulls whose final model's halves (after the diagnosis) fail it;
- ``verdict``: nulls whose calibration holds a halves doubt (QUESTIONABLE because of them,
  unless something graver already refused it).

Each count is printed beside what the stated rate expects of ``N`` tests and the binomial
upper 95 % bound of that expectation: a count above the bound says the stated rate does not
hold. When the diagnosis runs (as in ``calibrate``), the final model's check is the one
the verdict carries; the estimate's is shown for comparison.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
from scipy.stats import binom

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
sys.path.insert(0, str(ROOT / "tests"))

from indep_gen import null_specs, write  # noqa: E402
from results import record  # noqa: E402

from pipeline.run.runner import analyse_recording  # noqa: E402
from stages.estimators import checks  # noqa: E402

HALVES = "the two halves"


def one(path: Path) -> dict:
    """Calibrate one recording as ``calibrate`` does; the halves' checks and the verdict."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = analyse_recording(path).need_calibration()
    ch = cal.checks
    lim = getattr(checks, "split_limit", None)

    def failed(key: str) -> bool | None:
        s = ch.get(key)
        if not s:
            return None
        if "consistent" in s:
            return not bool(s["consistent"])
        return float(s["chi2"]) > (lim(3) if lim else checks.SPLIT_CHI2_95)

    v = cal.verdict
    return {
        "estimate": failed("split"),
        "final": failed("split_final"),
        "verdict": any(d.startswith(HALVES) for d in ch.get("doubts", ())),
        "status": None if v is None else v.status.value,
        "chi2": [None if not ch.get(k) else float(ch[k]["chi2"])
                 for k in ("split", "split_final")],
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=50)
    ap.add_argument("--seed", type=int, default=3901)
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--no-record", action="store_true")
    a = ap.parse_args(argv)
    rate = float(getattr(checks, "SPLIT_FALSE_ALARM", 0.05))
    t0 = time.perf_counter()
    rows = []
    with tempfile.TemporaryDirectory() as d:
        for spec in null_specs(a.n, a.seed, duration_s=a.duration):
            p = write(spec, Path(d) / f"{spec.name}.mcap")
            r = one(p)
            rows.append(r)
            print(f"{spec.name}: {spec.motion:6s} noise {spec.mag_noise_nT:6.2f} nT "
                  f"chi2 {r['chi2']} -> {r['status']}"
                  + ("  [halves doubt]" if r["verdict"] else ""), flush=True)
            p.unlink()
    n = len(rows)
    expect = n * rate
    upper = int(binom.ppf(0.95, n, rate))
    print(f"\nstated false-alarm rate {rate:g} per check: {expect:.1f} of {n} expected, "
          f"at most {upper} at 95 %")
    out = {}
    for key in ("estimate", "final", "verdict"):
        tested = [r[key] for r in rows if r[key] is not None]
        k = int(np.sum(tested))
        out[key] = k
        print(f"  {key:9s}: {k} of {len(tested)} nulls"
              + ("  (above the bound)" if key != "verdict" and k > upper else ""))
    print(f"({time.perf_counter() - t0:.0f} s)")
    if not a.no_record:
        record("halves_null", f"verdicts_naming_the_halves_of_{n}_nulls",
               float(out["verdict"]), "count", reference=expect)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
