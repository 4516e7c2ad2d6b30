"""Survey campaigns: which recordings to process, with which options, in which order.

More in docs/modules.md, ``pipeline.app.campaign``.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import enum
import glob as globmod
import hashlib
import importlib
import json
import math
import re
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import numpy as np

from pipeline import __version__
from pipeline.app.simulate import load_scenario, simulate, write_simulated
from pipeline.core.atomic import safe_join, sha256_file, write_hint, write_text_atomic
from pipeline.core.config import TomlDoc
from pipeline.core.errors import (
    ConfigError,
    InputError,
    MagalignError,
    OutputError,
    UsageError,
)
from pipeline.core.vocabulary import EstimateTerm, EstimatorKind, ExcludeWindow
from pipeline.model.calibration import Calibration
from pipeline.model.igrf import igrf_enu_nT
from pipeline.run.options import ProcessOptions
from stages.write_survey import write_campaign_anomaly

#: the analysis a worker runs on each recording: imported by name in the worker, so that the
#: process that plans the campaign and gathers its rows never loads it (scipy's signal and
#: spatial modules, the diagnosis: slow to import)
RUNNER_MODULE = "pipeline.run.runner"

DONE_MARKER = ".magalign-done.json"
#: /2: a recording with positions also has targets.csv and anomaly.nc, which a folder done
#: under /1 lacks (it is processed again rather than reused)
DONE_FORMAT = "magalign.done/2"
CAMPAIGN_FORMAT = "magalign.campaign/1"


class RecordingRole(str, enum.Enum):
    """What a recording is for in a campaign."""

    CALIBRATION = "calibration"
    SURVEY = "survey"


class ReferenceFieldMode(str, enum.Enum):
    """Where the background field ``B_enu`` comes from."""

    ESTIMATE = "estimate"
    FIXED = "fixed"
    IGRF = "igrf"


@dataclass(frozen=True)
class ReferenceField:
    """Reference field options.

    Attributes
    ----------
    mode : ReferenceFieldMode
    enu_nT : tuple of 3 float or None
        The field for ``FIXED``, ENU, nT.
    lat_deg, lon_deg, alt_m : float or None
        Site for ``IGRF``.
    date : str or None
        ISO date for ``IGRF``.

    """

    mode: ReferenceFieldMode = ReferenceFieldMode.ESTIMATE
    enu_nT: tuple[float, float, float] | None = None
    lat_deg: float | None = None
    lon_deg: float | None = None
    alt_m: float | None = None
    date: str | None = None

    def resolve_enu_nT(self) -> tuple[float, float, float] | None:
        """Return the reference field in ENU (nT), or None when it is to be estimated."""
        if self.mode is ReferenceFieldMode.FIXED:
            return self.enu_nT
        if self.mode is ReferenceFieldMode.IGRF:


            # the campaign file reader sets the site with the IGRF mode
            assert self.lat_deg is not None and self.lon_deg is not None
            assert self.alt_m is not None
            b = igrf_enu_nT(self.lat_deg, self.lon_deg, self.alt_m,
                            dt.date.fromisoformat(str(self.date)))
            return cast("tuple[float, float, float]",
                        tuple(float(x) for x in np.asarray(b).reshape(3)))
        return None


@dataclass(frozen=True)
class RecordingOptions:
    """Options of one recording's processing: small, frozen, JSON-able (its hash is a key).

    Attributes
    ----------
    estimator : EstimatorKind
    terms : tuple of EstimateTerm
    reference_field : ReferenceField
    mag_topic, attitude_topic, turntable_topic : str or None
        Channel mapping; None = found by message type.
    outputs : tuple of (str, bool)
        Output switches of the ``[outputs]`` table (e.g. ``("rerun", True)``).
    exclude : tuple of str
        Stretches left out of the fit and the verdict, ``START:END`` as the command line's
        ``--exclude`` (:class:`pipeline.core.vocabulary.ExcludeWindow`).

    """

    estimator: EstimatorKind = EstimatorKind.ML
    terms: tuple[EstimateTerm, ...] = ()
    reference_field: ReferenceField = field(default_factory=ReferenceField)
    mag_topic: str | None = None
    attitude_topic: str | None = None
    turntable_topic: str | None = None
    outputs: tuple[tuple[str, bool], ...] = ()
    exclude: tuple[str, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form (enum values as strings)."""
        return _jsonable(dataclasses.asdict(self))


@dataclass(frozen=True)
class RecordingSpec:
    """One recording of a campaign.

    Attributes
    ----------
    name : str
        Output stem (one safe path component): results go to ``DIR/<name>/``.
    path : str or None
        The recording file; None when it is generated from ``scenario``.
    role : RecordingRole
    calibration_from : str or None
        Name of the calibration recording whose result this survey line uses.
    scenario : str or None
        Simulator scenario to generate the recording from when ``path`` is absent.
    seed : int or None
    options : RecordingOptions

    """

    name: str
    path: str | None
    role: RecordingRole = RecordingRole.SURVEY
    calibration_from: str | None = None
    scenario: str | None = None
    seed: int | None = None
    options: RecordingOptions = field(default_factory=RecordingOptions)


@dataclass(frozen=True)
class Campaign:
    """A validated campaign.

    Attributes
    ----------
    source : str
        The TOML file, the folder or the recording it was made from.
    name : str
    data_dir : str
        Folder (relative to the output folder) where recordings made from scenarios go.
    recordings : tuple of RecordingSpec
        Calibration runs first, then survey lines (dependency order).

    """

    source: str
    name: str
    data_dir: str
    recordings: tuple[RecordingSpec, ...]

    def stages(self) -> tuple[tuple[RecordingSpec, ...], tuple[RecordingSpec, ...]]:
        """(calibration runs, everything else): the second needs results of the first."""
        first = tuple(r for r in self.recordings if r.role is RecordingRole.CALIBRATION)
        rest = tuple(r for r in self.recordings if r.role is not RecordingRole.CALIBRATION)
        return first, rest


# --------------------------------------------------------------------------- parsing

_TOP_KEYS = {"campaign", "channels", "estimator", "reference_field", "outputs", "recordings"}
_REC_KEYS = {"name", "path", "glob", "scenario", "seed", "role", "calibration", "mag",
             "attitude", "exclude"}
_OUTPUT_KEYS = {"diagnose", "rerun", "report"}
# [outputs] switch -> ProcessOptions field
_OUTPUT_FIELDS = {"diagnose": "diagnose", "rerun": "write_rerun", "report": "write_report"}


def _jsonable(x: Any) -> Any:
    """Plain JSON types from dataclass dicts, enums and numpy values (NaN/inf -> None)."""
    if isinstance(x, enum.Enum):
        return x.value
    if isinstance(x, Mapping):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, np.generic):
        return _jsonable(x.item())
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, Path):
        return str(x)
    return x


def jsonable(x: Any) -> Any:
    """Public alias of the JSON converter used for summary rows and markers."""
    return _jsonable(x)


def safe_name(name: str) -> str:
    """One safe path component for ``name`` (the rule of :func:`pipeline.core.atomic.safe_join`)."""
    s = "".join(c if (c.isalnum() or c in "._-") else "_" for c in str(name)).strip(".")
    return s or "_"


class _Doc:
    """TomlDoc plus line lookup inside the i-th ``[[recordings]]`` table."""

    def __init__(self, doc: TomlDoc):
        self.doc = doc
        self.lines = doc.text.splitlines()

    def rec_line(self, i: int, key: str | None) -> int | None:
        hdr = re.compile(r"^\s*\[\[\s*recordings\s*\]\]\s*$")
        starts = [n for n, ln in enumerate(self.lines) if hdr.match(ln)]
        if i >= len(starts):
            return self.doc.line_of("recordings")
        lo = starts[i]
        hi = starts[i + 1] if i + 1 < len(starts) else len(self.lines)
        if key is not None:
            pat = re.compile(r"^\s*(" + re.escape(key) + r'|"' + re.escape(key) + r'")\s*=')
            for n in range(lo, hi):
                if pat.match(self.lines[n]):
                    return n + 1
        return lo + 1

    def rec_error(self, i: int, key: str | None, message: str,
                  hint: str | None = None) -> ConfigError:
        dotted = f"recordings[{i}]" + (f".{key}" if key else "")
        return ConfigError(message, path=self.doc.path, key=dotted, line=self.rec_line(i, key),
                           hint=hint)


def _opt_str(doc: TomlDoc, key: str, table: Mapping, err) -> str | None:
    v = table.get(key.rsplit(".", 1)[-1])
    if v is None:
        return None
    if not isinstance(v, str) or not v:
        raise err(key, f"must be a non-empty string, got {v!r}")
    return v


def _parse_options(doc: TomlDoc) -> RecordingOptions:
    d = doc.data
    ch = d.get("channels", {})
    if not isinstance(ch, Mapping):
        raise doc.error("channels", "must be a table")
    doc.check_keys(ch, {"mag", "attitude", "turntable"}, "channels")
    mag = _opt_str(doc, "channels.mag", ch, doc.error)
    att = _opt_str(doc, "channels.attitude", ch, doc.error)
    tt = _opt_str(doc, "channels.turntable", ch, doc.error)

    est = d.get("estimator", {})
    if not isinstance(est, Mapping):
        raise doc.error("estimator", "must be a table")
    doc.check_keys(est, {"kind", "terms"}, "estimator")
    kind = doc.choice("estimator.kind", EstimatorKind, EstimatorKind.ML)
    terms_raw = est.get("terms", [])
    if not isinstance(terms_raw, list):
        raise doc.error("estimator.terms", f"must be a list of term names, got {terms_raw!r}")
    terms = []
    for t in terms_raw:
        try:
            terms.append(EstimateTerm(t))
        except ValueError:
            allowed = ", ".join(e.value for e in EstimateTerm)
            raise doc.error("estimator.terms",
                            f"unknown term {t!r} (allowed: {allowed})") from None

    rf = d.get("reference_field", {})
    if not isinstance(rf, Mapping):
        raise doc.error("reference_field", "must be a table")
    doc.check_keys(rf, {"mode", "enu_nT", "lat_deg", "lon_deg", "alt_m", "date"},
                   "reference_field")
    mode = doc.choice("reference_field.mode", ReferenceFieldMode, ReferenceFieldMode.ESTIMATE)
    ref = ReferenceField(mode)
    if mode is ReferenceFieldMode.FIXED:
        v = doc.vector("reference_field.enu_nT", 3)
        if not 1e3 < float(np.linalg.norm(v)) < 1e5:
            raise doc.error("reference_field.enu_nT",
                            f"field magnitude {np.linalg.norm(v):.0f} nT is not an Earth field "
                            "(expected 20,000-70,000 nT)", hint="give the field in nanotesla")
        ref = ReferenceField(mode, enu_nT=cast("tuple[float, float, float]", tuple(v)))
    elif mode is ReferenceFieldMode.IGRF:
        lat = doc.number("reference_field.lat_deg", lo=-90, hi=90)
        lon = doc.number("reference_field.lon_deg", lo=-180, hi=360)
        alt = doc.number("reference_field.alt_m", 0.0, lo=-1e4, hi=1e6)
        date = doc.get("reference_field.date")

        try:
            dt.date.fromisoformat(str(date))
        except ValueError:
            raise doc.error("reference_field.date", f"must be an ISO date YYYY-MM-DD, got "
                            f"{date!r}") from None
        ref = ReferenceField(mode, lat_deg=lat, lon_deg=lon, alt_m=alt, date=str(date))

    out = d.get("outputs", {})
    if not isinstance(out, Mapping):
        raise doc.error("outputs", "must be a table")
    doc.check_keys(out, _OUTPUT_KEYS, "outputs")
    flags = []
    for k in sorted(out):
        if not isinstance(out[k], bool):
            raise doc.error(f"outputs.{k}", f"must be true or false, got {out[k]!r}")
        flags.append((k, bool(out[k])))
    return RecordingOptions(kind, tuple(sorted(set(terms), key=lambda t: t.value)), ref, mag,
                            att, tt, tuple(flags))


def load_campaign(path: str | Path) -> Campaign:
    """Read and validate a campaign TOML file.

    Relative ``path``, ``glob`` and ``scenario`` entries are relative to the TOML file's folder.

    Raises
    ------
    ConfigError
        Naming the file, the key and the line of the first problem.

    """
    doc = TomlDoc.load(path)
    return campaign_from_doc(doc)


def campaign_from_doc(doc: TomlDoc) -> Campaign:
    """Validate a parsed campaign document (see :func:`load_campaign`)."""
    d = doc.data
    base = Path(doc.path).resolve().parent
    doc.check_keys(d, _TOP_KEYS)
    camp = d.get("campaign", {})
    if not isinstance(camp, Mapping):
        raise doc.error("campaign", "must be a table")
    doc.check_keys(camp, {"name", "data_dir", "format"}, "campaign")
    fmt = camp.get("format", CAMPAIGN_FORMAT)
    if fmt != CAMPAIGN_FORMAT:
        raise doc.error("campaign.format", f"unsupported format {fmt!r} (this magalign reads "
                        f"{CAMPAIGN_FORMAT})")
    name = camp.get("name", Path(doc.path).stem)
    if not isinstance(name, str) or not name:
        raise doc.error("campaign.name", f"must be a non-empty string, got {name!r}")
    data_dir = camp.get("data_dir", "data")
    if not isinstance(data_dir, str) or not data_dir:
        raise doc.error("campaign.data_dir", f"must be a folder name, got {data_dir!r}")
    if Path(data_dir).is_absolute() or ".." in Path(data_dir).parts:
        raise doc.error("campaign.data_dir", "must be a folder inside the output folder "
                        f"(no absolute path, no '..'), got {data_dir!r}")
    base_opts = _parse_options(doc)

    recs = d.get("recordings")
    if recs is None:
        raise doc.error("recordings", "is required: at least one [[recordings]] table")
    if not isinstance(recs, list) or not all(isinstance(r, Mapping) for r in recs) or not recs:
        raise doc.error("recordings", "must be one or more [[recordings]] tables")
    dd = _Doc(doc)
    specs: list[tuple[int, RecordingSpec]] = []
    for i, r in enumerate(recs):
        for k in r:
            if k not in _REC_KEYS:
                raise dd.rec_error(i, k, f"unknown key (allowed: {', '.join(sorted(_REC_KEYS))})")
        for k in ("name", "path", "glob", "scenario", "role", "calibration", "mag", "attitude"):
            if k in r and (not isinstance(r[k], str) or not r[k]):
                raise dd.rec_error(i, k, f"must be a non-empty string, got {r[k]!r}")
        if "seed" in r and (isinstance(r["seed"], bool) or not isinstance(r["seed"], int)
                            or r["seed"] < 0):
            raise dd.rec_error(i, "seed", f"must be a non-negative integer, got {r['seed']!r}")
        try:
            role = RecordingRole(r.get("role", "survey"))
        except ValueError:
            raise dd.rec_error(i, "role",
                               f"must be calibration or survey, got {r['role']!r}") from None
        cal = r.get("calibration")
        if cal is not None and role is RecordingRole.CALIBRATION:
            raise dd.rec_error(i, "calibration", "a calibration run cannot take another "
                               "recording's calibration", hint="remove the key or the role")
        exclude = r.get("exclude", [])
        if not isinstance(exclude, list) or not all(isinstance(x, str) for x in exclude):
            raise dd.rec_error(i, "exclude", f"must be a list of \"START:END\" strings, got "
                               f"{exclude!r}")
        for x in exclude:
            try:
                ExcludeWindow.parse(x)
            except ValueError as exc:
                raise dd.rec_error(i, "exclude", str(exc)) from None
        opts = dataclasses.replace(
            base_opts,
            mag_topic=r.get("mag", base_opts.mag_topic),
            attitude_topic=r.get("attitude", base_opts.attitude_topic),
            exclude=tuple(exclude),
        )
        has = [k for k in ("path", "glob") if k in r]
        if len(has) > 1:
            raise dd.rec_error(i, "glob", "give either path or glob, not both")
        if "glob" in r:
            for k in ("name", "scenario", "seed"):
                if k in r:
                    raise dd.rec_error(i, k, f"{k} cannot be combined with glob (it names one "
                                       "recording)")
            pattern = r["glob"]
            if Path(pattern).is_absolute():
                full = pattern
            else:
                full = str(base / pattern)
            found = sorted(p for p in globmod.glob(full, recursive=True)
                           if Path(p).is_file())
            if not found:
                raise dd.rec_error(i, "glob", f"matches no file ({full})",
                                   hint="check the pattern; it is relative to the campaign file")
            for p in found:
                specs.append((i, RecordingSpec(safe_name(Path(p).stem), str(Path(p).resolve()),
                                               role, cal, None, None, opts)))
            continue
        scen = r.get("scenario")
        if "path" not in r and scen is None:
            raise dd.rec_error(i, None, "needs path, glob or scenario",
                               hint="say which file (or which simulator scenario) this is")
        rec_path = None
        if "path" in r:
            rec_path = str((base / r["path"]).resolve())
            if scen is None and not Path(rec_path).is_file():
                raise dd.rec_error(i, "path", f"file not found: {rec_path}")
        scen_path = None
        if scen is not None:
            scen_path = str((base / scen).resolve())
            if not Path(scen_path).is_file():
                raise dd.rec_error(i, "scenario", f"scenario file not found: {scen_path}")
        if "name" in r:
            nm = r["name"]
        elif rec_path is not None:
            nm = Path(rec_path).stem
        else:
            assert scen_path is not None  # no path: a scenario (checked above)
            nm = Path(scen_path).stem
        if rec_path is not None and "name" in r and safe_name(nm) != safe_name(
                Path(rec_path).stem):
            raise dd.rec_error(i, "name", "a recording given by path is named after its file "
                               f"({Path(rec_path).stem!r})", hint="drop the name key")
        specs.append((i, RecordingSpec(safe_name(nm), rec_path, role, cal, scen_path,
                                       r.get("seed"), opts)))

    seen: dict[str, int] = {}
    for i, s in specs:
        if s.name in seen:
            raise dd.rec_error(i, None, f"two recordings have the output name {s.name!r} "
                               f"(also recordings[{seen[s.name]}])",
                               hint="rename one file or give a different name")
        seen[s.name] = i
    cal_names = {s.name for _, s in specs if s.role is RecordingRole.CALIBRATION}
    for i, s in specs:
        if s.calibration_from is not None:
            if safe_name(s.calibration_from) not in cal_names:
                raise dd.rec_error(
                    i, "calibration",
                    f"names {s.calibration_from!r}, which is not a calibration recording "
                    f"(calibration recordings: {', '.join(sorted(cal_names)) or 'none'})")
    ordered = [s for _, s in specs if s.role is RecordingRole.CALIBRATION]
    ordered += [dataclasses.replace(s, calibration_from=safe_name(s.calibration_from))
                if s.calibration_from else s
                for _, s in specs if s.role is not RecordingRole.CALIBRATION]
    return Campaign(doc.path, name, data_dir, tuple(ordered))


def campaign_for_input(input_path: str | Path, *, options: RecordingOptions | None = None,
                       out_dir: str | Path | None = None) -> Campaign:
    """Make the campaign for what the command line was given: a TOML, a folder or one recording.

    A folder means every ``*.mcap`` directly in it (sorted), each calibrated on its own.
    ``options`` replaces the defaults for folders and single recordings; for a TOML the
    file's own options hold.
    """
    p = Path(input_path)
    if not p.exists():
        raise UsageError(f"{p}: no such file or folder",
                         hint="give a recording, a folder of recordings or a campaign .toml")
    if p.is_file() and p.suffix.lower() == ".toml":
        return load_campaign(p)
    opts = options or RecordingOptions()
    if p.is_dir():
        out_r = Path(out_dir).resolve() if out_dir is not None else None
        files = sorted(f for f in p.glob("*.mcap") if f.is_file()
                       and (out_r is None or out_r not in f.resolve().parents))
        if not files:
            raise InputError("folder holds no .mcap recording", path=p)
        specs = [RecordingSpec(safe_name(f.stem), str(f.resolve()), options=opts) for f in files]
    else:
        specs = [RecordingSpec(safe_name(p.stem), str(p.resolve()), options=opts)]
    names = [s.name for s in specs]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise InputError(f"recordings share the output name(s) {', '.join(dup)}", path=p,
                         hint="rename the files so that their names differ")
    return Campaign(str(p), p.stem, "data", tuple(specs))


# --------------------------------------------------------------------------- tasks

@dataclass(frozen=True)
class RecordingTask:
    """Everything one worker needs to process one recording (paths and small values only).

    Attributes
    ----------
    name : str
        Output stem: results in ``out_dir/<name>/``.
    input_path : str
        The recording (generated from ``scenario`` first when absent).
    out_dir : str
        The campaign output folder.
    role : RecordingRole
    options : RecordingOptions
    calibration_path : str or None
        A calibration.json to restore with instead of estimating.
    scenario : str or None
    seed : int or None
    config_sha256 : str
        Hash of everything besides the input bytes that determines the outputs.

    """

    name: str
    input_path: str
    out_dir: str
    role: RecordingRole
    options: RecordingOptions
    calibration_path: str | None
    scenario: str | None
    seed: int | None
    config_sha256: str


def config_sha256(spec: RecordingSpec, calibration_sha256: str | None) -> str:
    """Hash of the configuration that determines a recording's outputs.

    Includes the options, the role, the hash of the calibration it is restored with, the
    scenario and seed it is generated from, and the magalign version.
    """
    scen_hash = sha256_file(spec.scenario) if spec.scenario else None
    key = {
        "magalign": __version__,
        "options": spec.options.to_dict(),
        "role": spec.role.value,
        "calibration_sha256": calibration_sha256,
        "scenario_sha256": scen_hash,
        "seed": spec.seed,
    }
    return hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()


def make_task(spec: RecordingSpec, out_dir: str | Path, data_dir: str,
              calibration_path: str | None) -> RecordingTask:
    """Make the task for ``spec``; scenario recordings without a file go to ``out/<data_dir>/``."""
    out = Path(out_dir).resolve()
    if spec.path is not None and Path(spec.path).is_file():
        inp = spec.path
    elif spec.scenario is not None:
        inp = str(safe_join(out, data_dir, f"{spec.name}.mcap"))
    else:
        inp = spec.path or ""
    cal_hash = sha256_file(calibration_path) if calibration_path else None
    return RecordingTask(spec.name, inp, str(out), spec.role, spec.options, calibration_path,
                         spec.scenario if inp != spec.path else None, spec.seed,
                         config_sha256(spec, cal_hash))


def output_dir(task: RecordingTask) -> Path:
    """``out_dir/<name>``, refused if it would leave the output folder."""
    return safe_join(task.out_dir, task.name)


def read_done(folder: str | Path) -> dict[str, Any] | None:
    """Read the done-marker of a recording's output folder, or None if absent or unreadable."""
    p = Path(folder) / DONE_MARKER
    try:
        d = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(d, dict) or d.get("format") != DONE_FORMAT:
        return None
    return d


def finished_row(task: RecordingTask, input_sha256: str | None = None) -> dict[str, Any] | None:
    """Return the stored summary row when ``task``'s outputs are finished and still current."""
    d = read_done(output_dir(task))
    if d is None or d.get("config_sha256") != task.config_sha256:
        return None
    if not Path(task.input_path).is_file():
        return None
    if input_sha256 is None:
        input_sha256 = sha256_file(task.input_path)
    if d.get("input_sha256") != input_sha256:
        return None
    row = d.get("row")
    if not isinstance(row, dict):
        return None
    # Every output the row lists must still be there (someone may have deleted one); looked
    # up by name inside the folder so that a moved output folder stays valid.
    paths = row.get("paths")
    if isinstance(paths, dict):
        folder = output_dir(task)
        if not all((folder / Path(str(v)).name).is_file() for v in paths.values()):
            return None
    return row


def _process_options(task: RecordingTask) -> Any:
    """Build the ``ProcessOptions`` of a task, passing only the fields it has."""
    o = task.options
    names = {f.name for f in dataclasses.fields(ProcessOptions)}
    want: dict[str, Any] = {}
    est: Any = EstimatorKind(o.estimator)
    terms: Any = frozenset(EstimateTerm(t) for t in o.terms)
    want["estimator"] = est
    want["terms"] = terms
    want["mag_topic"] = o.mag_topic
    want["attitude_topic"] = o.attitude_topic
    want["turntable_topic"] = o.turntable_topic
    ref = o.reference_field.resolve_enu_nT()
    want["reference_field_enu_nT"] = None if ref is None else tuple(ref)
    want["calibration_path"] = task.calibration_path
    if o.exclude:
        want["exclude"] = tuple(ExcludeWindow.parse(x) for x in o.exclude)
    for k, v in o.outputs:
        want[_OUTPUT_FIELDS[k]] = v
    missing = sorted(set(want) - names)
    if missing:
        raise ConfigError(f"this magalign cannot apply the option(s) {', '.join(missing)}")
    return ProcessOptions(**want)


def _generate(task: RecordingTask) -> None:
    """Simulate a scenario recording into the campaign's data folder (atomic write)."""
    assert task.scenario is not None  # called for scenario recordings only
    sim = simulate(load_scenario(task.scenario), seed=task.seed)
    Path(task.input_path).parent.mkdir(parents=True, exist_ok=True)
    write_simulated(sim, task.input_path)


def run_task(task: RecordingTask) -> dict[str, Any]:
    """Process one recording; never raises for a recording's own problems.

    Returns
    -------
    dict
        ``{"name", "status": "ok" | "reused" | "failed", "row": summary row or None,
        "error": one line or None, "input_path"}`` (JSON-able).

    """
    base = {"name": task.name, "input_path": task.input_path, "role": task.role.value}
    t0 = time.perf_counter()
    try:
        if task.scenario is not None and not Path(task.input_path).is_file():
            _generate(task)
        if not Path(task.input_path).is_file():
            raise InputError("recording not found", path=task.input_path)
        in_hash = sha256_file(task.input_path)
        row = finished_row(task, in_hash)
        if row is not None:
            return {**base, "status": "reused", "row": row, "error": None}
        folder = output_dir(task)
        # A stale marker must not survive a run that rewrites the outputs; temporary files
        # of a killed run (atomic writes never renamed) are removed.
        (folder / DONE_MARKER).unlink(missing_ok=True)
        if folder.is_dir():
            for tmp in folder.glob(".*.tmp"):
                tmp.unlink(missing_ok=True)

        process_recording = importlib.import_module(RUNNER_MODULE).process_recording
        row = process_recording(task.input_path, task.out_dir, options=_process_options(task))
        row = jsonable(dict(row or {}))
        marker = {
            "format": DONE_FORMAT,
            "name": task.name,
            "input_path": task.input_path,
            "input_sha256": in_hash,
            "config_sha256": task.config_sha256,
            "row": row,
        }
        folder.mkdir(parents=True, exist_ok=True)
        # Written last and atomically: its presence means every output above is complete.
        write_text_atomic(folder / DONE_MARKER, json.dumps(marker, indent=1, allow_nan=False))
        return {**base, "status": "ok", "row": row, "error": None,
                "elapsed_s": round(time.perf_counter() - t0, 3)}
    except MagalignError as exc:
        return {**base, "status": "failed", "row": None,
                "error": exc.naming(task.input_path).one_line()}
    except OSError as exc:
        # the file system refused an output (a read-only or full folder): the user's to
        # fix, named in one line like every other bad input
        err = OutputError(f"cannot write: {exc.strerror or exc}",
                          path=exc.filename or task.out_dir, hint=write_hint(exc))
        return {**base, "status": "failed", "row": None, "error": err.one_line()}
    except Exception as exc:  # noqa: BLE001 - one bad recording must not stop the campaign
        return {**base, "status": "failed", "row": None,
                "error": f"{task.input_path}: internal error {type(exc).__name__}: {exc}"}


# --------------------------------------------------------------------------- orchestration

def _failed(spec: RecordingSpec, path: str | None, why: str) -> dict[str, Any]:
    return {"name": spec.name, "input_path": path, "role": spec.role.value, "status": "failed",
            "row": None, "error": why}


def run_campaign(
    campaign: Campaign,
    out_dir: str | Path,
    executor: Any,
    *,
    calibration_path: str | Path | None = None,
    progress: Any = None,
) -> list[dict[str, Any]]:
    """Process every recording of ``campaign`` into ``out_dir``; calibration runs first.

    Parameters
    ----------
    campaign : Campaign
        The validated campaign.
    out_dir : path
        Output folder; ``out_dir/<name>/`` per recording.
    executor : pipeline.app.executors.Executor
        Where the recordings are processed.
    calibration_path : path, optional
        calibration.json for survey recordings that do not name a calibration run.
    progress : callable, optional
        ``progress(result)`` after each recording (for a progress bar).

    Returns
    -------
    list of dict
        One result per recording in campaign order (see :func:`run_task`), with
        ``calibration_from`` added. Recordings whose outputs are current are ``reused``
        without being sent to a worker.

    """
    out = Path(out_dir).resolve()
    if calibration_path is not None:
        # refuse a bad file before any work, and before the output folder exists
        cp = Path(calibration_path)
        Calibration.load(cp)
        calibration_path = str(cp.resolve())
    out.mkdir(parents=True, exist_ok=True)
    results: dict[str, dict[str, Any]] = {}

    def note(res: dict[str, Any]) -> None:
        results[res["name"]] = res
        if progress is not None:
            progress(res)

    for specs in campaign.stages():
        tasks: list[RecordingTask] = []
        for s in specs:
            cal = None
            if s.calibration_from is not None:
                dep = results.get(s.calibration_from)
                if dep is None or dep["status"] == "failed":
                    note(_failed(s, s.path, f"calibration run {s.calibration_from} failed"))
                    continue
                cal = str(out / s.calibration_from / "calibration.json")
            elif s.role is RecordingRole.SURVEY and calibration_path is not None:
                cal = str(calibration_path)
            try:
                task = make_task(s, out, campaign.data_dir, cal)
                row = finished_row(task) if Path(task.input_path).is_file() else None
            except (MagalignError, OSError) as exc:
                why = exc.one_line() if isinstance(exc, MagalignError) else str(exc)
                note(_failed(s, s.path, why))
                continue
            if row is not None:
                note({"name": s.name, "input_path": task.input_path, "role": s.role.value,
                      "status": "reused", "row": row, "error": None})
            else:
                tasks.append(task)
        for task, res in executor.map(run_task, tasks):
            if isinstance(res, BaseException):
                res = {"name": task.name, "input_path": task.input_path,
                       "role": task.role.value, "status": "failed", "row": None,
                       "error": f"{task.input_path}: worker failed: {type(res).__name__}: {res}"}
            note(res)
    ordered = []
    for s in campaign.recordings:
        r = dict(results[s.name])
        r["calibration_from"] = s.calibration_from or (
            "--calibration" if calibration_path is not None and s.role is RecordingRole.SURVEY
            else None)
        ordered.append(r)
    # one anomaly grid over every recording with positions (DIR/anomaly.nc)
    grids = [out / r["name"] / "anomaly.nc" for r in ordered if r["status"] in ("ok", "reused")]
    write_campaign_anomaly(out, [g for g in grids if g.is_file()])
    return ordered
