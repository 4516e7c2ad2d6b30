"""Diagnosis bench: a challenge of >= 60 recordings, the confusion table, and the speed.

Usage: ``python bench/diagnose.py [N] [SEED] [WORKDIR]``. Prints the confusion table, the
rates the issue asks for (correct effect set on recordings whose effects are >= 5x their
detection threshold, false findings on null recordings, parameter errors within 3 sigma)
and the time to diagnose a 10-minute 200 Hz recording.
"""

from __future__ import annotations

import json
import sys
import tempfile
import time
from pathlib import Path

from pipeline.atomic import write_text_atomic
from pipeline.challenge import confusion_text, generate, score
from pipeline.commands.diagnose import diagnose_file


def run_challenge(n: int, seed: int, work: Path, null_fraction: float = 0.3,
                  name: str = "challenge") -> dict:
    rec_dir = work / name
    t0 = time.perf_counter()
    generate(n, seed, rec_dir, null_fraction=null_fraction)
    t_gen = time.perf_counter() - t0
    res_dir = work / f"{name}_results"
    t0 = time.perf_counter()
    for f in sorted(rec_dir.glob("*.mcap")):
        ctx = diagnose_file(f)
        out = res_dir / f.stem
        out.mkdir(parents=True, exist_ok=True)
        write_text_atomic(out / "diagnosis.json", json.dumps(ctx.diagnosis.to_dict(), indent=1))
    t_diag = time.perf_counter() - t0
    r = score(rec_dir, res_dir)
    print(f"generated {n} recordings in {t_gen:.0f} s, diagnosed in {t_diag:.0f} s "
          f"({t_diag / n:.1f} s each)")
    print(confusion_text(r))
    for row in r["rows"]:
        if not row["exact"]:
            print(f"  miss {row['recording']}: true {row['true']} found {row['found']} "
                  f"strength {({k: round(v, 1) for k, v in row['strength'].items()})}")
    p3 = r["param_within_3sigma"]
    print(f"exact effect set: {r['exact']}/{r['n']}")
    print(f"effects >= 5x threshold, correct set: {r['strong_exact']}/{r['strong_n']}")
    print(f"null recordings with false findings: {r['null_false']}/{r['null_n']}")
    print(f"parameter errors within 3 sigma: "
          f"{'n/a' if p3 is None else f'{100 * p3:.0f} %'} of {r['n_param_checks']}")
    return r


def time_long(work: Path) -> float:
    import numpy as np

    from pipeline.challenge import _scenario
    from pipeline.simulate import scenario_from_dict, simulate, write_simulated

    scen = _scenario(np.random.default_rng(5), {"hard_iron": {"offset_nT": [40.0, -20.0, 10.0]},
                                                 "time_offset": {"time_offset_s": 0.003}}, 0)
    scen["timing"].update(duration_s=600.0, mag_rate_hz=200.0, attitude_rate_hz=200.0)
    path = write_simulated(simulate(scenario_from_dict(scen)), work / "long.mcap")
    t0 = time.perf_counter()
    ctx = diagnose_file(path)
    dt = time.perf_counter() - t0
    print(f"10-minute 200 Hz recording ({len(ctx.recording.mag)} samples): read + align + "
          f"estimate + diagnose in {dt:.1f} s; found {sorted(ctx.diagnosis.effects)}")
    return dt


def main() -> int:
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 60
    seed = int(sys.argv[2]) if len(sys.argv) > 2 else 2026
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(sys.argv[3]) if len(sys.argv) > 3 else Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        time_long(work)
        run_challenge(n, seed, work)
        # extra null recordings: the false-alarm rate needs more than the challenge's share
        print("\nnull-only challenge (false alarms):")
        r = run_challenge(n // 2, seed + 1, work, null_fraction=1.0, name="nulls")
        print(f"false findings on null recordings: {r['null_false']}/{r['null_n']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
