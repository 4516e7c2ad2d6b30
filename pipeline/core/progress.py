"""Progress of long work: per stage, with an estimate of the time left.

On a terminal one line is redrawn; elsewhere (a log file, a pipe, CI) each stage of each
recording is told once, on a line of its own.

More in docs/modules.md, ``pipeline.core.progress``.
"""

from __future__ import annotations

import json
import os
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TextIO

from pipeline.core.style import terminal_width, wrap

#: folder where worker processes write their progress files (set by the parent command)
ENV_DIR = "MAGALIGN_PROGRESS_DIR"
#: ``auto`` (default: the redrawn line on a terminal, else one line per stage of work that
#: lasts), ``always`` (the redrawn line), ``lines`` (one line per stage, from the start) or
#: ``never``
ENV_MODE = "MAGALIGN_PROGRESS"

#: the redrawn line on a terminal (:func:`mode_for`)
LINE = "line"
#: one plain line per stage (no carriage return, no colour): a log keeps every line
LOG = "log"
#: nothing
OFF = "off"

#: In ``auto`` mode without a terminal, the stage lines of a command wait this long (seconds)
#: and are not printed if it ends first: a command that refuses its input (one error line,
#: exit 2) or ends at once prints nothing else, while a long one logs every stage, those of
#: its first seconds included.
LOG_AFTER_S = 5.0

#: the progress line's width when the terminal does not say (the classic 80 columns, less
#: one: a line as wide as the terminal wraps on some)
DEFAULT_WIDTH = 79
#: the widest progress line, however wide the terminal
MAX_WIDTH = 99

#: Typical relative wall time of each stage (class names; measured on the demo campaign and
#: the lab recordings). Stages not listed weigh 1.
STAGE_WEIGHTS: dict[str, float] = {
    "Ingest": 4.0,
    "TurntableAttitude": 1.0,
    "Resample": 1.0,
    "SegmentMotion": 1.0,
    "Estimate": 4.0,
    "EstimateFromSums": 1.0,
    "LoadCalibration": 0.2,
    "RequireObservable": 0.1,
    "Diagnose": 40.0,
    "Judge": 2.0,
    "Restore": 2.0,
    "Metrics": 2.0,
    "WriteResults": 0.3,
    "WriteCorrectedMcap": 6.0,
    "WriteRerun": 4.0,
    "Report": 8.0,
}

#: plain names of the stages, as the user reads them on the progress line
STAGE_LABELS: dict[str, str] = {
    "Ingest": "reading",
    "TurntableAttitude": "turntable attitude",
    "Resample": "aligning",
    "SegmentMotion": "segmenting",
    "Estimate": "estimating",
    "EstimateFromSums": "estimating",
    "LoadCalibration": "loading calibration",
    "RequireObservable": "checking",
    "Diagnose": "diagnosing",
    "Judge": "judging",
    "Restore": "restoring",
    "Metrics": "metrics",
    "WriteResults": "writing results",
    "WriteCorrectedMcap": "writing corrected MCAP",
    "WriteSurvey": "writing targets and grid",
    "WriteRerun": "writing rerun recording",
    "Report": "writing report",
    "Exclude": "leaving out windows",
    "NoteExclusions": "noting what was left out",
    "CheckApplied": "checking the calibration",
    "AxisTiltNote": "turntable axis tilt",
}


def weight(name: str) -> float:
    """Relative cost of the stage ``name`` (1 when unknown)."""
    return STAGE_WEIGHTS.get(name, 1.0)


def label(name: str) -> str:
    """Plain name of the stage ``name``."""
    return STAGE_LABELS.get(name, name)


# ----------------------------------------------------------------------------- worker side

class _RunState:
    """What one recording's run has done so far (plain JSON)."""

    def __init__(self, name: str, stages: list[str] | None = None):
        self.name = name
        self.stages: list[str] = list(stages or [])
        self.index = -1
        self.detail = ""
        self.fraction = 0.0  # inside the current stage
        self.started = time.time()
        self.stage_started = self.started
        self.timings: dict[str, float] = {}
        # every stage started, in order, as [index, name, wall time]: a display that polls
        # (a worker's file) may miss a short stage in the current state alone
        self.history: list[list[Any]] = []

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "stages": self.stages, "index": self.index,
                "detail": self.detail, "fraction": self.fraction, "started": self.started,
                "stage_started": self.stage_started, "timings": self.timings,
                "history": list(self.history)}


class _ProgressSink:
    """Receives a run's progress; subclasses publish it."""

    def __init__(self, name: str):
        self.state = _RunState(name)

    def publish(self, force: bool) -> None:  # pragma: no cover - overridden
        """Make the state visible to the display."""

    def stage(self, name: str, index: int, total: int, stages: list[str] | None = None) -> None:
        """Start stage ``name`` (``index`` of ``total``)."""
        st = self.state
        now = time.time()
        if 0 <= st.index < len(st.stages):
            prev = st.stages[st.index]
            st.timings[prev] = st.timings.get(prev, 0.0) + now - st.stage_started
        if stages is not None:
            st.stages = list(stages)
        elif len(st.stages) != total:
            st.stages = (st.stages + [""] * total)[:total]
        if 0 <= index < len(st.stages):
            st.stages[index] = name
        st.index, st.detail, st.fraction, st.stage_started = index, "", 0.0, now
        if name:
            st.history.append([index, name, now])
        self.publish(True)

    def finish(self) -> None:
        """End the run."""
        self.stage("", len(self.state.stages), len(self.state.stages))

    def detail(self, text: str, done: float, total: float | None) -> None:
        """Progress inside the current stage."""
        self.state.detail = text
        if total:
            self.state.fraction = max(0.0, min(1.0, done / total))
        self.publish(False)


class FileSink(_ProgressSink):
    """Writes the state to ``folder/<pid>-<name>.json`` (atomically, at most 5 times a second).

    Parameters
    ----------
    folder : path
        The folder the display polls.
    name : str
        The recording's name.

    """

    def __init__(self, folder: str | Path, name: str):
        super().__init__(name)
        self.path = Path(folder) / f"{os.getpid()}-{abs(hash(name)) % 10**8}.json"
        self._last = 0.0

    def publish(self, force: bool) -> None:
        """Write the state file (never raises: progress must not break the work)."""
        now = time.monotonic()
        if not force and now - self._last < 0.2:
            return
        self._last = now
        try:
            tmp = self.path.with_suffix(".tmp")
            tmp.write_text(json.dumps(self.state.to_dict()))
            os.replace(tmp, self.path)
        except OSError:
            pass


class DirectSink(_ProgressSink):
    """Hands the state to ``callback(state_dict)`` in this process."""

    def __init__(self, name: str, callback: Callable[[dict[str, Any]], None]):
        super().__init__(name)
        self.callback = callback

    def publish(self, force: bool) -> None:
        """Call the callback with a copy of the state."""
        self.callback(self.state.to_dict())


_local = threading.local()


def current() -> _ProgressSink | None:
    """Return the sink of this thread, or None."""
    return getattr(_local, "sink", None)


@contextmanager
def use_sink(sink: _ProgressSink | None) -> Iterator[_ProgressSink | None]:
    """Install ``sink`` for the calls to :func:`stage` and :func:`detail` inside the block."""
    old = current()
    _local.sink = sink
    try:
        yield sink
    finally:
        if sink is not None:
            sink.finish()
        _local.sink = old


def sink_from_env(name: str) -> _ProgressSink | None:
    """Return a :class:`FileSink` when the parent asked for progress files (:data:`ENV_DIR`)."""
    folder = os.environ.get(ENV_DIR)
    if not folder or not Path(folder).is_dir():
        return None
    return FileSink(folder, name)


def stage(name: str, index: int, total: int, stages: list[str] | None = None) -> None:
    """Tell the current sink (if any) that stage ``name`` starts (``index`` of ``total``).

    ``stages``, when given, names every stage of the run (for the estimate of time left).
    """
    s = current()
    if s is not None:
        s.stage(name, index, total, stages)


def detail(text: str, done: float = 0.0, total: float | None = None) -> None:
    """Tell the current sink (if any) how far the current stage is (``done`` of ``total``)."""
    s = current()
    if s is not None:
        s.detail(text, done, total)


# ----------------------------------------------------------------------------- display side

def _asked() -> str:
    """Return :data:`ENV_MODE` as one of ``auto``, ``always``, ``lines``, ``never``."""
    mode = os.environ.get(ENV_MODE, "auto").strip().lower()
    if mode in ("never", "0", "off", "no"):
        return "never"
    if mode in ("always", "1", "on", "yes"):
        return "always"
    return "lines" if mode in ("lines", "log") else "auto"


def mode_for(stream: TextIO, disable: bool = False) -> str:
    """How to show progress on ``stream``: :data:`LINE`, :data:`LOG` or :data:`OFF`.

    The redrawn line on a terminal, one plain line per stage elsewhere (a log file, a
    pipe); :data:`ENV_MODE` decides first, and ``disable`` (``--no-progress``) before it.
    """
    asked = "never" if disable else _asked()
    if asked == "never":
        return OFF
    if asked == "always":
        return LINE
    if asked == "lines":
        return LOG
    try:
        tty = bool(stream.isatty())
    except (AttributeError, ValueError):
        tty = False
    return LINE if tty else LOG


def enabled_for(stream: TextIO, disable: bool = False) -> bool:
    """Whether to draw the redrawn progress line on ``stream`` (:func:`mode_for` is LINE)."""
    return mode_for(stream, disable) == LINE


def display_for(total: int, title: str, *, stream: TextIO | None = None,
                disable: bool = False, folder: str | Path | None = None) -> ProgressDisplay:
    """Return the :class:`ProgressDisplay` a command shows on ``stream`` (stderr by default).

    Its mode is :func:`mode_for`; the stage lines of a log wait :data:`LOG_AFTER_S` unless
    :data:`ENV_MODE` asks for ``lines``.
    """
    stream = stream if stream is not None else sys.stderr
    mode = mode_for(stream, disable)
    return ProgressDisplay(total, title, stream=stream, enabled=mode != OFF, log=mode == LOG,
                           log_after_s=0.0 if _asked() == "lines" else LOG_AFTER_S,
                           folder=folder)


def fmt_duration(s: float) -> str:
    """``m:ss`` (or ``h:mm:ss``) of ``s`` seconds."""
    s = max(0, int(round(s)))
    h, rem = divmod(s, 3600)
    m, sec = divmod(rem, 60)
    return f"{h}:{m:02d}:{sec:02d}" if h else f"{m}:{sec:02d}"


def run_fraction(state: dict[str, Any]) -> float:
    """Fraction of one run done, from the stage weights (0..1)."""
    stages = state.get("stages") or []
    if not stages:
        return 0.0
    w = [weight(s) if s else 1.0 for s in stages]
    i = int(state.get("index", -1))
    if i >= len(stages):
        return 1.0
    if i < 0:
        return 0.0
    done = sum(w[:i]) + w[i] * float(state.get("fraction") or 0.0)
    return max(0.0, min(1.0, done / sum(w)))


class ProgressDisplay:
    """Progress on stderr: one redrawn line on a terminal, else a log of the stages.

    The line tells the recordings done, the current stage, the time elapsed and left; the
    log has one plain line per stage of each recording and one when it ends.

    Parameters
    ----------
    total : int
        Recordings (or runs) to do.
    title : str
        First word of the line.
    stream : text stream
        Where to draw (stderr).
    enabled : bool
        Show anything at all (see :func:`mode_for`).
    log : bool
        One plain line per stage of each recording (:meth:`log_lines`), and one when it
        ends, rather than the redrawn line: for a stream that keeps every line.
    log_after_s : float
        The log's lines wait this long after the display started; if the display is
        closed first, they are never printed (:data:`LOG_AFTER_S`).
    folder : path, optional
        Poll the progress files of worker processes here.
    interval_s : float
        Redraw (or poll) period.

    """

    def __init__(self, total: int, title: str = "magalign", *, stream: TextIO | None = None,
                 enabled: bool = True, log: bool = False, log_after_s: float = 0.0,
                 folder: str | Path | None = None, interval_s: float = 0.25):
        self.total = max(1, int(total))
        self.title = title
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = enabled
        self.folder = Path(folder) if folder is not None else None
        self.interval_s = interval_s
        self.done = 0
        self.started = time.time()
        self._direct: dict[str, dict[str, Any]] = {}
        self._lock = threading.Lock()
        self._draw_lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._width = 0
        self._shown = 0.0  # the largest share done drawn so far
        self.log = log
        self.log_after_s = log_after_s
        self._logged: dict[str, int] = {}  # run name -> stages of its history printed
        # (wall time, name, status, runs done) of the run ends not printed yet
        self._held: list[tuple[float, str, str, int]] = []

    def __enter__(self) -> ProgressDisplay:
        if self.enabled:
            if not self.log:
                self.draw()  # at once: the user sees that work started
            self._thread = threading.Thread(target=self._loop, daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def update(self, state: dict[str, Any]) -> None:
        """Take the state of an in-process run (:class:`DirectSink` callback).

        A new stage is drawn at once (not only at the next redraw), so that even a short
        stage shows.
        """
        with self._lock:
            old = self._direct.get(state["name"])
            self._direct[state["name"]] = state
        if self.enabled and (old is None or old.get("index") != state.get("index")):
            try:
                self.draw()
            except (OSError, ValueError):
                pass

    def run_done(self, name: str, status: str = "ok") -> None:
        """One recording (run) finished, with ``status`` (``ok``, ``reused``, ``failed``).

        In a log, its stages not printed yet are printed, then a line saying it ended.
        """
        if self.enabled and self.log:
            with self._draw_lock:
                self._log_new()
                with self._lock:
                    done = self.done + 1
                self._held.append((time.time(), name, status, done))
                self._log_new()
        with self._lock:
            self.done += 1
            self._direct.pop(name, None)

    def _all_states(self) -> list[dict[str, Any]]:
        """Return the states of the runs here and in the progress files, finished too."""
        with self._lock:
            states = list(self._direct.values())
        if self.folder is not None and self.folder.is_dir():
            for f in sorted(self.folder.glob("*.json")):
                try:
                    states.append(json.loads(f.read_text()))
                except (OSError, ValueError):
                    continue
        return states

    def _states(self) -> list[dict[str, Any]]:
        return [s for s in self._all_states() if run_fraction(s) < 1.0]

    def log_lines(self, now: float | None = None) -> list[str]:
        """Return the log's lines not printed yet, oldest first, and count them as printed.

        One line per stage started, ``magalign: NAME: STAGE (k/n), m:ss elapsed``, and one
        per run ended; wrapped to the terminal's width (80 columns when unknown) between
        words, so no number is cut. Nothing (and nothing counted) before
        ``log_after_s``: the lines held until then are all given at once.
        """
        now = time.time() if now is None else now
        if now - self.started < self.log_after_s:
            return []
        events: list[tuple[float, str]] = []
        for st in self._all_states():
            name = str(st.get("name", ""))
            history = st.get("history") or []
            total = len(st.get("stages") or [])
            for index, stage_name, t in history[self._logged.get(name, 0):]:
                count = f" ({index + 1}/{total})" if 0 <= index < total else ""
                events.append((float(t), f"{name}: {label(stage_name)}{count}, "
                                         f"{fmt_duration(float(t) - self.started)} elapsed"))
            self._logged[name] = len(history)
        events += [(t, self._end_line(name, status, done, t))
                   for t, name, status, done in self._held]
        self._held = []
        events.sort(key=lambda e: e[0])  # a stable sort: each run's stages stay in order
        texts = [text for _, text in events]
        prefix = self.title.split(" ")[0] + ": "
        width = terminal_width()
        return [line for text in texts for line in wrap(prefix + text, "", "    ", width)]

    def _end_line(self, name: str, status: str, done: int, t: float) -> str:
        """Return the log's text for run ``name`` ending at wall time ``t`` (no prefix)."""
        word = {"ok": "done", "reused": "earlier results reused"}.get(status, status)
        of = f" ({done} of {self.total} recordings)" if self.total > 1 else ""
        return f"{name}: {word}{of}, {fmt_duration(t - self.started)} elapsed"

    def _log_new(self) -> None:
        """Print the log's new lines (the caller holds the draw lock)."""
        lines = self.log_lines()
        if lines:
            self.stream.write("".join(line + "\n" for line in lines))
            self.stream.flush()

    def line(self, now: float | None = None, width: int = DEFAULT_WIDTH) -> str:
        """Return the progress line as it would be drawn now, at most ``width`` characters.

        The percentage, the elapsed time and the estimate of the time left always show in
        full: when the line is too long, the recording's name and stage are shortened
        (ending in ``...``), then the title is left out.
        """
        now = time.time() if now is None else now
        states = self._states()
        with self._lock:
            done = self.done
        frac = min(1.0, (done + sum(run_fraction(s) for s in states)) / self.total)
        # progress only moves forward: a run whose stage list grows (or a worker's file read
        # between two stages) would otherwise draw a smaller share done than before
        with self._lock:
            frac = self._shown = max(frac, self._shown)
        elapsed = now - self.started
        head = [self.title]
        if self.total > 1:
            head.append(f"[{done}/{self.total}]")
        where = ""
        if states:
            s = max(states, key=lambda x: x.get("stage_started", 0))
            stages = s.get("stages") or []
            i = int(s.get("index", -1))
            where = s.get("name", "")
            if 0 <= i < len(stages):
                what = f"{label(stages[i])} ({i + 1}/{len(stages)})"
                if s.get("detail"):
                    what += f": {s['detail']}"
                where = f"{where}: {what}"
            if len(states) > 1:
                where += f" (+{len(states) - 1} more)"
        tail = [f"{100 * frac:3.0f}%", f"elapsed {fmt_duration(elapsed)}"]
        if frac > 0.02 and elapsed > 1.0:
            tail.append(f"left ~{fmt_duration(elapsed * (1 - frac) / frac)}")
        fixed = "  ".join(tail)
        # the title goes before the recording's stage is cut short
        for h, least in ((head, min(len(where), 48)), (head[1:], 12)):
            lead = "  ".join(h)
            room = width - len(fixed) - (len(lead) + 2 if lead else 0) - (2 if where else 0)
            if not where or len(where) <= room:
                return "  ".join([x for x in (lead, where, fixed) if x])
            if room >= least:
                return "  ".join([x for x in (lead, where[: room - 3] + "...", fixed) if x])
        return "  ".join([x for x in ("  ".join(head[1:]), fixed) if x])[:width]

    def draw(self) -> None:
        """Redraw the line, or print the log's new lines (nothing when disabled)."""
        if not self.enabled:
            return
        with self._draw_lock:
            if self.log:
                self._log_new()
            else:
                self._draw()

    def _draw(self) -> None:
        try:
            cols = os.get_terminal_size(self.stream.fileno()).columns
        except (OSError, AttributeError, ValueError):
            cols = 0
        cols = cols if cols > 20 else DEFAULT_WIDTH + 1  # a pseudo-terminal may report 0
        # one column short of the terminal: a full-width line would wrap on some terminals
        text = self.line(width=min(cols - 1, MAX_WIDTH))
        pad = max(0, self._width - len(text))
        self.stream.write("\r" + text + " " * pad)
        self.stream.flush()
        self._width = len(text)

    def _loop(self) -> None:
        while not self._stop.wait(self.interval_s):
            try:
                self.draw()
            except (OSError, ValueError):
                return

    def close(self) -> None:
        """Stop redrawing and clear the line."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2)
            self._thread = None
        with self._draw_lock:
            if self.enabled and self.log:
                try:
                    self._log_new()  # the last stages (none if the command ended at once)
                except (OSError, ValueError):
                    pass
            self._clear()

    def _clear(self) -> None:
        if self.enabled and not self.log and self._width:
            try:
                self.stream.write("\r" + " " * self._width + "\r")
                self.stream.flush()
            except (OSError, ValueError):
                pass
            self._width = 0
        self.enabled = False


def timings_text(timings: dict[str, float]) -> str:
    """Return ``reading 1.2 s, aligning 0.3 s, ...`` of stage name -> seconds."""
    return ", ".join(f"{label(k)} {v:.1f} s" for k, v in timings.items())
