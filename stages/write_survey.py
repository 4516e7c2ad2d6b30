"""The survey's products: ``targets.csv`` (the located objects) and ``anomaly.nc`` (the grid).

Both are written by ``process`` for a recording with positions (CONVENTIONS, "Output
files"); a campaign whose recordings have positions also gets one ``anomaly.nc`` over all of
them (:func:`write_campaign_anomaly`).

The grid (:func:`grid_survey`):

- *Along-path blocks.* The restored ENU field is averaged over consecutive stretches of the
  path ``step_m`` long (half the grid spacing, or longer when the path would give more than
  :data:`MAX_POINTS` blocks), so the fit's memory is bounded by the area, not the samples.
- *Line spacing* (:func:`line_spacing_m`): the median, over the path, of the distance to the
  nearest point of another pass (a point that the path reaches only after a detour more than
  :data:`DETOUR` times the straight distance). Parallel survey lines give their spacing; a
  path that never comes back gives a tenth of its extent.
- *Grid spacing* a quarter of the line spacing (four cells from one line to the next, the
  ``s / 4`` rule of thumb for line-based magnetic surveys), coarsened only to stay under
  :data:`MAX_CELLS` cells; *mask distance* 0.6 line spacing: every cell between two
  neighbouring lines (at most half a spacing from one) is kept, and the grid reaches past
  the outer lines by little more than half a spacing, where it is an extrapolation.
- *Method.* The compact sources the diagnosis located (``local_source``) are evaluated on
  the grid exactly (``harmonica.dipole_magnetic``); what the restored field holds beyond them
  and the background is interpolated by equivalent sources (``harmonica.EquivalentSources``,
  Dampney 1969; Soler & Uieda 2021), one fit per ENU component: each component of a
  potential field is itself harmonic above its sources, so the point-source kernel ``1/r``
  represents it. The sources lie one line spacing below the data (deep enough for the field
  to stay smooth across a line spacing without data). The mask is ``verde.distance_mask``.

The grid's libraries (harmonica, verde, xarray, h5netcdf) are imported inside the functions
that use them: a recording without positions never loads them.
"""

from __future__ import annotations

import csv
import dataclasses
import datetime as dt
import io
import math
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.core.atomic import atomic_path, write_text_atomic
from pipeline.core.errors import OutputError
from pipeline.core.recording import GeodeticOrigin
from pipeline.core.style import num
from pipeline.io.mcap_decode import geodetic_to_local_enu, local_enu_to_geodetic
from pipeline.model.effects.local_source import objects
from pipeline.model.forward import dipole_field

#: columns of targets.csv, in order (CONVENTIONS)
TARGET_COLUMNS = (
    "id", "east_m", "north_m", "up_m", "lat_deg", "lon_deg", "height_m",
    "depth_below_sensor_m", "sigma_east_m", "sigma_north_m", "sigma_up_m",
    "moment_east_Am2", "moment_north_Am2", "moment_up_Am2", "moment_Am2",
    "closest_approach_m", "closest_approach_utc", "peak_nT", "delta_bic", "position_frame",
)
#: most along-path blocks the equivalent sources are fitted to (the fit's Jacobian and its
#: normal matrix are points x sources, float64: 3,000 x 3,000 is 72 MB each)
MAX_POINTS = 3000
#: most grid cells (the field is predicted at them in blocks of ``_PREDICT_ROWS``)
MAX_CELLS = 250_000
#: a point of another pass: the path between the two is longer than this many times the
#: straight distance between them
DETOUR = 3.0
#: grid spacing as a fraction of the line spacing
SPACING_PER_LINE = 0.25
#: mask distance as a multiple of the line spacing
MASK_PER_LINE = 0.6
#: radius of the neighbourhood whose mean sensor height gives a target's depth, m
DEPTH_RADIUS_M = 5.0
#: the equivalent sources' damping (ridge regularisation of verde's least squares on the
#: column-scaled Jacobian): small, the data's noise is averaged out by the along-path blocks
DAMPING = 1e-3
#: columns of the Jacobian whose standard deviations are taken together (their deviations
#: from the mean are a temporary copy: 256 columns of 3,000 rows are 6 MB)
_STD_COLUMNS = 256
#: grid cells whose Green's functions are formed at once (1,024 cells of 3,000 sources are
#: 25 MB)
_PREDICT_ROWS = 1024


@dataclass(frozen=True)
class PathBlocks:
    """The path averaged over consecutive stretches.

    Attributes
    ----------
    p_m : ndarray (M, 3)
        Mean sensor position of each block, m, in the positions' frame.
    B_enu_nT : ndarray (M, 3)
        Mean restored field of each block, ENU, nT.
    n : ndarray (M,)
        Samples in each block.

    """

    p_m: np.ndarray
    B_enu_nT: np.ndarray
    n: np.ndarray


@dataclass(frozen=True)
class Grid:
    """The gridded field (``anomaly.nc``'s content).

    Attributes
    ----------
    easting_m, northing_m : ndarray (nx,), (ny,)
        Cell centres, m.
    B_enu_nT : ndarray (3, ny, nx)
        East, north, up field at ``height_m``, NaN beyond the mask.
    total_field_anomaly_nT : ndarray (ny, nx)
        ``|B| - |B_background|``, NaN beyond the mask.
    height_m, spacing_m, mask_distance_m, line_spacing_m : float
    background_B_enu_nT : ndarray (3,)
    method : str
    n_points : int
        Along-path blocks fitted.

    """

    easting_m: np.ndarray
    northing_m: np.ndarray
    B_enu_nT: np.ndarray
    total_field_anomaly_nT: np.ndarray
    height_m: float
    spacing_m: float
    mask_distance_m: float
    line_spacing_m: float
    background_B_enu_nT: np.ndarray
    method: str
    n_points: int


# ----------------------------------------------------------------------------- the path


def path_blocks(p_m: np.ndarray, B_enu_nT: np.ndarray, step_m: float) -> PathBlocks:
    """Average positions and field over consecutive stretches of the path ``step_m`` long.

    Samples without a position or a restored field are left out; a block is cut wherever
    the cumulative distance along the path crosses a multiple of ``step_m`` (a sensor at rest
    stays in one block).
    """
    p = np.asarray(p_m, dtype=float).reshape(-1, 3)
    B = np.asarray(B_enu_nT, dtype=float).reshape(-1, 3)
    ok = np.isfinite(p).all(axis=1) & np.isfinite(B).all(axis=1)
    p, B = p[ok], B[ok]
    if not len(p):
        return PathBlocks(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, dtype=np.int64))
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p[:, :2], axis=0), axis=1))])
    _, idx = np.unique(np.floor(s / max(step_m, 1e-9)).astype(np.int64), return_inverse=True)
    n = np.bincount(idx)
    pm = np.stack([np.bincount(idx, weights=p[:, k]) / n for k in range(3)], axis=1)
    Bm = np.stack([np.bincount(idx, weights=B[:, k]) / n for k in range(3)], axis=1)
    return PathBlocks(pm, Bm, n)


def line_spacing_m(p_m: np.ndarray) -> float:
    """Return the typical distance between neighbouring passes of the path ``p_m`` (N, 2+), m.

    The path is resampled every ``max(0.05 m, length / 10,000)`` along its length; for each
    point the nearest point of another pass is found (one the path reaches only after more
    than :data:`DETOUR` times the straight distance), and the median of those distances is
    the spacing. Parallel survey lines give their spacing (the turns at the line ends count
    little against the lines). A path that never comes back (one line) gives a tenth of its
    horizontal extent, at least 1 m.
    """
    from scipy.spatial import cKDTree

    xy = np.asarray(p_m, dtype=float)[:, :2]
    xy = xy[np.isfinite(xy).all(axis=1)]
    if len(xy) < 2:
        return 1.0
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    extent = float(np.max(np.ptp(xy, axis=0)))
    fallback = max(1.0, extent / 10.0)
    if s[-1] <= 0:
        return fallback
    step = max(0.05, s[-1] / 10000.0)  # 10,000 points x 400 neighbours: 70 MB at most
    keep = np.unique(np.searchsorted(s, np.arange(0.0, s[-1], step)))
    pts, sk = xy[keep], s[keep]
    tree = cKDTree(pts)
    k = min(len(pts), 400)
    d, j = tree.query(pts, k=k)
    d, j = d.reshape(len(pts), -1), j.reshape(len(pts), -1)
    other = np.abs(sk[j] - sk[:, None]) > DETOUR * np.maximum(d, step)
    found = other.any(axis=1)
    if np.count_nonzero(found) < 0.2 * len(pts):
        return fallback
    first = np.argmax(other[found], axis=1)
    return float(np.median(d[found][np.arange(len(first)), first]))


def grid_rule(p_m: np.ndarray) -> tuple[float, float, float]:
    """Return ``(line_spacing_m, spacing_m, mask_distance_m)`` for the path ``p_m`` (N, 2+).

    Spacing :data:`SPACING_PER_LINE` of the line spacing, coarsened to keep the grid within
    :data:`MAX_CELLS`; mask distance :data:`MASK_PER_LINE` of the line spacing.
    """
    xy = np.asarray(p_m, dtype=float)[:, :2]
    xy = xy[np.isfinite(xy).all(axis=1)]
    line = line_spacing_m(xy)
    mask = MASK_PER_LINE * line
    spacing = SPACING_PER_LINE * line
    if len(xy):
        w, h = (np.ptp(xy, axis=0) + 2 * mask).tolist()
        spacing = max(spacing, math.sqrt(w * h / MAX_CELLS))
    return line, _round_spacing(spacing), mask


def _round_spacing(x: float) -> float:
    """Round a spacing down to 1, 2 or 5 times a power of ten (a surveyor's round number)."""
    e = math.floor(math.log10(x))
    for m in (5.0, 2.0, 1.0):
        if m * 10.0**e <= x:
            return m * 10.0**e
    return 10.0**e


# ----------------------------------------------------------------------------- dipoles


def dipole_field_nT(p_m: np.ndarray, source_m: np.ndarray, moment_Am2: np.ndarray) -> np.ndarray:
    """Field of a point dipole at points ``p_m`` (N, 3), ENU nT (CONVENTIONS ``local_source``).

    The forward model's own dipole (:func:`pipeline.model.forward.dipole_field`), so that the
    grid and the diagnosis evaluate one field.
    """
    r = np.asarray(p_m, dtype=float).reshape(-1, 3) - np.asarray(source_m, dtype=float)
    return dipole_field(r, moment_Am2)


@dataclass(frozen=True)
class Source:
    """A located object: one ``local_source`` finding of the final model."""

    position_m: np.ndarray
    sigma_m: np.ndarray
    moment_Am2: np.ndarray
    closest_approach_m: float | None
    closest_approach_s: float | None
    delta_bic: float
    position_frame: str
    #: the dipoles, ``(position_m, moment_Am2)``, of an object described by several
    #: (:func:`one_row_per_object`); empty: the source is its own one dipole
    parts: tuple[tuple[np.ndarray, np.ndarray], ...] = ()

    def field_nT(self, p_m: np.ndarray) -> np.ndarray:
        """Field of the object at points ``p_m`` (N, 3), ENU nT: the sum of its dipoles."""
        parts = self.parts or ((self.position_m, self.moment_Am2),)
        return sum((dipole_field_nT(p_m, c, m) for c, m in parts),
                   start=np.zeros((len(np.asarray(p_m).reshape(-1, 3)), 3)))


def one_row_per_object(sources: list[Source]) -> list[Source]:
    """Merge the dipoles the data do not resolve apart into one object each.

    The grouping is the ``local_source`` effect's (:func:`pipeline.model.effects.local_source.
    objects`: closer together than the sensor came to either). An object of several dipoles
    is listed at their centre weighted by each moment's size, with a sigma that holds the
    centre's own (the dipoles' positions taken as independent) and the object's extent (the
    dipoles' weighted spread about the centre, per axis: which point of an object larger
    than a point is where it is, the data cannot say closer), the sum of their moments (the object's
    dipole moment, what its field is far away), the closest pass of any of them and the sum
    of their ``delta_bic`` (each dipole's own evidence as it was added). Ordered again by
    ``delta_bic``.
    """
    as_params = [{"position_m": s.position_m, "closest_approach_m": s.closest_approach_m,
                  "position_frame": s.position_frame} for s in sources]
    out = []
    for g in objects(as_params):
        members = [sources[i] for i in g]
        if len(members) == 1:
            out.append(members[0])
            continue
        w = np.array([float(np.linalg.norm(m.moment_Am2)) for m in members])
        w = w / max(float(w.sum()), 1e-300)
        near = min(members, key=lambda m: math.inf if m.closest_approach_m is None
                   else m.closest_approach_m)
        centre = np.sum([wi * m.position_m for wi, m in zip(w, members, strict=True)], axis=0)
        known = np.sum([(wi * m.sigma_m) ** 2 for wi, m in zip(w, members, strict=True)], axis=0)
        extent = np.sum([wi * (m.position_m - centre) ** 2 for wi, m in
                         zip(w, members, strict=True)], axis=0)
        out.append(Source(
            centre, np.sqrt(known + extent),
            np.sum([m.moment_Am2 for m in members], axis=0),
            near.closest_approach_m, near.closest_approach_s,
            float(sum(m.delta_bic for m in members)), members[0].position_frame,
            tuple((m.position_m, m.moment_Am2) for m in members)))
    out.sort(key=lambda s: s.delta_bic if math.isfinite(s.delta_bic) else math.inf)
    return out


def located_sources(diagnosis: Any) -> list[Source]:
    """Return the diagnosis's ``local_source`` findings, the strongest evidence first.

    ``delta_bic`` is the change of ``-2 log`` of the Laplace evidence when the object was
    added (after minus before, :func:`stages.diagnose.statistics.evidence`; CONVENTIONS keeps
    the BIC's name): the more negative, the more strongly the data ask for it, so the order
    is ``delta_bic`` ascending.
    """
    if diagnosis is None:
        return []
    final = getattr(diagnosis, "final", None) or {}
    if "effects" in final and "local_source" not in final["effects"]:
        return []  # found on the way, then left out of the final model
    out = []
    for f in diagnosis.findings:
        if f.effect != "local_source":
            continue
        p = f.params
        sig = (f.sigma or {}).get("position_m") or [math.nan] * 3
        out.append(Source(
            np.asarray(p["position_m"], dtype=float),
            np.asarray([math.nan if v is None else float(v) for v in sig]),
            np.asarray(p["moment_Am2"], dtype=float),
            None if p.get("closest_approach_m") is None else float(p["closest_approach_m"]),
            None if p.get("closest_approach_s") is None else float(p["closest_approach_s"]),
            float((f.evidence or {}).get("delta_bic", math.nan)),
            str(p.get("position_frame") or "enu")))
    out.sort(key=lambda s: s.delta_bic if math.isfinite(s.delta_bic) else math.inf)
    return out


# ----------------------------------------------------------------------------- targets.csv


def target_rows(sources: list[Source], p_m: np.ndarray, t_ns: np.ndarray, t0_ns: int,
                origin: GeodeticOrigin | None) -> list[list[str]]:
    """Return targets.csv's rows (strings, no header), one per source, in the given order.

    Parameters
    ----------
    sources : list of Source
        The located objects, in the order of the rows.
    p_m : ndarray (N, 3)
        Sensor positions along the path (NaN where lost), m, in the positions' frame.
    t_ns : ndarray (N,)
        Their stamps.
    t0_ns : int
        The first magnetometer stamp (``closest_approach_s`` counts from it).
    origin : GeodeticOrigin or None
        The geodetic point of the ENU origin (None: a local frame, no latitude/longitude).

    """
    p = np.asarray(p_m, dtype=float).reshape(-1, 3)
    ok = np.isfinite(p).all(axis=1)
    p, t = p[ok], np.asarray(t_ns, dtype=np.int64)[ok]
    rows = []
    for i, s in enumerate(sources):
        x = s.position_m
        if origin is not None:
            lat, lon, h = (float(v[0]) for v in local_enu_to_geodetic(x[None, :], origin))
            geo = [num(lat, ".9f"), num(lon, ".9f"), num(h, ".3f")]
        else:
            geo = ["", "", ""]
        near = np.linalg.norm(p[:, :2] - x[:2], axis=1) <= DEPTH_RADIUS_M
        up = p[near, 2] if near.any() else p[:, 2]
        depth = float(np.mean(up)) - float(x[2]) if len(up) else math.nan
        utc, peak = "", math.nan
        if s.closest_approach_s is not None:
            tc = int(t0_ns) + int(round(s.closest_approach_s * 1e9))
            utc = _iso_utc(tc)
            if len(t):
                j = int(np.argmin(np.abs(t - tc)))
                peak = float(np.linalg.norm(s.field_nT(p[j])))
        rows.append([f"T{i + 1}", *(num(v, ".3f") for v in x), *geo, _f(depth, ".3f"),
                     *(_f(v, ".3f") for v in s.sigma_m),
                     *(num(v, ".3f") for v in s.moment_Am2),
                     num(float(np.linalg.norm(s.moment_Am2)), ".3f"),
                     _f(s.closest_approach_m, ".3f"), utc, _f(peak, ".1f"),
                     _f(s.delta_bic, ".1f"), s.position_frame])
    return rows


def _f(x: float | None, spec: str) -> str:
    """Return a number for the CSV: empty when unknown, never a negative zero."""
    if x is None or not math.isfinite(float(x)):
        return ""
    return num(float(x), spec)


def _iso_utc(t_ns: int) -> str:
    """ISO 8601 UTC time of ``t_ns`` with microseconds and a ``Z``."""
    sec, ns = divmod(int(t_ns), 1_000_000_000)
    d = dt.datetime.fromtimestamp(sec, tz=dt.timezone.utc)
    return d.strftime("%Y-%m-%dT%H:%M:%S") + f".{ns // 1000:06d}Z"


def write_targets(path: str | Path, rows: list[list[str]]) -> Path:
    """Write targets.csv (header, then ``rows``) atomically."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(TARGET_COLUMNS)
    w.writerows(rows)
    return write_text_atomic(path, buf.getvalue())


# ----------------------------------------------------------------------------- the grid


def library_versions() -> str:
    """Return ``harmonica X, verde Y`` as installed."""
    return ", ".join(f"{n} {metadata.version(n)}" for n in ("harmonica", "verde"))


def compile_grid() -> Grid | None:
    """Grid a small circle of constant field once, for what numba compiles on first use.

    harmonica's equivalent-source kernels are compiled by numba in every new process, and
    take several times longer than the fit they serve (docs/performance.md); ``process``
    runs this on its helper thread while the analysis runs (``pipeline.core.warm``),
    through the same code as a recording's grid.
    """
    angle = np.linspace(0.0, 2.0 * np.pi, 64, endpoint=False)
    p = np.column_stack([np.cos(angle), np.sin(angle), np.ones_like(angle)])
    background = np.array([0.0, 20000.0, -40000.0])
    return grid_survey(p, np.tile(background, (len(p), 1)), background)


def grid_survey(p_m: np.ndarray, B_enu_nT: np.ndarray, background_B_enu_nT: np.ndarray,
                sources: list[Source] | None = None, *,
                rule: tuple[float, float, float] | None = None) -> Grid | None:
    """Grid the restored field over the surveyed area (see the module's description).

    Parameters
    ----------
    p_m : ndarray (N, 3)
        Sensor positions, m (NaN where lost).
    B_enu_nT : ndarray (N, 3)
        Restored field there, ENU nT (NaN where not restored).
    background_B_enu_nT : ndarray (3,)
        The model's background field.
    sources : list of Source, optional
        Located objects, evaluated exactly on the grid (ENU positions only: in a frame
        turned by an unknown angle the dipole's field cannot be placed).
    rule : (line_spacing_m, spacing_m, mask_distance_m), optional
        Default :func:`grid_rule` of the path.

    Returns
    -------
    Grid or None
        None when fewer than 10 positions have a restored field.

    """
    import harmonica as hm
    import verde as vd

    p = np.asarray(p_m, dtype=float).reshape(-1, 3)
    B = np.asarray(B_enu_nT, dtype=float).reshape(-1, 3)
    ok = np.isfinite(p).all(axis=1) & np.isfinite(B).all(axis=1)
    if np.count_nonzero(ok) < 10:
        return None
    p, B = p[ok], B[ok]
    line, spacing, mask_dist = grid_rule(p) if rule is None else rule
    length = float(np.sum(np.linalg.norm(np.diff(p[:, :2], axis=0), axis=1)))
    blocks = path_blocks(p, B, max(spacing / 2.0, length / MAX_POINTS))
    bg = np.asarray(background_B_enu_nT, dtype=float)
    height = float(np.mean(blocks.p_m[:, 2]))
    srcs = [s for s in (sources or []) if s.position_frame == "enu"]
    remainder = blocks.B_enu_nT - bg
    for s in srcs:
        remainder = remainder - dipole_field_nT(blocks.p_m, s.position_m, s.moment_Am2)

    lo, hi = blocks.p_m[:, :2].min(axis=0) - mask_dist, blocks.p_m[:, :2].max(axis=0) + mask_dist
    # cell centres on multiples of the spacing: grids of one frame line up
    west, south = (np.floor(lo / spacing) + 0.5) * spacing
    east, north = (np.ceil(hi / spacing) - 0.5) * spacing
    e_c = np.arange(west, east + spacing / 2, spacing)
    n_c = np.arange(south, north + spacing / 2, spacing)
    ee, nn = np.meshgrid(e_c, n_c)
    uu = np.full_like(ee, height)
    data_coords = (blocks.p_m[:, 0], blocks.p_m[:, 1], blocks.p_m[:, 2])
    inside = vd.distance_mask(data_coords[:2], mask_dist, coordinates=(ee, nn))

    field = np.full((3, *ee.shape), np.nan)
    at = (ee[inside], nn[inside], uu[inside])
    pred = equivalent_sources(data_coords, remainder, at, depth_m=line, block_m=spacing)
    if srcs:
        b = hm.dipole_magnetic(
            at, (np.array([s.position_m[0] for s in srcs]),
                 np.array([s.position_m[1] for s in srcs]),
                 np.array([s.position_m[2] for s in srcs])),
            tuple(np.array([s.moment_Am2 for s in srcs]).T), field="b")
        pred += np.asarray(b)
    for k in range(3):
        field[k][inside] = pred[k] + bg[k]
    tfa = np.linalg.norm(field, axis=0) - float(np.linalg.norm(bg))
    dipoles = (f" and the {len(srcs)} located dipoles (harmonica.dipole_magnetic, added back "
               "on the grid)" if srcs else "")
    method = (f"equivalent sources (harmonica.EquivalentSources, depth {num(line, '.3g')} m, "
              f"damping {DAMPING:g}, sources in blocks of {num(spacing, '.3g')} m) fitted per "
              f"ENU component to {len(blocks.n)} along-path block means of the restored field "
              f"less the background{dipoles}; mask verde.distance_mask; {library_versions()}")
    return Grid(e_c, n_c, field, tfa, height, spacing, mask_dist, line, bg, method,
                len(blocks.n))


def equivalent_sources(data_m: tuple[np.ndarray, np.ndarray, np.ndarray], values: np.ndarray,
                       at_m: tuple[np.ndarray, np.ndarray, np.ndarray], *, depth_m: float,
                       block_m: float) -> np.ndarray:
    """Fit equivalent sources to each column of ``values`` and predict them at ``at_m``.

    ``harmonica.EquivalentSources`` (point sources, Green's function ``1/r``) with its
    sources under the block means of the data (blocks of ``block_m``) at ``depth_m`` below
    them, as harmonica places them with ``block_size`` and a fixed ``depth``. The columns
    share the sources, so the damped least squares of ``verde.base.least_squares`` (the
    Jacobian's columns scaled to unit standard deviation, a ridge of ``DAMPING``) is solved
    once with one right-hand side per column instead of once per column.

    Parameters
    ----------
    data_m : (easting, northing, upward) arrays (M,)
        The data's positions, m.
    values : ndarray (M, K)
        The data, one column per field component.
    at_m : (easting, northing, upward) arrays (P,)
        Where to predict.
    depth_m, block_m : float
        Depth of the sources below the data, size of the blocks that place them, m.

    Returns
    -------
    ndarray (K, P)

    """
    import harmonica as hm
    from scipy.linalg import solve

    e, n, u = (np.asarray(c, dtype=float) for c in data_m)
    key = np.floor(np.column_stack([e, n]) / block_m).astype(np.int64)
    _, idx = np.unique(key, axis=0, return_inverse=True)
    idx = idx.ravel()
    cnt = np.bincount(idx)
    points = tuple(np.bincount(idx, weights=c) / cnt for c in (e, n, u - depth_m))
    es = hm.EquivalentSources(points=points, damping=DAMPING)
    A = es.jacobian((e, n, u), points)
    # column by column (blocks of them): the deviations from the mean of the whole matrix
    # at once were one more copy of it; each column's standard deviation is the same
    scale = np.concatenate([A[:, a:a + _STD_COLUMNS].std(axis=0)
                            for a in range(0, A.shape[1], _STD_COLUMNS)])
    scale[scale == 0] = 1.0
    A /= scale
    # At MAX_POINTS blocks and as many sources each of these matrices is 72 MB: the Jacobian
    # goes once its products are formed, and the ridge is added to the normal matrix's
    # diagonal in place (the numbers of ``+ DAMPING * np.eye(n)``, whose off-diagonal terms
    # are exact zeros) rather than through three more matrices of its size.
    rhs = A.T @ np.asarray(values, float)
    normal = A.T @ A
    del A
    normal[np.diag_indices_from(normal)] += DAMPING
    # a matrix times its own transpose is exactly symmetric (numpy forms one triangle and
    # mirrors it), so its transpose is the same matrix in Fortran order, which the solver
    # factorises in place instead of in a copy
    coefs = solve(normal.T, rhs, assume_a="pos", overwrite_a=True) / scale[:, None]
    del normal
    # The columns share the sources' Green's functions at every cell: one block of them
    # (the Jacobian's rows at the cells, as harmonica's ``predict`` sums them) serves every
    # column, where ``predict`` per column evaluated them once per column.
    at = tuple(np.asarray(c, dtype=float).ravel() for c in at_m)
    out = np.empty((coefs.shape[1], at[0].size))
    for a in range(0, at[0].size, _PREDICT_ROWS):
        rows = tuple(c[a:a + _PREDICT_ROWS] for c in at)
        out[:, a:a + _PREDICT_ROWS] = (es.jacobian(rows, points) @ coefs).T
    return out


def write_anomaly(path: str | Path, grid: Grid, *, position_frame: str,
                  origin: GeodeticOrigin | None, magalign_version: str) -> Path:
    """Write ``anomaly.nc`` (NetCDF-4, CF-1.8, CONVENTIONS layout) atomically."""
    import xarray as xr

    dims = ("northing", "easting")
    data_vars: dict[str, Any] = {}
    for k, (name, axis) in enumerate((("B_east_nT", "east"), ("B_north_nT", "north"),
                                      ("B_up_nT", "up"))):
        data_vars[name] = (dims, grid.B_enu_nT[k].astype(np.float64), {
            "units": "nT", "long_name": f"restored magnetic field, {axis} component",
            "_FillValue": np.nan})
    data_vars["total_field_anomaly_nT"] = (dims, grid.total_field_anomaly_nT, {
        "units": "nT", "long_name": "total-field anomaly: |B| minus the magnitude of the "
        "background field", "_FillValue": np.nan})
    attrs: dict[str, Any] = {"Conventions": "CF-1.8",
                             "title": "magalign restored magnetic field grid"}
    if origin is not None:
        ee, nn = np.meshgrid(grid.easting_m, grid.northing_m)
        lat, lon, _ = local_enu_to_geodetic(
            np.column_stack([ee.ravel(), nn.ravel(), np.full(ee.size, grid.height_m)]), origin)
        data_vars["latitude"] = (dims, lat.reshape(ee.shape), {
            "units": "degrees_north", "standard_name": "latitude"})
        data_vars["longitude"] = (dims, lon.reshape(ee.shape), {
            "units": "degrees_east", "standard_name": "longitude"})
        attrs |= {"position_origin_lat_deg": float(origin.lat_deg),
                  "position_origin_lon_deg": float(origin.lon_deg),
                  "position_origin_height_m": float(origin.height_m)}
    attrs |= {"position_frame": str(position_frame), "height_m": float(grid.height_m),
              "spacing_m": float(grid.spacing_m), "mask_distance_m": float(grid.mask_distance_m),
              "background_B_enu_nT": np.asarray(grid.background_B_enu_nT, dtype=float),
              "method": grid.method, "magalign_version": magalign_version}
    frame = "east" if position_frame == "enu" else "x"
    coords = {
        "northing": ("northing", grid.northing_m, {
            "units": "m", "axis": "Y",
            "long_name": f"{'north' if frame == 'east' else 'y'} of the cell centre, "
                         f"{position_frame} frame"}),
        "easting": ("easting", grid.easting_m, {
            "units": "m", "axis": "X",
            "long_name": f"{frame} of the cell centre, {position_frame} frame"}),
    }
    ds = xr.Dataset(data_vars, coords=coords, attrs=attrs)
    try:
        with atomic_path(path) as tmp:
            ds.to_netcdf(tmp, engine="h5netcdf", format="NETCDF4")
    except OSError as exc:
        raise OutputError(f"cannot write anomaly.nc: {exc}", path=Path(path).parent) from exc
    return Path(path)


def read_grid(path: str | Path) -> dict[str, Any]:
    """Return an anomaly.nc's arrays and attributes as plain numpy (for the report, rerun)."""
    import xarray as xr

    out: dict[str, Any] = {}
    with xr.open_dataset(path, engine="h5netcdf") as ds:
        for k in ds.variables:
            out[str(k)] = np.asarray(ds[k].values)
        out["attrs"] = {str(k): v for k, v in ds.attrs.items()}
    return out


def magalign_version() -> str:
    """Return the installed magalign's version."""
    try:
        return metadata.version("magalign")
    except metadata.PackageNotFoundError:
        return "unknown"


# ----------------------------------------------------------------------------- campaign


def write_campaign_anomaly(out_dir: str | Path, grids: list[str | Path]) -> Path | None:
    """Write ``out_dir/anomaly.nc`` over the recordings' grids (a campaign with positions).

    Each recording's unmasked cells become data at their grid height; grids with a geodetic
    origin are brought into the local ENU frame of the first one (through their cells'
    latitude and longitude), local grids are taken in their own frame (one frame for all:
    the campaign's recordings share their attitude source). The union is gridded again by
    :func:`grid_survey`, with the finest line spacing of the recordings; its mask distance
    is the largest of the recordings' plus one cell.

    Returns None when fewer than two grids are given or their frames differ.
    """
    if len(grids) < 2:
        return None
    parts = [read_grid(g) for g in grids]
    frames = {str(p["attrs"].get("position_frame")) for p in parts}
    if len(frames) != 1:
        return None
    geo = all("position_origin_lat_deg" in p["attrs"] for p in parts)
    a0 = parts[0]["attrs"]
    origin = (GeodeticOrigin(float(a0["position_origin_lat_deg"]),
                             float(a0["position_origin_lon_deg"]),
                             float(a0["position_origin_height_m"])) if geo else None)
    ps, bs, lines = [], [], []
    for part in parts:
        a = part["attrs"]
        ee, nn = np.meshgrid(part["easting"], part["northing"])
        B = np.stack([part["B_east_nT"], part["B_north_nT"], part["B_up_nT"]], axis=-1)
        ok = np.isfinite(B).all(axis=-1)
        if origin is not None:
            pe = geodetic_to_local_enu(part["latitude"][ok], part["longitude"][ok],
                                       np.full(np.count_nonzero(ok), float(a["height_m"])
                                               + float(a["position_origin_height_m"])),
                                       origin)
            # the cells' heights are their grid height above the recording's origin
            pe[:, 2] = float(a["height_m"]) + float(a["position_origin_height_m"]) \
                - origin.height_m
        else:
            pe = np.column_stack([ee[ok], nn[ok], np.full(np.count_nonzero(ok),
                                                          float(a["height_m"]))])
        ps.append(pe)
        bs.append(B[ok])
        lines.append(float(a["mask_distance_m"]) / MASK_PER_LINE)
    p, B = np.concatenate(ps), np.concatenate(bs)
    line = min(lines)
    w, h = (np.ptp(p[:, :2], axis=0) + 2 * MASK_PER_LINE * line).tolist()
    spacing = _round_spacing(max(SPACING_PER_LINE * line, math.sqrt(w * h / MAX_CELLS)))
    bg = np.mean([np.asarray(pt["attrs"]["background_B_enu_nT"], dtype=float)
                  for pt in parts], axis=0)
    # the data are cells already within a recording's mask of its path: a campaign cell is
    # kept within one cell of them, so within that mask plus a cell of a path
    grid = grid_survey(p, B, bg, None, rule=(line, spacing, spacing))
    if grid is None:
        return None
    grid = dataclasses.replace(grid, mask_distance_m=max(lines) * MASK_PER_LINE + spacing)
    return write_anomaly(Path(out_dir) / "anomaly.nc", grid, position_frame=frames.pop(),
                         origin=origin, magalign_version=magalign_version())


# ----------------------------------------------------------------------------- process


def write_survey(out_dir: str | Path, recording: Any, sample: Any, calibration: Any,
                 diagnosis: Any, t0_ns: int) -> tuple[tuple[str, str], ...]:
    """Write ``targets.csv`` and ``anomaly.nc`` into ``out_dir`` for a recording with positions.

    Parameters
    ----------
    out_dir : path
        The recording's output folder.
    recording : Recording
        Its ``position`` series (None: nothing is written).
    sample : RestoreResult
        The restored rows (every row, or every k-th of a long recording).
    calibration : Calibration
        The final model (its background field).
    diagnosis : Diagnosis or None
        The located objects (``local_source`` findings).
    t0_ns : int
        The first magnetometer stamp.

    Returns
    -------
    tuple of (name, path)
        The files written.

    """
    pos = getattr(recording, "position", None)
    if pos is None or not len(pos) or sample is None or not len(sample.t_ns):
        return ()
    out = Path(out_dir)
    t = np.asarray(sample.t_ns, dtype=np.int64)
    # the tracked point's positions, as the diagnosis placed its sources against them
    p = pos.at(t)
    frame = str(getattr(pos.frame, "value", pos.frame))
    sources = located_sources(diagnosis)
    written: list[tuple[str, str]] = []
    rows = target_rows(one_row_per_object(sources), p, t, t0_ns, pos.origin)
    written.append(("targets.csv", str(write_targets(out / "targets.csv", rows))))
    grid = grid_survey(p, np.asarray(sample.enu_nT, dtype=float),
                       np.asarray(calibration.B_enu_nT, dtype=float), sources)
    if grid is not None:
        path = write_anomaly(out / "anomaly.nc", grid, position_frame=frame, origin=pos.origin,
                             magalign_version=magalign_version())
        written.append(("anomaly.nc", str(path)))
    return tuple(written)
