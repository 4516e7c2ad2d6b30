"""``magalign process INPUT --out DIR``: the whole pipeline on a recording, folder or campaign.

INPUT is one ``.mcap`` recording, a folder of them, or a campaign ``.toml``
(``docs/campaigns.md``). Calibration runs are processed first; survey lines that name one are
restored with its result. One failing recording does not stop the others (exit status 3,
each failure listed). Finished outputs whose input bytes and configuration are unchanged are
reused, so an interrupted run resumes where it stopped.
"""

from __future__ import annotations

import argparse
import builtins
import dataclasses
import logging
import os
import shutil
import sys
import tempfile
import warnings
from pathlib import Path

from pipeline.app.campaign import (
    RecordingOptions,
    ReferenceField,
    ReferenceFieldMode,
    campaign_for_input,
    run_campaign,
)
from pipeline.app.commands._options import (
    ESTIMATE_HELP,
    add_exclude_option,
    add_field_options,
    add_topic_options,
    check_mcap_file,
    exclude_from_args,
    field_from_args,
)
from pipeline.app.executors import SerialExecutor, make_executor
from pipeline.app.summary import read_json, row_for, write_summary
from pipeline.core import errors
from pipeline.core import progress as pg
from pipeline.core.errors import CampaignPartialFailure, InputError, UsageError
from pipeline.core.style import minus, terminal_width, wrap
from pipeline.core.vocabulary import EstimateTerm, EstimatorKind
from pipeline.core.warm import warm_in_background
from stages.report_text import rows as finding_rows

log = logging.getLogger("magalign")


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register the subcommand."""
    p = sub.add_parser("process", help="process a recording, a folder or a campaign TOML",
                       description="The whole pipeline on one recording, a folder of "
                       "recordings or a campaign TOML file.")
    p.add_argument("input", help="recording (.mcap), folder of recordings, or campaign (.toml)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--calibration", help="calibration.json to restore survey recordings with "
                   "(those that do not name a calibration run)")
    p.add_argument("--jobs", type=int, default=None, help="local worker processes (default 1)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--dask-local", type=int, default=None, metavar="N",
                   help="start a Dask LocalCluster of N workers")
    g.add_argument("--scheduler", default=None, metavar="ADDR",
                   help="join a Dask scheduler tcp://host:port (trust it like a shell)")
    p.add_argument("--estimator", choices=[e.value for e in EstimatorKind], default=None,
                   help="estimator (default: the campaign's, else ml)")
    p.add_argument("--estimate", default=None, metavar="TERMS",
                   help=ESTIMATE_HELP)
    add_field_options(p)
    add_topic_options(p)
    add_exclude_option(p)
    p.add_argument("--no-progress", action="store_true",
                   help="no progress line (shown only on a terminal anyway; "
                   "MAGALIGN_PROGRESS=always|never overrides)")
    p.set_defaults(func=run)


def _overrides(args: argparse.Namespace):
    """Options given explicitly on the command line (they win over a campaign file's)."""
    ov: dict = {}
    if args.estimator is not None:
        ov["estimator"] = EstimatorKind(args.estimator)
    if args.estimate is not None:
        try:
            ov["terms"] = tuple(sorted({EstimateTerm(t.strip()) for t in args.estimate.split(",")
                                        if t.strip()}, key=lambda t: t.value))
        except ValueError:
            raise UsageError(f"--estimate {args.estimate!r}: terms are "
                             + ", ".join(t.value for t in EstimateTerm)) from None
    ref = field_from_args(args)
    if ref is not None:
        ov["reference_field"] = ReferenceField(ReferenceFieldMode.FIXED,
                                               enu_nT=(float(ref[0]), float(ref[1]), float(ref[2])))
    if args.mag is not None:
        ov["mag_topic"] = args.mag
    if args.attitude is not None:
        ov["attitude_topic"] = args.attitude
    if args.exclude:
        exclude_from_args(args)  # a malformed window: one line, exit 2, before any output
        ov["exclude"] = tuple(args.exclude)
    return ov


def _category(name: str) -> type[Warning]:
    """Return the warning class named ``name`` (magalign's or built-in), else UserWarning."""
    cls = getattr(errors, name, None) or getattr(builtins, name, None)
    return cls if isinstance(cls, type) and issubclass(cls, Warning) else UserWarning


def issue_warnings(results: list[dict]) -> None:
    """Issue, in this process, the warnings each recording's run collected.

    The recordings are processed in worker processes (or on Dask workers), whose warnings
    would otherwise be lost or printed there in Python's two-line format; the rows carry
    them back (``run_warnings``, :func:`pipeline.run.runner.process_recording`) and each is
    warned here once, as one ``magalign: warning: ...`` line. A reused result repeats its
    warnings: its outputs were made from the same damaged input.
    """
    for res in results:
        row = res.get("row") or {}
        for pair in row.get("run_warnings") or ():
            cat, msg = pair
            warnings.warn(str(msg), _category(str(cat)), stacklevel=2)


def _run_with_progress(camp, out: Path, executor, args: argparse.Namespace) -> list[dict]:
    """Run the campaign with its progress on stderr (``pipeline.core.progress``).

    A line redrawn on a terminal, else one line per stage of each recording. The workers
    write their stage into small files in a temporary folder the display reads;
    with ``-v`` the time of each stage of each recording is logged when it finishes.
    """
    old_env = os.environ.get(pg.ENV_DIR)
    with tempfile.TemporaryDirectory(prefix="magalign-progress-") as folder:
        display = pg.display_for(len(camp.recordings), "magalign process",
                                 disable=args.no_progress, folder=folder)
        if display.enabled:
            os.environ[pg.ENV_DIR] = folder

        def progress(res: dict) -> None:
            display.run_done(res["name"], str(res.get("status") or "ok"))
            timings = (res.get("row") or {}).get("timings_s")
            if timings and res.get("status") == "ok":
                log.info("%s: %s", res["name"], pg.timings_text(timings))

        try:
            with display:
                return run_campaign(camp, out, executor, calibration_path=args.calibration,
                                    progress=progress)
        finally:
            executor.close()
            if old_env is None:
                os.environ.pop(pg.ENV_DIR, None)
            else:
                os.environ[pg.ENV_DIR] = old_env


def _wrapped(text: str, first: str, rest: str) -> list[str]:
    """Return ``text`` wrapped to the terminal's width (80 columns when unknown).

    After ``first`` then ``rest``; lines break between words, so a number or a path is
    never cut (a path longer than the line stands whole on its own line).
    """
    return wrap(text, first, rest, terminal_width())


def recording_summary(result: dict, row: dict, out: Path) -> list[str]:
    """Return the final summary's lines of one recording: its verdict, findings and warnings.

    The verdict line as the report gives it, then (when it is not OK) why, then each
    diagnosis finding as the report's sentence (events that touch are one) and each warning
    of the calibration, all in words, wrapped to the terminal's width.
    """
    name = str(result["name"])
    line = (result.get("row") or {}).get("verdict_line")
    if not line:
        return []
    # the report's signs (± and a true minus), as the lines below it
    lines = _wrapped(f"{name}: {minus(line)}", "", "    ")
    folder = out / name
    cal = read_json(folder / "calibration.json") or {}
    verdict = cal.get("verdict") if isinstance(cal.get("verdict"), dict) else {}
    if verdict and verdict.get("status") != "OK" and verdict.get("reason"):
        lines += _wrapped(minus(str(verdict["reason"])), "  why: ", "       ")
    diag = read_json(folder / "diagnosis.json")
    if diag and diag.get("findings"):

        for fr in finding_rows(diag, 0):
            lines += _wrapped(fr.sentence, "  found: ", "         ")
    for w in cal.get("warnings") or []:
        lines += _wrapped(minus(str(w)), "  warning: ", "           ")
    return lines


def summary_title(name: str) -> str:
    """Title of summary.html: the campaign's name, after "magalign: " unless it names it."""
    return name if name.lower().startswith("magalign") else f"magalign: {name}"


def _remove_failed(out: Path, name: str, made_out: bool) -> None:
    """Remove what a failed single-recording run made.

    ``out`` when this run created it, else the recording's folder when it holds no file.
    """
    if made_out:
        shutil.rmtree(out, ignore_errors=True)
        return
    folder = out / name
    if folder.is_dir() and not any(f.is_file() for f in folder.rglob("*")):
        shutil.rmtree(folder, ignore_errors=True)


def run(args: argparse.Namespace) -> int:
    """Process; print where the results are; exit 3 when some recordings failed."""
    if args.jobs is not None and (args.dask_local is not None or args.scheduler is not None):
        raise UsageError("--jobs is for the local pool; with Dask give --dask-local N only")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {out} exists and is not a folder")
    made_out = not out.exists()  # a failed single recording leaves nothing behind then
    inp = Path(args.input)
    single = inp.is_file() and inp.suffix.lower() != ".toml"
    if single:
        check_mcap_file(inp)  # not a recording: one line, exit 2, no output folder
    ov = _overrides(args)
    camp = campaign_for_input(args.input, options=RecordingOptions(**ov), out_dir=out)
    if ov:
        camp = dataclasses.replace(camp, recordings=tuple(
            dataclasses.replace(r, options=dataclasses.replace(r.options, **ov))
            for r in camp.recordings))
    executor = make_executor(jobs=args.jobs, dask_local=args.dask_local,
                             scheduler=args.scheduler, items=len(camp.recordings))
    # the summary's imports (pandas through pyarrow's conversions, matplotlib for its
    # figure, which compares two runs or more) while the workers run, in the cycles they
    # leave idle. Not beside a recording run in this process: it would wait on a starved
    # thread's import lock, and matplotlib's catch_warnings there could end the run's own
    # collecting of warnings
    summary_imports = ("pyarrow.parquet", "pandas") + (
        ("pipeline.core.style:pyplot",) if len(camp.recordings) > 1 else ())
    warm = None if isinstance(executor, SerialExecutor) else warm_in_background(
        *summary_imports, idle=True)
    results = _run_with_progress(camp, out, executor, args)
    if warm is not None:
        # matplotlib reads its style files inside warnings.catch_warnings, which swaps the
        # process-wide warning hooks: a warning issued meanwhile on this thread would be
        # logged as matplotlib's ("In <style file>: ...") instead of ours
        warm.join()
    issue_warnings(results)
    out_r = out.resolve()
    failures = [(r["name"], r["error"] or "unknown error") for r in results
                if r["status"] == "failed"]
    if failures and len(results) == 1 and single:
        # One recording given: its failure is bad input (exit 2, one line), not a campaign
        # that partly failed (CONVENTIONS, "Exit status"); outputs appear only when complete
        _remove_failed(out, failures[0][0], made_out)
        raise InputError(failures[0][1], path="")  # the line names its file already
    rows = [row_for(out_r, r) for r in results]
    pq_path, html_path = write_summary(out_r, rows, title=summary_title(camp.name))
    n_ok = sum(r["status"] == "ok" for r in results)
    n_re = sum(r["status"] == "reused" for r in results)
    where = executor.describe()
    # where the work ran says nothing new for the default single local worker
    where = "" if where in ("1 local worker", "in this process") else f" ({where})"
    n = len(results)
    print(f"{n} recording{'s' if n != 1 else ''}: {n_ok} processed, {n_re} reused "
          f"(unchanged), {len(failures)} failed{where}")
    for r, row in zip(results, rows, strict=True):
        for line in recording_summary(r, row, out_r):
            print(line)
    print(f"results in {out}:")
    print(f"  summary  {out / html_path.name}   (open in a browser)")
    print(f"  table    {out / pq_path.name}")
    if (out / "anomaly.nc").is_file():
        print(f"  grid     {out / 'anomaly.nc'}   (the campaign's anomaly grid)")
    width = terminal_width()
    for r in rows:
        pad = " " * len(r["name"])
        view = f"  {r['name']}: magalign view {out / r['rrd']}" if r["rrd"] else ""
        if view and len(view) > width:
            # a path is printed whole: under the name when the line would overflow
            print(f"  {r['name']}:")
            view, pad = f"    magalign view {out / r['rrd']}", ""
        if view:
            print(view)
        if r["report"]:
            print(f"  {pad}  {'report':<7} {out / r['report']}")
        # a survey's products, where the recording has positions
        for what, name in (("targets", "targets.csv"), ("grid", "anomaly.nc")):
            if (out / r["name"] / name).is_file():
                print(f"  {pad}  {what:<7} {out / r['name'] / name}")
    if failures:
        for name, why in failures:
            print(f"magalign: FAILED {name}: {why}", file=sys.stderr)
        raise CampaignPartialFailure(failures)
    return 0
