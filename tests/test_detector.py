"""The transient detector's false-alarm rate on noise alone, and its power on a short anomaly.

``stages.diagnose.search.scan_windows`` opens a window where the residual stands out by more
than the noise model allows. The target: at most one false event per 10 hours of noise-only
data (``SCAN_FALSE_ALARM`` per scan). Ten hours of 5-minute 200 Hz surveys, decimated as the
diagnosis does (every 5th sample, at most 12000), of white noise and of white noise plus
attitude noise drawn at 20 Hz and interpolated (correlated over 1/20 s, in the plane normal
to the field), open at most one window in all. A 1 s anomaly of 20 times the residual RMS is
found where it is. ``bench/false_alarm.py`` measures more noise models and recording types
over 100 hours each."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stages.diagnose.result import DiagnoseConfig
from stages.diagnose.search import scan_windows

RATE_HZ = 200.0
SECONDS = 300.0
SIGMA_NT = 20.0
FIELD_NT = 50_000.0


def _times() -> tuple[np.ndarray, int]:
    """Full-rate sample times of a 5-minute survey and the diagnosis' decimation stride."""
    n = int(SECONDS * RATE_HZ)
    return np.arange(n) / RATE_HZ, math.ceil(n / DiagnoseConfig().max_samples)


def _noise(rng: np.random.Generator, t: np.ndarray, attitude_ratio: float) -> np.ndarray:
    """White noise (n, 3), plus interpolated 20 Hz attitude noise of that RMS ratio."""
    r = SIGMA_NT * rng.normal(size=(t.size, 3))
    if attitude_ratio > 0:
        knots = np.arange(-0.05, t[-1] + 0.1, 0.05)
        # rotation-vector noise crossed with the field: per component RMS sigma * B * sqrt(2/3)
        sigma = attitude_ratio * SIGMA_NT / (FIELD_NT * math.sqrt(2.0 / 3.0))
        dth = sigma * rng.normal(size=(knots.size, 3))
        d = np.stack([np.interp(t, knots, dth[:, j]) for j in range(3)], axis=1)
        u = rng.normal(size=3)
        r += np.cross(d, FIELD_NT * u / np.linalg.norm(u))
    return r


@pytest.mark.parametrize("attitude_ratio", [0.0, 3.0])
def test_ten_hours_of_noise_open_at_most_one_window(attitude_ratio):
    t, k = _times()
    cfg = DiagnoseConfig()
    n_rec = int(10 * 3600 / SECONDS)
    opened = 0
    for i in range(n_rec):
        rng = np.random.default_rng([11, i])
        opened += len(scan_windows(_noise(rng, t, attitude_ratio)[::k], t[::k], cfg))
    assert opened <= 1


@pytest.mark.parametrize("attitude_ratio", [0.0, 3.0])
def test_a_one_second_anomaly_is_found_where_it_is(attitude_ratio):
    t, k = _times()
    rng = np.random.default_rng(5)
    r = _noise(rng, t, attitude_ratio)
    rms = float(np.sqrt(np.mean(r**2)))
    t0 = 137.3  # s
    fwhm = 1.0  # s
    bump = np.exp(-0.5 * ((t - t0) / (fwhm / (2.0 * math.sqrt(2.0 * math.log(2.0))))) ** 2)
    r += 20.0 * rms * bump[:, None] * np.array([0.6, -0.48, 0.64])  # unit direction
    wins = scan_windows(r[::k], t[::k], DiagnoseConfig())
    assert len(wins) == 1, wins
    a, b = wins[0]
    assert a - 1.0 <= t0 <= b + 1.0, wins
    assert abs(0.5 * (a + b) - t0) <= 1.0, wins
