"""Waiting for a run paused at the test hook of ``pipeline.atomic`` (kill tests)."""

from __future__ import annotations

import subprocess
import time
from pathlib import Path


def wait_paused(p: subprocess.Popen, hook: Path, limit_s: float = 600) -> str:
    """Wait until the run pauses at its test hook (pipeline.atomic); return the event.

    The limit is only a guard against a hang: the run pauses at a point of its work, never
    at a moment of the clock, so the test does not depend on the speed of the machine.
    """
    paused = hook / "paused"
    t_end = time.monotonic() + limit_s
    while not paused.exists():
        assert p.poll() is None, f"the run ended (status {p.returncode}) before its pause point"
        assert time.monotonic() < t_end, "the run did not reach its pause point"
        time.sleep(0.02)
    return paused.read_text().strip()
