"""Waiting for a run paused at the test hook of ``pipeline.core.atomic`` (kill tests)."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from collections.abc import Callable
from pathlib import Path


def wait_paused(p: subprocess.Popen, hook: Path, limit_s: float = 600) -> str:
    """Wait until the run pauses at its test hook (pipeline.core.atomic); return the event.

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


def kill_paused_worker(p: subprocess.Popen, hook: Path, is_worker: Callable[[int], bool],
                       timeout_s: float = 900) -> str:
    """SIGKILL the worker paused at the hook, let the run finish; return the run's stderr.

    ``is_worker(pid)`` is asserted first: the process that paused must be a worker, not the
    command. The run is killed with its whole session if it does not end by itself.
    """
    try:
        wait_paused(p, hook)
        pid = int((hook / "pid").read_text())
        assert is_worker(pid), f"process {pid} paused, not a worker"
        os.kill(pid, signal.SIGKILL)
        _, err = p.communicate(timeout=timeout_s)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
    return err
