"""Where a long recording's field stands out: windows the analysis must see besides its spread.

A long recording is analysed on windows spread evenly over it (:func:`pipeline.run.plan.
windows_ns`). An event that lasts a second (a survey line passing over a buried object, a
vehicle passing) falls between them more often than not: in a 2-hour survey the analysed
windows hold a tenth of the time. The first pass therefore also watches the field's
magnitude at the full rate. ``|B|`` does not depend on the attitude, the misalignment or a
time offset, so it can be judged before anything is fitted: over a few seconds of a line the
Earth's field and a platform's iron give a steady magnitude, and a local source or a passing
vehicle adds a bump. Each bump that stands :data:`PASS_Z` robust sigmas out of the
magnitude's own running mean becomes a candidate; the strongest :data:`PASS_WINDOWS`
candidates, :data:`PASS_WINDOW_S` long each, are read again and analysed with the spread
windows.

The threshold: the high-passed magnitude of white sensor noise is close to Gaussian; at six
robust sigmas a smoothed sample exceeds it with probability 2e-9, about one false candidate
per 10 hours at 200 Hz with the 0.1 s smoothing (7.2e6 samples, about 3.6e5 independent
values). A candidate that is not an event costs only a window more for the diagnosis, which
judges it as it judges any other data; heading changes with a platform's iron (turns at the
ends of lines) also pass the threshold, which is why the candidates are ranked by their
size and capped.
"""

from __future__ import annotations

import numpy as np

#: the magnitude's running mean over this span is its background, s
PASS_BASE_S = 4.0
#: the high-passed magnitude is smoothed over this span before it is judged, s
PASS_SMOOTH_S = 0.1
#: a candidate stands this many robust sigmas out of its background
PASS_Z = 6.0
#: each candidate's window, centred on its peak, s (a pass over an object 2 m away at
#: walking speed lasts about 3 s; the window holds it and the quiet on either side)
PASS_WINDOW_S = 8.0
#: most candidate windows (the strongest); the spread windows are 12
PASS_WINDOWS = 12


def _moving_mean(x: np.ndarray, n: int) -> np.ndarray:
    """Centred running mean over ``n`` samples (``x`` itself where ``n`` < 2)."""
    if n < 2 or len(x) < n:
        return x.copy()
    c = np.concatenate([[0.0], np.cumsum(x)])
    out = np.empty_like(x)
    h = n // 2
    lo = np.clip(np.arange(len(x)) - h, 0, len(x))
    hi = np.clip(np.arange(len(x)) - h + n, 0, len(x))
    out[:] = (c[hi] - c[lo]) / np.maximum(hi - lo, 1)
    return out


class PassFinder:
    """Candidate events in a long recording's magnitude, chunk by chunk, in bounded memory.

    Each magnetometer sample is judged once, in the buffer where it has
    :data:`PASS_BASE_S` / 2 of samples on either side; the buffer's last
    :data:`PASS_BASE_S` carry into the next chunk's. The first and last half spans of the
    recording are not judged.
    """

    def __init__(self) -> None:
        self._t = np.zeros(0, np.int64)
        self._b = np.zeros(0)
        self._n: int | None = None  # samples in PASS_BASE_S
        self._w = 1  # samples in PASS_SMOOTH_S
        self.candidates: list[tuple[float, int]] = []  # (score in sigmas, peak ns)

    def add(self, t_ns: np.ndarray, mag_nT: np.ndarray) -> None:
        """Judge the samples of one chunk (stamps in time order)."""
        b = np.linalg.norm(np.asarray(mag_nT, float), axis=1)
        t = np.asarray(t_ns, np.int64)
        if self._n is None:
            if len(t) < 3:
                return
            dt = float(np.median(np.diff(t))) * 1e-9
            if not dt > 0:
                return
            self._n = max(3, int(round(PASS_BASE_S / dt)))
            self._w = max(1, int(round(PASS_SMOOTH_S / dt)))
        n = self._n
        t = np.concatenate([self._t, t])
        b = np.concatenate([self._b, b])
        keep = min(len(t), n)
        self._t, self._b = t[len(t) - keep:], b[len(b) - keep:]
        if len(t) < n + 1:
            return
        hp = _moving_mean(b - _moving_mean(b, n), self._w)
        judged = slice(n // 2, len(t) - (n - n // 2))
        x, tj = hp[judged], t[judged]
        if not len(x):
            return
        sigma = 1.4826 * float(np.median(np.abs(x - np.median(x))))
        if not sigma > 0:
            return
        z = np.abs(x) / sigma
        above = z > PASS_Z
        if not above.any():
            return
        # one candidate per run of samples above the threshold: its peak
        edges = np.flatnonzero(np.diff(np.concatenate([[0], above.astype(np.int8), [0]])))
        for a, e in zip(edges[::2], edges[1::2], strict=True):
            k = a + int(np.argmax(z[a:e]))
            self.candidates.append((float(z[k]), int(tj[k])))
        # bounded: the strongest few times the windows kept
        if len(self.candidates) > 8 * PASS_WINDOWS:
            self.candidates = sorted(self.candidates, reverse=True)[:4 * PASS_WINDOWS]

    def windows(self, spread_ns: np.ndarray) -> np.ndarray:
        """Return the candidates' windows, (K, 2) int64 ns, half-open, in time order.

        The strongest :data:`PASS_WINDOWS` candidates whose peak no stronger one's window or
        spread window already holds, each :data:`PASS_WINDOW_S` long about its peak;
        overlapping windows are one, and what the spread windows hold is cut out (the
        windows stay disjoint from them and from each other).
        """
        half = int(PASS_WINDOW_S * 0.5e9)
        spread = np.asarray(spread_ns, np.int64).reshape(-1, 2)
        chosen: list[tuple[int, int]] = []
        for _, tp in sorted(self.candidates, reverse=True):
            if len(chosen) >= PASS_WINDOWS:
                break
            held = [(int(a), int(b)) for a, b in spread] + chosen
            if any(a <= tp < b for a, b in held):
                continue
            chosen.append((tp - half, tp + half))
        merged: list[list[int]] = []
        for a, b in sorted(chosen):
            if merged and a <= merged[-1][1]:
                merged[-1][1] = max(merged[-1][1], b)
            else:
                merged.append([a, b])
        out: list[tuple[int, int]] = []
        for a, b in merged:
            for s0, s1 in sorted((int(x), int(y)) for x, y in spread):
                if s1 <= a or b <= s0:
                    continue
                if s0 > a:
                    out.append((a, s0))
                a = max(a, s1)
                if a >= b:
                    break
            if b > a:
                out.append((a, b))
        return np.array(sorted(out), np.int64).reshape(-1, 2)
