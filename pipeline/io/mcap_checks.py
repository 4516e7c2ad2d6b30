"""Checks of decoded channels.

Sorting and duplicate stamps, non-finite values, quaternion norms, magnetometer magnitude,
spikes, saturation and clock jumps, gaps in the attitude, position fixes lost or missing
altogether: each a ``Problem`` with its count.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from pipeline.core.errors import (
    DataQualityError,
)
from pipeline.core.recording import (
    Problem,
    Role,
)
from pipeline.io.mcap_decode import DecodedColumns
from pipeline.io.mcap_scan import Scan

#: Plausible range of the median field magnitude. The Earth's field is 20,000-70,000 nT; an
#: indoor MEMS sensor near steel reads somewhat off that (the lab data: ~43,800 nT), so only
#: values off by more than a factor of ~20 are refused: those are unit mistakes.
FIELD_MIN_NT = 1_000.0


FIELD_MAX_NT = 200_000.0


#: stamps that differ from the logger's receive time by more than this (beyond the median
#: difference) are taken as clock jumps and dropped
STAMP_JUMP_NS = 3600 * 1_000_000_000


MIN_MAG_SAMPLES = 10


#: magnetometer samples larger than this many times the median field magnitude are damaged
#: values, not readings (a sensor's range is at most some 30 times the Earth's field)
SPIKE_FACTOR = 100.0


#: no magnetometer reads this (1000 T): a value beyond it is damage (chunked reading, which
#: has no median to compare with, drops such samples)
ABSURD_NT = 1e12


MIN_ATTITUDE_SAMPLES = 2


# --------------------------------------------------------------------------- checks
def _sort_dedupe(name: str, dec: DecodedColumns, problems: list[Problem], path: str
                 ) -> DecodedColumns:
    """Drop clock jumps, sort by stamp, drop duplicated stamps; count all in problems."""
    t, log = dec.t_ns, dec.log_time_ns
    if len(t) > 2:
        d = t - log
        # the median lies between the extremes: when they are within STAMP_JUMP_NS of each
        # other no sample can be a jump, and the median (a partition of a copy) is not needed
        if int(d.max()) - int(d.min()) <= STAMP_JUMP_NS:
            jump = np.zeros(0, dtype=bool)
        else:
            jump = np.abs(d - np.median(d)) > STAMP_JUMP_NS
        if jump.any() and not jump.all():
            k = int(jump.sum())
            problems.append(Problem("stamp_jump", f"{name}: {k} samples with stamps more than "
                                    "an hour away from their receive time were dropped", k))
            dec = dec.take(~jump)
            t = dec.t_ns
    dt = np.diff(t)
    if len(dt) and int(dt.min()) > 0:
        return dec  # strictly increasing: nothing to sort, no duplicate
    back = int(np.count_nonzero(dt < 0))
    if back:
        problems.append(Problem("out_of_order", f"{name}: {back} stamps going backwards; "
                                "samples were sorted by stamp", back))
        order = np.argsort(t, kind="stable")
        dec = dec.take(order)
        t = dec.t_ns
        dt = np.diff(t)
    if not len(t) or bool((dt != 0).all()):
        return dec
    dup = np.concatenate([[False], dt == 0])
    if dup.any():
        k = int(dup.sum())
        problems.append(Problem("duplicate", f"{name}: {k} samples with a duplicated stamp "
                                "were dropped (first kept)", k))
        dec = dec.take(~dup)
    return dec


def finite_rows(values: np.ndarray) -> np.ndarray:
    """Return True for each sample (row, or element of a 1-D column) with finite values.

    Also for a channel with no readable message (shape ``(0,)`` or ``(0, k)``), where a
    ``reshape(0, -1)`` would be ambiguous.
    """
    fin = np.isfinite(values)
    return fin if fin.ndim == 1 else fin.all(axis=tuple(range(1, fin.ndim)))


def _drop_nonfinite(name: str, dec: DecodedColumns, problems: list[Problem]) -> DecodedColumns:
    with np.errstate(over="ignore", invalid="ignore"):
        if np.isfinite(np.sum(dec.values)):
            return dec  # a finite sum has no NaN or Inf term (an overflow checks row by row)
    ok = finite_rows(dec.values)
    if ok.all():
        return dec
    k = int((~ok).sum())
    problems.append(Problem("nonfinite", f"{name}: {k} samples with NaN or Inf values were "
                            "dropped", k))
    return dec.take(ok)


def quat_norm(q: np.ndarray) -> np.ndarray:
    """Norm of each quaternion without overflow or underflow (damaged values reach 1e308)."""
    with np.errstate(over="ignore", invalid="ignore"):
        n = np.sqrt(np.einsum("ij,ij->i", q, q))
    if not len(n) or (float(n.min()) > 1e-150 and float(n.max()) < 1e150):
        return n  # the usual case: one pass, no scaling needed (a NaN fails both tests)
    m = np.abs(q).max(axis=1) if len(q) else np.zeros(0)
    safe = np.where(m > 0, m, 1.0)
    return m * np.linalg.norm(q / safe[:, None], axis=1)


def _check_quaternions(name: str, dec: DecodedColumns, problems: list[Problem]) -> DecodedColumns:
    q = dec.values
    n = quat_norm(q)
    lo, hi = (float(n.min()), float(n.max())) if len(n) else (1.0, 1.0)
    zero = n < 1e-6 if not lo >= 1e-6 else None  # (the extremes say when none can be)
    if zero is not None and zero.any():
        k = int(zero.sum())
        problems.append(Problem("zero_quaternion", f"{name}: {k} zero quaternions were "
                                "dropped", k))
        q, n = q[~zero], n[~zero]
        dec = dec.take(~zero, q)
        lo, hi = np.nan, np.nan
    # n - 1 rounds monotonically: no norm is off when neither extreme is
    off = (np.abs(n - 1.0) > 1e-6 if not (hi - 1.0 <= 1e-6 and lo - 1.0 >= -1e-6)
           else None)
    if off is not None and off.any():
        k = int(off.sum())
        problems.append(Problem("non_unit_quaternion", f"{name}: {k} quaternions were not of "
                                f"unit norm (up to {np.abs(n - 1).max():.3g} off) and were "
                                "normalised", k))
    if q.flags.writeable and q.flags.owndata:
        q /= n[:, None]  # the decoder's own array: normalise in place (no second copy)
    else:
        q = q / n[:, None]
    return dataclasses.replace(dec, values=q)


def _check_mag(path: str, name: str, dec: DecodedColumns, problems: list[Problem]
               ) -> DecodedColumns:
    """Refuse unusable magnetometer data; return ``dec`` without samples pinned at a rail.

    A saturated axis reports its extreme value again and again while the true field is
    beyond it; those samples would bias the rotation by degrees, so they are dropped like
    NaN samples (and counted in ``problems``). More than half of the samples pinned is
    refused: what is left cannot be trusted to represent the motion.
    """
    v = dec.values
    if len(v) < MIN_MAG_SAMPLES:
        raise DataQualityError(f"{name}: only {len(v)} usable magnetometer samples",
                               path=path, hint="the recording is too short to calibrate "
                               f"anything (at least {MIN_MAG_SAMPLES} needed)")
    if bool((v[-1] == v[0]).all()) and np.all(v == v[0]):
        raise DataQualityError(f"{name}: every magnetometer sample is identical "
                               f"({v[0].tolist()} nT): the sensor is stuck", path=path,
                               hint="check the sensor and its driver")
    with np.errstate(over="ignore", invalid="ignore"):
        norm_nT = np.sqrt(np.einsum("ij,ij->i", v, v))
    mag_nT = float(np.median(norm_nT))
    if mag_nT > FIELD_MAX_NT or mag_nT < FIELD_MIN_NT:
        if mag_nT > FIELD_MAX_NT:
            hint = ("the values look like microtesla (or gauss) written into a tesla field; "
                    "sensor_msgs/MagneticField must carry tesla (REP-145): convert before "
                    "recording")
        else:
            hint = ("the values look too small for tesla (nanotesla written as tesla?); "
                    "sensor_msgs/MagneticField must carry tesla (REP-145)")
        raise DataQualityError(f"{name}: median field magnitude {mag_nT:.4g} nT is far "
                               "outside the Earth's 20,000-70,000 nT", path=path, hint=hint)
    # a few samples far beyond any field the sensor can see are damaged values (a flipped
    # exponent bit), not readings: dropped like NaN (their squares would overflow the fit)
    with np.errstate(over="ignore"):
        # the largest norm (a NaN fails the test) says when no sample can be wild
        wild = (~(norm_nT <= SPIKE_FACTOR * mag_nT)
                if not float(norm_nT.max()) <= SPIKE_FACTOR * mag_nT else None)
    if wild is not None and wild.any():
        k = int(np.count_nonzero(wild))
        problems.append(Problem("impossible_value", f"{name}: {k} samples more than "
                                f"{SPIKE_FACTOR:g} times the median field magnitude were "
                                "dropped (damaged values)", k))
        dec = DecodedColumns(dec.t_ns[~wild], v[~wild], dec.log_time_ns[~wild], dec.frame_id)
        v = dec.values
        if len(v) < MIN_MAG_SAMPLES:
            raise DataQualityError(f"{name}: only {len(v)} usable magnetometer samples",
                                   path=path, hint="the recording is too short to calibrate "
                                   f"anything (at least {MIN_MAG_SAMPLES} needed)")
    # saturation: many samples pinned at the extreme value of an axis (a rail)
    pinned = np.zeros(len(v), dtype=bool)
    rails: list[str] = []
    # each axis as a contiguous row (one transposing copy; strided columns cost about twice
    # as much); a zero extreme is taken from the column as before, for its printed sign
    cols = np.ascontiguousarray(v.T)
    for ax in range(3):
        c = cols[ax]
        for top, ext in ((True, c.max()), (False, c.min())):
            k = int(np.count_nonzero(c == ext))
            if k >= max(10, len(v) // 100):
                if ext == 0:
                    ext = v[:, ax].max() if top else v[:, ax].min()
                at = v[:, ax] == ext
                pinned |= at
                rails.append(f"{k} at {ext:.6g} nT on axis {'xyz'[ax]}")
    if not pinned.any():
        return dec
    k = int(np.count_nonzero(pinned))
    where = "; ".join(rails)
    if k > len(v) / 2:
        raise DataQualityError(
            f"{name}: {k / len(v):.0%} of the magnetometer samples sit at the extreme value "
            f"of an axis ({where}): the sensor is saturated", path=path,
            hint="reduce the sensor's range setting or move it from magnetic sources")
    problems.append(Problem(
        "saturated", f"{name}: {k} samples pinned at the rail of a saturated sensor ({where}) "
        "were dropped", k))
    keep = ~pinned
    return DecodedColumns(dec.t_ns[keep], v[keep], dec.log_time_ns[keep], dec.frame_id)


def _clean_position(name: str, dec: DecodedColumns, problems: list[Problem], path: str
                    ) -> DecodedColumns:
    """Check a position channel's fixes: clock jumps and duplicates dropped, stamps sorted.

    Rows without a valid fix (the decoder made them NaN: no fix, non-finite or out-of-range
    values) are kept, so that the series keeps the channel's stamps; they are counted in a
    ``position_lost`` problem. A channel without a single valid fix gives no positions: a
    ``no_position_fix`` problem says so (the recording is still usable; positions are only
    needed by the spatial effects of the diagnosis). Nothing here refuses a recording.
    """
    dec = _sort_dedupe(name, dec, problems, path)
    n = len(dec.t_ns)
    lost = int(np.count_nonzero(~finite_rows(dec.values)))
    if n == 0:
        problems.append(Problem("no_position_fix", f"{name}: no readable position message: "
                                "the channel gives no positions", 0))
    elif lost == n:
        problems.append(Problem("no_position_fix", f"{name}: none of its {n:,} messages holds "
                                "a valid fix (status below 0, or non-finite or out-of-range "
                                "latitude, longitude or altitude): the channel gives no "
                                "positions", n))
    elif lost:
        problems.append(Problem("position_lost", f"{name}: {lost:,} of {n:,} messages without "
                                "a valid fix (status below 0, or non-finite or out-of-range "
                                "values) are kept as lost positions (NaN)", lost))
    return dec


def check_channel(role: Role, name: str, dec: DecodedColumns, problems: list[Problem], path: str
           ) -> DecodedColumns:
    """Run the reader's value checks of one channel, in the order :func:`read_recording` needs.

    Non-finite samples dropped; quaternions (attitude) checked and normalised; clock jumps
    dropped, stamps sorted, duplicates dropped; magnetometer data refused when unusable
    (too short, stuck, wrong unit, saturated) and samples pinned at a rail dropped. A
    position channel keeps its lost fixes as NaN rows (:func:`_clean_position`). Every
    repair is appended to ``problems``. :func:`inspect_recording` runs the same checks.

    Raises
    ------
    DataQualityError
        Magnetometer data that cannot be used at all.

    """
    if role is Role.POSITION:
        return _clean_position(name, dec, problems, path)
    dec = _drop_nonfinite(name, dec, problems)
    if role is Role.ATTITUDE:
        dec = _check_quaternions(name, dec, problems)
    dec = _sort_dedupe(name, dec, problems, path)
    if role is Role.MAGNETOMETER:
        dec = _check_mag(path, name, dec, problems)
    return dec


def gap_problems(name: str, t: np.ndarray, problems: list[Problem], min_gap_s: float = 1.0
                  ) -> None:
    """Note the gaps of a channel longer than ``min_gap_s`` (s) and 100 median spacings."""
    if len(t) < 3:
        return
    dt = np.diff(t)
    if float(dt.max()) <= min_gap_s * 1e9:
        return  # no interval above the smaller threshold: the median is not needed
    med = float(np.median(dt))
    big = dt > max(min_gap_s * 1e9, 100 * med)
    if big.any():
        k = int(big.sum())
        longest = float(dt.max()) * 1e-9
        code = "time_jump" if longest > 3600 else "gap"
        limit_s = max(min_gap_s, 100 * med * 1e-9)
        gaps = "gaps" if k > 1 else "gap"
        problems.append(Problem(code, f"{name}: {k} {gaps} longer than {limit_s:.3g} s "
                                f"(longest {longest:.4g} s)", k))


#: an attitude stamp interval longer than this many median intervals has lost samples
ATTITUDE_GAP_FACTOR = 1.5


def attitude_gaps(t_ns: np.ndarray, span_ns: tuple[int, int] | None = None) -> dict | None:
    """Measure the attitude samples missing against the channel's own median rate.

    A gap is a stamp interval longer than :data:`ATTITUDE_GAP_FACTOR` median intervals (a
    motion-capture system losing its markers, an INS dropping messages); it holds
    ``round(interval / median) - 1`` missing samples. With ``span_ns`` (the magnetometer's
    first and last stamp) the stretches of it before the first and after the last attitude
    sample count as missing too: those magnetometer samples have no attitude either.

    Parameters
    ----------
    t_ns : ndarray of int64
        Stamps of the attitude channel, sorted.
    span_ns : (int, int), optional
        First and last magnetometer stamp.

    Returns
    -------
    dict or None
        ``{rate_hz, missing_samples, missing_s, n_gaps, longest_gap_s, gap_samples,
        gap_s, lead_samples, lead_s, trail_samples, trail_s}`` (times in s: ``gap_s`` is
        the time without attitude beyond one median interval per gap), or None when nothing
        is missing or there are fewer than three stamps.

    """
    if len(t_ns) < 3:
        return None
    t = np.asarray(t_ns, dtype=np.int64)
    dt = np.diff(t)
    pos = dt[dt > 0]
    if not len(pos):
        return None
    med = float(np.median(pos))
    g = dt[dt > ATTITUDE_GAP_FACTOR * med].astype(float)
    lead = trail = 0.0
    if span_ns is not None:
        lead = max(0.0, float(t[0] - span_ns[0]))
        trail = max(0.0, float(span_ns[1] - t[-1]))
    out = {
        "rate_hz": 1e9 / med,
        "n_gaps": int(len(g)),
        "longest_gap_s": float(g.max()) * 1e-9 if len(g) else 0.0,
        "gap_samples": int(np.maximum(np.rint(g / med) - 1, 1).sum()),
        "gap_s": float((g - med).sum()) * 1e-9,
        "lead_samples": int(np.rint(lead / med)),
        "lead_s": lead * 1e-9,
        "trail_samples": int(np.rint(trail / med)),
        "trail_s": trail * 1e-9,
    }
    out["missing_samples"] = out["gap_samples"] + out["lead_samples"] + out["trail_samples"]
    out["missing_s"] = out["gap_s"] + (out["lead_s"] if out["lead_samples"] else 0.0) + (
        out["trail_s"] if out["trail_samples"] else 0.0)
    return out if out["missing_samples"] else None


def attitude_gap_problems(name: str, t_ns: np.ndarray, problems: list[Problem],
                           span_ns: tuple[int, int] | None = None) -> None:
    """Add an ``attitude_gaps`` problem when the attitude lost samples (:func:`attitude_gaps`)."""
    g = attitude_gaps(t_ns, span_ns)
    if g is None:
        return
    where = []
    if g["lead_samples"]:
        where.append(f"{g['lead_samples']:,} in the {g['lead_s']:.3f} s before the first "
                     "attitude sample")
    if g["trail_samples"]:
        where.append(f"{g['trail_samples']:,} in the {g['trail_s']:.3f} s after the last")
    if g["n_gaps"]:
        gaps = "gaps" if g["n_gaps"] > 1 else "gap"
        where.append(f"{g['gap_samples']:,} in {g['n_gaps']:,} {gaps} inside "
                     f"(longest {g['longest_gap_s']:.3g} s)")
    problems.append(Problem(
        "attitude_gaps",
        f"{name}: {g['missing_samples']:,} attitude samples missing against its median rate "
        f"{g['rate_hz']:.4g} Hz ({g['missing_s']:.3f} s of the magnetometer's span without "
        f"attitude): " + "; ".join(where), g["missing_samples"]))


#: problem codes of :func:`check_channel` that :func:`inspect_recording` finds itself for every
#: channel (stamps backwards, duplicated), in words that describe the file, not the repair
_INFO_OWN_CODES = frozenset({"out_of_order", "duplicate"})


def value_problems(scan: Scan, role: Role, name: str, dec: DecodedColumns) -> list[Problem]:
    """List what :func:`read_recording` would repair or refuse in one decoded channel."""
    found: list[Problem] = []
    # check_channel may normalise quaternions in place; the caller needs only the stamps, and
    # those are never modified
    try:
        check_channel(role, name, dec, found, scan.path)
    except DataQualityError as exc:
        msg = exc.message + (f" ({exc.hint})" if exc.hint else "")
        found.append(Problem("unusable", msg))
    return [pr for pr in found if pr.code not in _INFO_OWN_CODES]
