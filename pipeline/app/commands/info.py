"""``magalign info REC.mcap [--json]``: channels, roles, counts, rates, duration, problems.

More in docs/modules.md, ``pipeline.app.commands.info``.
"""

from __future__ import annotations

import argparse
import json
import sys
import textwrap
from typing import Any

import numpy as np

from pipeline.io.mcap_read import inspect_recording
from pipeline.model.sample_hold import detect_sample_hold


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register the subcommand."""
    p = sub.add_parser("info", help="channels, roles, counts, rates and problems of a recording",
                       description="Describe one recording: its channels, their message types "
                       "and roles (magnetometer, attitude, other), counts, rates, duration, "
                       "gaps and problems.")
    p.add_argument("recording", help="MCAP file")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run)


def to_json(info: dict) -> dict:
    """Build the CONVENTIONS object of ``magalign info --json``."""
    return {
        "channels": [
            {k: c[k] for k in ("topic", "type", "role", "count", "rate_hz")}
            for c in info["channels"]
        ],
        "duration_s": info["duration_s"],
        "problems": info["problems"],
    }


def sample_hold_probe(topic: str, t_ns: np.ndarray, values: np.ndarray
                      ) -> dict[str, Any] | None:
    """Sample-and-hold of a magnetometer channel, or None when it has none.

    ``{"topic", "repeats", "messages", "repeated_fraction", "native_rate_hz",
    "message_rate_hz"}``: the messages that repeat the previous reading exactly and the rate
    the sensor really converts at (:func:`pipeline.model.sample_hold.detect_sample_hold`).
    """
    t = np.asarray(t_ns, dtype=np.int64)
    v = np.asarray(values, dtype=float)
    ok = np.isfinite(v).all(axis=1)
    t, v = t[ok], v[ok]
    order = np.argsort(t, kind="stable")
    found = detect_sample_hold(t[order], v[order])
    if found is None:
        return None
    return {"topic": topic, "repeats": int(np.count_nonzero(~found.first)),
            "messages": int(len(t)), "repeated_fraction": float(found.repeated_fraction),
            "native_rate_hz": float(found.native_rate_hz),
            "message_rate_hz": float(found.message_rate_hz)}


def sample_hold_text(held: dict | None) -> str:
    """One line on the magnetometer's sample-and-hold repeats and its native rate."""
    if not held:
        return "sample-and-hold: none (every magnetometer message is a new reading)"
    return (f"sample-and-hold: {held['repeats']} of {held['messages']} {held['topic']} messages "
            f"({100 * held['repeated_fraction']:.1f} %) repeat the previous reading; the sensor "
            f"converts at about {held['native_rate_hz']:.1f} Hz, its messages come at "
            f"{held['message_rate_hz']:.1f} Hz")


def format_table(info: dict) -> str:
    """Format the human-readable form: a channel table, then duration and problems."""
    head = ("topic", "type", "role", "count", "rate_hz")
    rows = [head] + [
        (c["topic"], c["type"], c["role"], str(c["count"]),
         "-" if c["rate_hz"] is None else f"{c['rate_hz']:.3f}")
        for c in info["channels"]
    ]
    widths = [max(len(r[i]) for r in rows) for i in range(len(head))]
    lines = [f"{info['path']}  (profile {info['profile'] or '-'})"]
    for k, r in enumerate(rows):
        lines.append("  ".join(
            (s.rjust(w) if i >= 3 else s.ljust(w))
            for i, (s, w) in enumerate(zip(r, widths, strict=True))
        ).rstrip())
        if k == 0:
            lines.append("  ".join("-" * w for w in widths))
    lines.append(f"duration: {info['duration_s']:.3f} s")
    if any(c["role"] == "magnetometer" for c in info["channels"]):

        lines += textwrap.wrap(sample_hold_text(info.get("sample_hold")), 100,
                               subsequent_indent="  ")
    if info["problems"]:
        lines.append(f"problems ({len(info['problems'])}):")

        for p in info["problems"]:
            lines += textwrap.wrap(f"- [{p['code']}] {p['message']}", 100,
                                   initial_indent="  ", subsequent_indent="    ")
    else:
        lines.append("problems: none")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    """Print the description of one recording."""
    info = inspect_recording(args.recording, mag_probe=sample_hold_probe)
    if args.json:
        json.dump(to_json(info), sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        print(format_table(info))
    return 0
