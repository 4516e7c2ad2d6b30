"""Residual against turn rate on the real lab recordings: the magnetometer's conversion times.

Issue "the residual grows with the turn rate on every fast real recording". For each
``../shared/data/real/lab_0*.mcap`` (skipped cleanly when the folder is absent) the final
model of ``diagnose`` (:func:`pipeline.app.commands.diagnose.diagnose_file`) is taken as it
is, and this prints one table: rows are models, columns are turn-rate bins ``|omega|``
(rad/s, the angular velocity of the attitude interpolator at ``t - tau``), cells the residual
RMS in nT per component (``sqrt(mean(e_x^2 + e_y^2 + e_z^2) / 3)``), with the sample count of
each bin on the first line:

- ``final, in-sample``: the final model's residual, every valid message at its own stamp
  (what ``restore`` left before it timed the conversions as the diagnosis' handling does;
  with the anchored handling, restore leaves the ``anchor re-stamp`` row in-sample);
- ``held-out, stamps``: the same stamps, held out (below): the reference for the rows under it;
- ``held-out, anchor re-stamp``: each conversion sensed at the time the anchor rule below
  gives (no parameter);
- ``held-out, + pattern lateness``: the anchor rule plus one fitted lateness per local run
  pattern (about 14 classes with at least 500 conversions each): what the run pattern still
  tells beyond the anchor rule.

Held out: the recording is cut into one-second blocks, block ``b`` belongs to fold ``b % 5``;
the linearised core parameters (rotation, field, offset, soft iron, time offset: the columns
of :func:`pipeline.model.forward.jacobian`) and the candidate's own parameters are fitted on
four folds and predict the fifth. Every row uses the same messages and bins.

Anchor rule (the model the bench supports): the magnetometer converts at about 202.4 Hz and
its 285.714 Hz messages repeat a conversion in runs of 1 or 3 (rarely 5) messages. Measured
against the attitude, a run of three is sensed at its MIDDLE message (not at its first copy),
and the conversions between two such runs are evenly spaced in time between their middles.
So the sensing time of conversion ``k`` is ``t_k = interp(k, k_a, c_a)``: linear interpolation
in the conversion index ``k`` between the anchors ``a`` (runs of at least 3 messages) at their
centre stamps ``c_a``; the conversion time is then used for every message of its run, and
``tau`` stays the model's constant time offset on top.

Run: ``.venv/bin/python bench/turn_rate.py [lab_03 ...] [--distinct]`` (``--distinct``: one
row per conversion, the repeats left out). About 0.5-2 minutes per recording (the diagnosis).
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT.parent / "shared" / "data" / "real"
sys.path.insert(0, str(ROOT))

from pipeline.model import forward as fw  # noqa: E402
from pipeline.model.attitude import AttitudeInterpolator  # noqa: E402
from pipeline.model.sample_hold import repeated  # noqa: E402

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
B8 = NDArray[np.bool_]

#: turn-rate bin edges, rad/s
BINS = (0.0, 0.5, 1.0, 2.0, 4.0, 8.0, np.inf)
#: interleaved folds of one-second blocks
N_FOLDS = 5
BLOCK_S = 1.0
#: a run of at least this many identical messages is an anchor of the anchor rule
ANCHOR_RUN = 3
#: a run pattern needs this many conversions to get its own lateness
MIN_PATTERN = 500


@dataclass(frozen=True)
class Runs:
    """Runs of identical magnetometer messages (one run = one conversion)."""

    start: I64  # first message of each run, (K,)
    length: I64  # messages in each run, (K,)

    @classmethod
    def of(cls, mag_nT: F64) -> Runs:
        """Find the runs of a magnetometer series (N, 3)."""
        start = np.flatnonzero(~repeated(mag_nT))
        return cls(start, np.diff(np.r_[start, len(mag_nT)]))

    def per_message(self, x: NDArray) -> NDArray:
        """Spread a per-conversion array (K,) over the messages (N,)."""
        return np.repeat(x, self.length)


def anchor_times_ns(t_ns: I64, runs: Runs) -> I64:
    """Sensing time of every message's conversion by the anchor rule (module docstring), (N,).

    Conversions before the first or after the last anchor keep their run's centre stamp.
    """
    centre = (t_ns[runs.start] + t_ns[runs.start + runs.length - 1]) / 2.0  # (K,) float ns
    rel = centre - float(t_ns[0])
    k = np.arange(len(runs.start), dtype=float)
    anchors = np.flatnonzero(runs.length >= ANCHOR_RUN)
    sensed = rel.copy()
    if len(anchors) >= 2:
        inside = (k >= anchors[0]) & (k <= anchors[-1])
        sensed[inside] = np.interp(k[inside], anchors.astype(float), rel[anchors])
    return int(t_ns[0]) + runs.per_message(np.round(sensed).astype(np.int64))


def pattern_classes(runs: Runs) -> I64:
    """Class of every message's conversion by its local run pattern, (N,).

    The key is (conversions in the previous, the current and the next span between anchors,
    the conversion's place in its span): about 14 patterns cover 87 % of the conversions.
    """
    k = np.arange(len(runs.start))
    anchor = runs.length >= ANCHOR_RUN
    last = np.maximum.accumulate(np.where(anchor, k, -(10**9)))
    ka = np.flatnonzero(anchor)
    span = np.diff(ka)
    cur = np.searchsorted(ka, k, side="right") - 1

    def span_at(j: I64) -> I64:
        ok = (j >= 0) & (j < len(span))
        return np.where(ok, span[np.clip(j, 0, max(len(span) - 1, 0))], -1)

    key = np.stack([span_at(cur - 1), span_at(cur), span_at(cur + 1), k - last], axis=1)
    _, cls = np.unique(key, axis=0, return_inverse=True)
    return runs.per_message(np.asarray(cls).ravel())


def heldout(res: F64, J: F64, extra: F64 | None, sel: B8, fold: I64) -> F64:
    """Held-out residual (N, 3): core columns ``J`` (N, 3, P) and ``extra`` fitted per fold."""
    X = J if extra is None else np.concatenate([J, extra], axis=2)
    out = np.full_like(res, np.nan)
    for f in range(N_FOLDS):
        train, test = sel & (fold != f), sel & (fold == f)
        A = X[train].reshape(-1, X.shape[2])
        scale = np.sqrt(np.sum(A * A, axis=0))
        scale[scale == 0] = 1.0
        coef = np.linalg.lstsq(A / scale, res[train].reshape(-1), rcond=None)[0] / scale
        out[test] = res[test] - np.einsum("nij,j->ni", X[test], coef)
    return out


def binned_rms(e: F64, w: F64, sel: B8) -> list[float]:
    """RMS per component in each turn-rate bin, then over all of ``sel``."""
    out = []
    for lo, hi in zip(BINS[:-1], BINS[1:], strict=True):
        s = sel & (w >= lo) & (w < hi)
        out.append(float(np.sqrt(np.mean(e[s] ** 2))) if s.sum() >= 20 else float("nan"))
    out.append(float(np.sqrt(np.mean(e[sel] ** 2))))
    return out


def _row(label: str, cells: list[float]) -> str:
    return f"  {label:34s}" + "".join(f"{c:9.0f}" for c in cells)


def one(name: str, distinct: bool) -> None:
    """Print the table of one recording."""
    from pipeline.app.commands.diagnose import diagnose_file

    t_start = time.perf_counter()
    ctx = diagnose_file(REAL / f"{name}.mcap")
    rec, cal = ctx.recording, ctx.calibration
    model = cal.forward_model()
    it = AttitudeInterpolator.of(rec.attitude)
    t = np.asarray(rec.mag.t_ns, dtype=np.int64)
    y = np.asarray(rec.mag.values, dtype=float)
    t0 = int(t[0])
    kw = {"t0_ns": t0, "position": rec.position}

    ev = fw.evaluate(model, t, it, **kw)
    res = y - ev.y_nT  # the final model's residual at the stamps (as restore computes it)
    w = np.linalg.norm(ev.omega_body_rad_s, axis=1)
    J = fw.jacobian(model, t, it, **kw)  # (N, 3, 16), column 15: tau

    runs = Runs.of(y)
    t_sensed = anchor_times_ns(t, runs)
    y_anchor = fw.evaluate(model, t_sensed, it, **kw).y_nT
    res_anchor = y - y_anchor

    cls = pattern_classes(runs)
    first = np.zeros(len(t), dtype=bool)
    first[runs.start] = True
    counts = np.bincount(cls[first])
    big = np.flatnonzero(counts >= MIN_PATTERN)
    g = J[:, :, 15]  # d y / d tau: a lateness l adds l * g to the residual
    X_pattern = np.stack([g * (cls == c)[:, None] for c in big], axis=2)

    sel = ev.valid & np.all(np.isfinite(y_anchor), axis=1)
    if distinct:
        sel &= first
    fold = (np.floor((t - t0) * 1e-9 / BLOCK_S).astype(np.int64)) % N_FOLDS

    lat = (t - t_sensed) * 1e-9
    print(
        f"## {name}  ({time.perf_counter() - t_start:.0f} s; tau {model.time_offset_s * 1e3:.2f}"
        f" ms; {len(runs.start)} conversions in {len(t)} messages, anchor-rule lateness "
        f"{np.sqrt(np.mean(lat**2)) * 1e3:.2f} ms RMS beyond tau"
        f"{'; distinct conversions only' if distinct else ''})"
    )
    edges = [
        f"{lo:g}-{hi:g}" if np.isfinite(hi) else f">{lo:g}"
        for lo, hi in zip(BINS[:-1], BINS[1:], strict=True)
    ]
    print(f"  {'|omega| rad/s':34s}" + "".join(f"{e:>9s}" for e in edges) + f"{'all':>9s}")
    n_bin = [
        int(np.sum(sel & (w >= lo) & (w < hi))) for lo, hi in zip(BINS[:-1], BINS[1:], strict=True)
    ]
    print(f"  {'samples':34s}" + "".join(f"{n:9d}" for n in n_bin) + f"{int(sel.sum()):9d}")
    print(_row("final, in-sample", binned_rms(res, w, sel)))
    print(_row("held-out, stamps", binned_rms(heldout(res, J, None, sel, fold), w, sel)))
    print(
        _row(
            "held-out, anchor re-stamp", binned_rms(heldout(res_anchor, J, None, sel, fold), w, sel)
        )
    )
    print(
        _row(
            f"held-out, + pattern lateness ({len(big)})",
            binned_rms(heldout(res_anchor, J, X_pattern, sel, fold), w, sel),
        )
    )
    print()


def main(argv: list[str]) -> int:
    """Run the recordings named (default: all five)."""
    if not REAL.is_dir():
        print(f"real data folder absent ({REAL}); nothing to do")
        return 0
    distinct = "--distinct" in argv
    names = [a for a in argv if not a.startswith("--")] or sorted(
        p.stem for p in REAL.glob("lab_*.mcap")
    )
    for name in names:
        one(name, distinct)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
