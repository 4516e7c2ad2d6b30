"""MCAP message decoding.

The supported message types by role (``MAG_TYPES``, ``ATTITUDE_TYPES``, ``TURNTABLE_TYPES``,
``POSITION_TYPES``, from ``schemas.MESSAGE_TYPES``), message records decoded in batches
straight into numpy (CDR layouts from the stored definitions, JSON), WGS-84 fixes to local
ENU and back, and the channel of each role chosen.
"""

from __future__ import annotations

import itertools
import json
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any, Literal, overload

import jsonschema
import numpy as np
from numpy.typing import NDArray

from pipeline.core.errors import (
    ChannelError,
    SchemaError,
)
from pipeline.core.geometry import li2020_euler_to_quat, novatel_to_quat
from pipeline.core.recording import (
    GeodeticOrigin,
    Role,
)
from pipeline.io.cdr import (
    CdrLayout,
    UniformPlan,
    decode_uniform,
    normalise_type,
    stamp_ns,
    uniform_plan,
)
from pipeline.io.mcap_format import Opcode
from pipeline.io.mcap_scan import (
    BATCH_BYTES,
    ChannelRecord,
    ChunkRecord,
    Scan,
    compact_records,
    copy_ranges,
    decompressed_then,
    join_blocks,
    record_columns,
    release_pages,
    select_messages,
)
from schemas import MESSAGE_TYPES, MessageRole, types_of

#: message types by role, as normalised schema names (``pkg/Type`` or magalign.*), from the one
#: table of supported types (``schemas.MESSAGE_TYPES``)
MAG_TYPES = tuple(MESSAGE_TYPES[n].short_name for n in types_of(MessageRole.MAGNETOMETER))


ATTITUDE_TYPES = tuple(MESSAGE_TYPES[n].short_name for n in types_of(MessageRole.ATTITUDE))


TURNTABLE_TYPES = tuple(MESSAGE_TYPES[n].short_name for n in types_of(MessageRole.TURNTABLE))


POSITION_TYPES = tuple(MESSAGE_TYPES[n].short_name for n in types_of(MessageRole.POSITION))


# CDR field paths of the orientation and of the position an attitude message carries (the
# position is read when the stored definition has it); geodetic fixes (INSPVA, NavSatFix) are
# converted to local ENU after sorting (origin: the first valid fix)
_CDR_QUAT = {t.short_name: t.quaternion for t in MESSAGE_TYPES.values() if t.quaternion}


_CDR_POSITION = {t.short_name: t.position for t in MESSAGE_TYPES.values() if t.position}


_CDR_GEODETIC = {t.short_name: t.geodetic for t in MESSAGE_TYPES.values() if t.geodetic}


_CDR_FIX_STATUS = {t.short_name: t.fix_status for t in MESSAGE_TYPES.values() if t.fix_status}


#: WGS84 semi-major axis (m) and first eccentricity squared
WGS84_A_M = 6378137.0


WGS84_E2 = 6.69437999014e-3


# --------------------------------------------------------------------------- decoding
@dataclass
class DecodedColumns:
    """Decoded columns of one channel (stamps in file order)."""

    t_ns: np.ndarray
    # (N,3) nT | (N,4) q_enu_body | (N,) turntable deg | (N,3) position fix (as `position`)
    values: np.ndarray
    log_time_ns: np.ndarray
    frame_id: str = ""
    # (N, 3): metres, or lat deg, lon deg, ellipsoidal height m (NaN rows: no valid fix)
    position: np.ndarray | None = None
    position_kind: str = ""  # "local" (metres, the source's frame) or "geodetic"

    def take(self, idx: np.ndarray, values: np.ndarray | None = None) -> DecodedColumns:
        """Rows ``idx`` (mask or indices) of every column; ``values`` replaces the values."""
        v = self.values[idx] if values is None else values
        pos = None if self.position is None else self.position[idx]
        return DecodedColumns(self.t_ns[idx], v, self.log_time_ns[idx], self.frame_id, pos,
                        self.position_kind)


def _valid_fixes(lat_deg: np.ndarray, lon_deg: np.ndarray, h_m: np.ndarray) -> np.ndarray:
    """Rows holding a usable WGS-84 fix: finite, latitude within +-90 deg, longitude +-180 deg."""
    with np.errstate(invalid="ignore"):
        return (np.isfinite(lat_deg) & np.isfinite(lon_deg) & np.isfinite(h_m)
                & (np.abs(lat_deg) <= 90.0) & (np.abs(lon_deg) <= 180.0))


def first_valid_fix(lat_deg: np.ndarray, lon_deg: np.ndarray, h_m: np.ndarray
                    ) -> GeodeticOrigin | None:
    """Return the first usable fix of a series of geodetic fixes, or None without any.

    Parameters
    ----------
    lat_deg, lon_deg : ndarray, shape (N,)
        WGS-84 latitude and longitude, degrees, in the order of the series (sorted stamps).
    h_m : ndarray, shape (N,)
        Height above the WGS-84 ellipsoid, m.

    """
    lat, lon, h = (np.asarray(a, dtype=float).reshape(-1) for a in (lat_deg, lon_deg, h_m))
    ok = _valid_fixes(lat, lon, h)
    if not ok.any():
        return None
    i0 = int(np.argmax(ok))
    return GeodeticOrigin(float(lat[i0]), float(lon[i0]), float(h[i0]))


def geodetic_to_local_enu(lat_deg: np.ndarray, lon_deg: np.ndarray, h_m: np.ndarray,
                          origin: GeodeticOrigin | None = None) -> np.ndarray:
    """Local ENU positions (N, 3), m, of WGS-84 geodetic fixes: exact, through ECEF.

    Each fix is taken to Earth-centred Earth-fixed coordinates on the WGS-84 ellipsoid
    (prime-vertical radius ``N = a / sqrt(1 - e^2 sin^2 lat)``) and the difference from the
    origin is rotated into its east, north, up axes. No flat-earth approximation: a point
    1 km away at the origin's height is 7.8 cm below its Up = 0 plane (Earth curvature,
    ``d^2 / (2 R)``), as it is in any ENU frame. The differences are formed in closed form
    (sum-to-product identities) rather than by subtracting two ECEF vectors of 6,400 km, so
    a displacement keeps its own relative precision (nanometres, not the ~1e-9 m rounding of
    the Earth's radius).

    Parameters
    ----------
    lat_deg, lon_deg : ndarray, shape (N,)
        Latitude and longitude, degrees (north and east positive).
    h_m : ndarray, shape (N,)
        Height above the WGS-84 ellipsoid, m.
    origin : GeodeticOrigin, optional
        The point of ENU ``(0, 0, 0)``; default the first valid fix (:func:`first_valid_fix`).

    Returns
    -------
    ndarray, shape (N, 3)
        East, north, up, m. Rows of fixes that are not usable (non-finite, latitude beyond
        +-90 deg, longitude beyond +-180 deg) are NaN; all rows are NaN when there is no
        origin.

    """
    lat, lon, h = (np.asarray(a, dtype=float).reshape(-1) for a in (lat_deg, lon_deg, h_m))
    out = np.full((lat.shape[0], 3), np.nan)
    o = first_valid_fix(lat, lon, h) if origin is None else origin
    ok = _valid_fixes(lat, lon, h)
    if o is None or not ok.any():
        return out
    e2, a = WGS84_E2, WGS84_A_M
    phi0, h0 = np.radians(o.lat_deg), float(o.height_m)
    phi, dlam, hh = np.radians(lat[ok]), np.radians(lon[ok] - o.lon_deg), h[ok]
    dlam = (dlam + np.pi) % (2 * np.pi) - np.pi  # across the antimeridian
    s, c, s0, c0 = np.sin(phi), np.cos(phi), np.sin(phi0), np.cos(phi0)
    w, w0 = np.sqrt(1.0 - e2 * s**2), np.sqrt(1.0 - e2 * s0**2)
    n, n0 = a / w, a / w0
    half, mid = 0.5 * (phi - phi0), 0.5 * (phi + phi0)
    # N - N0 = a (w0 - w) / (w w0), with w0^2 - w^2 = e2 sin(phi + phi0) sin(phi - phi0)
    dn = a * e2 * np.sin(phi + phi0) * np.sin(phi - phi0) / ((w0 + w) * w * w0)
    dh = hh - h0
    dcos = -2.0 * np.sin(mid) * np.sin(half)  # cos(phi) - cos(phi0)
    dsin = 2.0 * np.cos(mid) * np.sin(half)  # sin(phi) - sin(phi0)
    # ECEF difference in the frame turned about z by the origin's longitude (x' towards the
    # origin's meridian, y' east there): the point is ((N + h) cos phi cos dlam,
    # (N + h) cos phi sin dlam, (N (1 - e2) + h) sin phi), the origin ((N0 + h0) cos phi0,
    # 0, (N0 (1 - e2) + h0) sin phi0)
    dx = ((n + hh) * c * (-2.0 * np.sin(0.5 * dlam) ** 2) + (dn + dh) * c
          + (n0 + h0) * dcos)
    dy = (n + hh) * c * np.sin(dlam)
    dz = (dn * (1.0 - e2) + dh) * s + (n0 * (1.0 - e2) + h0) * dsin
    out[ok, 0] = dy
    out[ok, 1] = -s0 * dx + c0 * dz
    out[ok, 2] = c0 * dx + s0 * dz
    return out


def local_enu_to_geodetic(p_enu_m: np.ndarray, origin: GeodeticOrigin
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return WGS-84 latitude, longitude (deg) and ellipsoidal height (m) of ENU points.

    The inverse of :func:`geodetic_to_local_enu` about ``origin`` (for writing fixes of a
    known path: the simulator, tests): ENU rotated into ECEF and added to the origin's ECEF
    position, then latitude by fixed-point iteration (``tan(lat) = Z / (p (1 - e2 N /
    (N + h)))``, converged to below 1e-15 rad within a few steps near the surface) and
    height ``p cos(lat) + Z sin(lat) - a sqrt(1 - e2 sin^2 lat)`` (well conditioned at every
    latitude).

    Parameters
    ----------
    p_enu_m : ndarray, shape (N, 3)
        East, north, up about ``origin``, m.
    origin : GeodeticOrigin
        The point of ENU ``(0, 0, 0)``.

    Returns
    -------
    lat_deg, lon_deg, h_m : ndarray, shape (N,)
        Longitude in [-180, 180) deg.

    """
    p = np.asarray(p_enu_m, dtype=float).reshape(-1, 3)
    e2, a = WGS84_E2, WGS84_A_M
    phi0, lam0, h0 = np.radians(origin.lat_deg), np.radians(origin.lon_deg), origin.height_m
    s0, c0, sl, cl = np.sin(phi0), np.cos(phi0), np.sin(lam0), np.cos(lam0)
    n0 = a / np.sqrt(1.0 - e2 * s0**2)
    x0 = np.array([(n0 + h0) * c0 * cl, (n0 + h0) * c0 * sl, (n0 * (1.0 - e2) + h0) * s0])
    # rows of the ECEF -> ENU rotation at the origin; ECEF = x0 + R.T @ enu
    r = np.array([[-sl, cl, 0.0], [-s0 * cl, -s0 * sl, c0], [c0 * cl, c0 * sl, s0]])
    x = x0 + p @ r
    xy = np.hypot(x[:, 0], x[:, 1])
    lat = np.arctan2(x[:, 2], xy * (1.0 - e2))
    for _ in range(6):
        n = a / np.sqrt(1.0 - e2 * np.sin(lat) ** 2)
        h = xy * np.cos(lat) + x[:, 2] * np.sin(lat) - a * np.sqrt(1.0 - e2 * np.sin(lat) ** 2)
        lat = np.arctan2(x[:, 2], xy * (1.0 - e2 * n / (n + h)))
    h = xy * np.cos(lat) + x[:, 2] * np.sin(lat) - a * np.sqrt(1.0 - e2 * np.sin(lat) ** 2)
    lon = np.degrees(np.arctan2(x[:, 1], x[:, 0]))
    lon = (lon + 180.0) % 360.0 - 180.0
    return np.degrees(lat), lon, h


class ChannelDecoder:
    """Decoder of one channel's payloads, built from the schema stored in the file."""

    def __init__(self, scan: Scan, ch: ChannelRecord):
        self.path = scan.path
        self.topic = ch.topic
        sch = scan.schemas.get(ch.schema_id)
        if sch is None:
            raise SchemaError(f"channel {ch.topic} refers to schema id {ch.schema_id}, which "
                              "the file does not define", path=scan.path)
        self.type = normalise_type(sch.name)
        self.encoding = ch.message_encoding
        self.layout: CdrLayout | None = None
        self.validator: Any = None
        if ch.message_encoding == "cdr":
            if sch.encoding != "ros2msg":
                raise SchemaError(f"channel {ch.topic}: schema encoding {sch.encoding!r} is "
                                  "not supported (only ros2msg)", path=scan.path)
            try:
                self.layout = CdrLayout(sch.name, sch.data.decode("utf-8"))
            except SchemaError as exc:
                raise SchemaError(exc.message, path=scan.path) from None
            except UnicodeDecodeError:
                raise SchemaError(f"channel {ch.topic}: schema text is not UTF-8",
                                  path=scan.path) from None
            self.paths = self._cdr_paths()
        elif ch.message_encoding == "json":
            if sch.encoding == "jsonschema" and sch.data:

                try:
                    schema_doc = json.loads(sch.data)
                    cls = jsonschema.validators.validator_for(schema_doc)
                    self.validator = cls(schema_doc)
                except (ValueError, jsonschema.SchemaError) as exc:
                    raise SchemaError(f"channel {ch.topic}: stored JSON Schema is invalid "
                                      f"({exc})", path=scan.path) from None
        else:
            raise SchemaError(f"channel {ch.topic}: message encoding {ch.message_encoding!r}"
                              " is not supported (cdr or json)", path=scan.path)

    def _cdr_paths(self) -> list[str]:
        assert self.layout is not None  # called for CDR channels, once the layout is built
        t = self.type
        if t == "sensor_msgs/MagneticField":
            return ["header.stamp.sec", "header.stamp.nanosec", "header.frame_id",
                    "magnetic_field.x", "magnetic_field.y", "magnetic_field.z"]
        if t == "sensor_msgs/Imu":
            return ["header.stamp.sec", "header.stamp.nanosec", "header.frame_id"] + [
                f"orientation.{k}" for k in "xyzw"]
        if t in _CDR_QUAT:
            q = _CDR_QUAT[t]
            out = ["header.stamp.sec", "header.stamp.nanosec"] + [f"{q}.{k}" for k in "xyzw"]
            pp = _CDR_POSITION.get(t)
            if pp is not None and self.layout.has_field(f"{pp}.x"):
                out += [f"{pp}.{k}" for k in "xyz"]
            return out
        if t == "novatel_oem7_msgs/INSPVA":
            out = ["header.stamp.sec", "header.stamp.nanosec", "roll", "pitch", "azimuth"]
            fix = _CDR_GEODETIC[t]
            if all(self.layout.has_field(k) for k in fix):
                out += list(fix)
            return out
        if t in POSITION_TYPES:
            return (["header.stamp.sec", "header.stamp.nanosec", _CDR_FIX_STATUS[t]]
                    + list(_CDR_GEODETIC[t]))
        if t == "std_msgs/Float64":
            return ["data"]
        raise SchemaError(f"channel {self.topic}: message type {self.type} is not supported",
                          path=self.path, hint=_SUPPORTED_HINT)

    def decode(self, buf: NDArray[np.uint8], rec: np.ndarray) -> DecodedColumns:
        """Decode the channel's records of one decompressed chunk into columns."""
        buf, rec = compact_records(buf, rec)
        cols = record_columns(buf, rec)
        log = cols["log_time_ns"]
        if self.layout is not None:
            try:
                f = self.layout.decode(buf, cols["start"], cols["length"], self.paths)
            except SchemaError as exc:
                raise SchemaError(f"channel {self.topic}: {exc.message}",
                                  path=self.path) from None
            return self._from_cdr(f, log, buf)
        return self._from_json(buf, cols, log)

    def _from_cdr(self, f: dict[str, np.ndarray], log: np.ndarray, buf: np.ndarray
                  ) -> DecodedColumns:
        t = self.type
        if t == "std_msgs/Float64":
            return DecodedColumns(log, f["data"].astype(float), log)  # no header: log time
        t_ns = stamp_ns(f["header.stamp.sec"], f["header.stamp.nanosec"])
        if t == "sensor_msgs/MagneticField":
            v = np.stack([f[f"magnetic_field.{k}"] for k in "xyz"], axis=-1) * 1e9
            s0, n0 = f["header.frame_id"][0]
            frame = bytes(buf[s0 : s0 + max(n0 - 1, 0)]).decode("utf-8", "replace")
            return DecodedColumns(t_ns, v, log, frame)
        if t == "sensor_msgs/Imu":  # its frame_id names the IMU's own (body) frame
            s0, n0 = f["header.frame_id"][0]
            frame = bytes(buf[s0 : s0 + max(n0 - 1, 0)]).decode("utf-8", "replace")
            return DecodedColumns(t_ns, np.stack([f[f"orientation.{k}"] for k in "xyzw"], axis=-1),
                            log, frame)
        if t in _CDR_QUAT:
            qp = _CDR_QUAT[t]
            pp = _CDR_POSITION.get(t)
            pos = (np.stack([f[f"{pp}.{k}"] for k in "xyz"], axis=-1)
                   if pp is not None and f"{pp}.x" in f else None)
            return DecodedColumns(t_ns, np.stack([f[f"{qp}.{k}"] for k in "xyzw"], axis=-1), log,
                            position=pos, position_kind="local" if pos is not None else "")
        if t in POSITION_TYPES:
            # a fix the receiver flags as none (NavSatStatus.status < 0), non-finite or out of
            # range is a lost position: a NaN row, kept so that the stamps stay the channel's
            fix = np.stack([f[k] for k in _CDR_GEODETIC[t]], axis=-1).astype(float)
            lost = (f[_CDR_FIX_STATUS[t]] < 0) | ~_valid_fixes(fix[:, 0], fix[:, 1], fix[:, 2])
            fix[lost] = np.nan
            return DecodedColumns(t_ns, fix, log, position=fix, position_kind="geodetic")
        q = novatel_to_quat(f["roll"], f["pitch"], f["azimuth"])
        geo = _CDR_GEODETIC[t]
        if geo[0] in f:
            fix = np.stack([f[k] for k in geo], axis=-1).astype(float)
            return DecodedColumns(t_ns, q, log, position=fix, position_kind="geodetic")
        return DecodedColumns(t_ns, q, log)

    def _from_json(self, buf: np.ndarray, cols: dict, log: np.ndarray) -> DecodedColumns:
        joined = copy_ranges(buf, cols["start"], cols["length"], sep=ord(","))
        try:
            text = b"[" + joined[:-1].tobytes() + b"]"
            objs = json.loads(text)
        except ValueError as exc:
            raise SchemaError(f"channel {self.topic}: messages are not valid JSON ({exc})",
                              path=self.path) from None
        if self.validator is not None and objs:
            # a sample (first, middle, last) is validated: enough to catch a wrong layout
            for o in (objs[0], objs[len(objs) // 2], objs[-1]):
                err = next(iter(self.validator.iter_errors(o)), None)
                if err is not None:
                    raise SchemaError(f"channel {self.topic}: message does not match the "
                                      f"stored JSON Schema: {err.message}", path=self.path)
        t = self.type
        try:
            t_ns = (np.array([o["t_ns"] for o in objs], dtype=np.int64)
                    if objs and "t_ns" in objs[0] else log)
            if t == "magalign.Magnetometer":
                v = np.array([o["mag_nT"] for o in objs], dtype=float).reshape(-1, 3)
                frame = str(objs[0].get("frame_id", "")) if objs else ""
                return DecodedColumns(t_ns, v, log, frame)
            if t == "magalign.AttitudeQuaternion":
                q = np.array([o["q_enu_body"] for o in objs], dtype=float).reshape(-1, 4)
                return DecodedColumns(t_ns, q, log)
            if t == "magalign.AttitudeEuler":
                hpr = np.array([[o["heading_deg"], o["pitch_deg"], o["roll_deg"]]
                                for o in objs], dtype=float).reshape(-1, 3)
                r = np.radians(hpr)
                return DecodedColumns(t_ns, li2020_euler_to_quat(r[:, 0], r[:, 1], r[:, 2]), log)
            if t == "magalign.Turntable":
                return DecodedColumns(t_ns, np.array([o["angle_deg"] for o in objs], dtype=float),
                                log)
        except (KeyError, TypeError, ValueError) as exc:
            raise SchemaError(f"channel {self.topic}: message lacks field {exc}",
                              path=self.path) from None
        raise SchemaError(f"channel {self.topic}: message type {t} is not supported",
                          path=self.path, hint=_SUPPORTED_HINT)


_SUPPORTED_HINT = "supported: " + ", ".join(MAG_TYPES + ATTITUDE_TYPES + TURNTABLE_TYPES
                                             + POSITION_TYPES)


# --------------------------------------------------------------------------- uniform records
#: bytes of a Message record before its payload: opcode, length, channel id, sequence, log and
#: publish times
_RECORD_HEAD = 31


@dataclass(frozen=True)
class _Shape:
    """One layout of a channel's message records: every wanted field at a fixed place.

    Records of one length whose opcode, length and channel id, CDR encapsulation and string
    lengths / sequence counts equal the template's have their wanted fields at the offsets
    of ``plan``; only their first ``width`` bytes are needed (the prefix up to the last
    wanted field). ``checked`` is a structured dtype of ``width`` bytes whose fields are
    those bytes, ``template`` the template's values: one comparison checks a whole chunk.
    """

    decoder: ChannelDecoder
    plan: UniformPlan
    width: int
    record: int
    checked: np.dtype
    template: np.ndarray

    def rows(self, buf: NDArray[np.uint8], off: np.ndarray) -> np.ndarray | None:
        """Return the first ``width`` bytes of the records at ``off`` (sorted), or None.

        None also when a record is not whole inside ``buf``: the caller then validates the
        offsets one by one (:func:`select_messages`) and reads them the general way.
        """
        n = len(buf)
        if int(off[0]) < 0 or int(off[-1]) + self.record > n:
            return None
        w = self.width
        view: np.ndarray = np.ndarray(shape=(n - w + 1,), dtype=f"V{w}", buffer=buf,
                                      strides=(1,))
        rows = view[off]
        if not bool((rows.view(self.checked) == self.template).all()):
            return None
        return rows

    def decode(self, rows: np.ndarray) -> DecodedColumns:
        """:meth:`ChannelDecoder.decode` of records gathered by :meth:`rows` (the same arrays)."""
        raw = rows.view(np.uint8)
        n, w = len(rows), self.width
        dec = self.decoder
        f = decode_uniform(raw, n, w, _RECORD_HEAD + 4, self.plan, dec.paths)
        log = np.ndarray(shape=(n,), dtype="<u8", buffer=raw, offset=15,
                         strides=(w,)).astype(np.int64)
        return dec._from_cdr(f, log, raw)

    def columns(self, rows: np.ndarray) -> DecodedColumns:
        """:meth:`decode`, through :meth:`decode_into` for the types it writes directly."""
        width = self.direct
        if not width:
            return self.decode(rows)
        n = len(rows)
        t, v, log = np.empty(n, np.int64), np.empty((n, width)), np.empty(n, np.int64)
        return DecodedColumns(t, v, log, self.decode_into(rows, t, v, log))

    @property
    def direct(self) -> int:
        """Columns of the values :meth:`decode_into` writes (0: use :meth:`decode`)."""
        d = _DIRECT.get(self.decoder.type)
        return len(d[1]) if d is not None else 0

    def decode_into(self, rows: np.ndarray, t: np.ndarray, v: np.ndarray, log: np.ndarray
                    ) -> str:
        """:meth:`decode` for the types of ``_DIRECT``, written straight into output arrays.

        ``t``, ``v`` and ``log`` (``len(rows)`` rows each) receive the stamps, values and log
        times :meth:`ChannelDecoder._from_cdr` computes, with the same arithmetic in place (no
        temporary arrays); returns the first message's frame id.
        """
        raw = rows.view(np.uint8)
        n, w = len(rows), self.width
        fields = self.plan.fields
        base = _RECORD_HEAD + 4

        def col(path: str) -> np.ndarray:
            _, off, dt, _ = fields[path]
            return np.ndarray(shape=(n,), dtype=np.dtype(dt).newbyteorder("<"), buffer=raw,
                              offset=base + off, strides=(w,))

        t[...] = col("header.stamp.sec")  # stamp_ns, in place
        t *= 1_000_000_000
        t += col("header.stamp.nanosec")
        prefix, axes, scale = _DIRECT[self.decoder.type]
        for j, k in enumerate(axes):
            v[:, j] = col(f"{prefix}.{k}")
        if scale is not None:
            v *= scale
        log[...] = np.ndarray(shape=(n,), dtype="<u8", buffer=raw, offset=15, strides=(w,))
        _, off, _, ln = fields["header.frame_id"]
        s0 = base + off
        return bytes(raw[s0 : s0 + max(ln - 1, 0)]).decode("utf-8", "replace")


#: types :meth:`_Shape.decode_into` writes straight into the output columns: the value
#: field, its components and the factor to nT (as :meth:`ChannelDecoder._from_cdr`)
_DIRECT: dict[str, tuple[str, str, float | None]] = {
    "sensor_msgs/MagneticField": ("magnetic_field", "xyz", 1e9),
    "sensor_msgs/Imu": ("orientation", "xyzw", None),
}


def _shape_at(decoder: ChannelDecoder, cid: int, buf: NDArray[np.uint8], o: int) -> _Shape | None:
    """Return the :class:`_Shape` of the record at ``o``, or None.

    None when it is not a whole record of channel ``cid`` or its layout is not one
    :func:`decode_uniform` reads.
    """
    n = len(buf)
    if decoder.layout is None or o < 0 or o + _RECORD_HEAD > n or buf[o] != Opcode.MESSAGE:
        return None
    head = buf[o : o + 11].tobytes()
    length = int.from_bytes(head[1:9], "little")
    if (length < 22 or length > n - 9 - o
            or int.from_bytes(head[9:11], "little") != cid):
        return None
    payload = buf[o + _RECORD_HEAD : o + 9 + length].tobytes()
    plan = uniform_plan(decoder.layout, payload, decoder.paths)
    if plan is None:
        return None
    width = _RECORD_HEAD + 4 + plan.end
    if -(-width // 8) * 8 <= 9 + length:
        width = -(-width // 8) * 8  # rows of whole words: their fields can be aligned
    # opcode and length (bytes 0-8), channel id (9-10), CDR encapsulation (31-32), and the
    # lengths / counts the field positions depend on
    fields = [(0, "<u8"), (7, "<u4"), (_RECORD_HEAD, "<u2")] + [
        (_RECORD_HEAD + 4 + p, "<u4") for p in plan.invariants]
    checked = np.dtype({"names": [f"f{i}" for i in range(len(fields))],
                        "formats": [f for _, f in fields],
                        "offsets": [o for o, _ in fields], "itemsize": width})
    template = np.frombuffer(buf[o : o + width].tobytes(), dtype=checked)
    return _Shape(decoder, plan, width, 9 + length, checked, template)


class _Uniform:
    """The fast path's state for one CDR channel: the shape of its last chunk's records."""

    def __init__(self, decoder: ChannelDecoder, cid: int):
        self.decoder = decoder
        self.cid = cid
        self.shape: _Shape | None = None

    def rows(self, buf: NDArray[np.uint8], off: np.ndarray
             ) -> tuple[np.ndarray, _Shape] | None:
        """Return the records at ``off`` as rows of one shape, or None (read the general way)."""
        if self.shape is not None:
            rows = self.shape.rows(buf, off)
            if rows is not None:
                return rows, self.shape
        shape = _shape_at(self.decoder, self.cid, buf, int(off[0]))
        if shape is None:
            return None
        self.shape = shape
        rows = shape.rows(buf, off)
        return None if rows is None else (rows, shape)


def _aligned_rows(parts: list[np.ndarray], width: int) -> np.ndarray:
    """Join rows of ``width`` bytes so that their CDR payloads start on 8-byte boundaries.

    A payload's fields are aligned relative to its start (``_RECORD_HEAD + 4`` bytes into
    the row): with rows of a multiple of 8 bytes starting 5 bytes into a fresh buffer, every
    8-byte field of every row is aligned, and numpy copies aligned values faster (about a
    third less time for the field columns).
    """
    n = sum(len(p) for p in parts)
    shift = (-(_RECORD_HEAD + 4)) % 8
    raw = np.empty(n * width + 8, dtype=np.uint8)
    out = raw[shift : shift + n * width].view(f"V{width}")
    np.concatenate(parts, out=out)
    return out


def _batches(scan: Scan, want: set[int], decoders: dict[int, ChannelDecoder],
             max_messages: int = 0
             ) -> Iterator[tuple[NDArray[np.uint8] | None, dict[int, Any], bool]]:
    """:func:`iter_blocks` with ``BATCH_BYTES``, reading uniform records the fast way.

    ``max_messages`` > 0 also ends a batch at the first chunk that brings the wanted
    messages since the last such end to that many: a range's end, where the ranges of
    :func:`pipeline.io.mcap_read.iter_recording_chunks` end. The third item of what is
    yielded says whether a range ends with it (messages outside chunks, yielded first,
    join the first range).

    Yields ``(buffer, {channel id: record offsets}, ends)`` as :func:`iter_blocks` does, or
    ``(None, {channel id: [(rows, shape), ...]}, ends)`` for a batch whose chunks all hold records
    of one shape per channel (:class:`_Shape`): only the bytes up to the last wanted field of
    each record are gathered, once, from the decompressed chunk, and every field is then a
    strided copy of those rows. The batches, the chunks' checks, the problems
    noted and the decoded arrays are those of :func:`iter_blocks` and
    :meth:`ChannelDecoder.decode`: a chunk whose records differ is selected by
    :func:`select_messages`
    (which validates each offset and walks a chunk whose index is damaged), and the runs of
    such chunks in a batch are yielded as blocks decoded the general way, in file order
    between the runs read the fast way.
    """
    for cid in sorted(want & scan.top_messages.keys()):
        yield scan.buf, {cid: np.asarray(scan.top_messages[cid], dtype=np.int64)}, False
    fast = {cid: _Uniform(decoders[cid], cid) for cid in want
            if decoders[cid].layout is not None}
    # a chunk read the fast way keeps only its gathered rows; one read the general way, its
    # decompressed bytes
    entries: list[tuple[bytes | None, dict[int, np.ndarray], dict[int, Any] | None]] = []
    size = count = 0
    todo = [ch for ch in scan.chunks
            if not ch.bad and ch.index and (want & ch.index.keys())]

    def uniform(run: list[dict[int, Any]]) -> dict[int, Any]:
        groups: dict[int, list[tuple[list[np.ndarray], _Shape]]] = {}
        for got in run:
            for cid, (rows, shape) in got.items():
                gs = groups.setdefault(cid, [])
                if gs and gs[-1][1] is shape:
                    gs[-1][0].append(rows)
                else:
                    gs.append(([rows], shape))
        return {cid: [(_aligned_rows(r, shape.width), shape) for r, shape in gs]
                for cid, gs in groups.items()}

    def flush(ends: bool) -> Iterator[tuple[NDArray[np.uint8] | None, dict[int, Any], bool]]:
        """Yield the batch's runs of chunks read alike, in file order; the last one ``ends``."""
        runs = [(fast_way, list(run)) for fast_way, run in
                itertools.groupby(entries, key=lambda e: e[2] is not None)]
        for k, (fast_way, es) in enumerate(runs):
            last = ends and k == len(runs) - 1
            if fast_way:
                yield None, uniform([got for _, _, got in es if got is not None]), last
            else:
                yield *join_blocks([b for b, _, _ in es if b is not None],
                                   [s for _, s, _ in es]), last

    def uniform_rows(ch: ChunkRecord, b: bytes) -> dict[int, Any] | None:
        """Return each wanted channel's records as rows of one shape, or None.

        Runs on the inflating thread: it only reads the chunk and the shapes (which any
        thread may replace: a shape is checked against every record it reads).
        """
        buf = np.frombuffer(b, dtype=np.uint8)
        assert ch.index is not None
        rows: dict[int, Any] = {}
        for cid in want & ch.index.keys():
            off = ch.index[cid]
            if not len(off):
                continue  # nothing to read (select_messages leaves it out too)
            r = fast[cid].rows(buf, off) if cid in fast else None
            if r is None:
                return None
            rows[cid] = r
        return rows

    for ch, b, got in decompressed_then(scan, todo, uniform_rows):
        if b is None:
            continue
        assert ch.index is not None
        sel = ({cid: ch.index[cid] for cid in got} if got is not None
               else select_messages(scan, ch, np.frombuffer(b, dtype=np.uint8), want))
        release_pages(scan, ch.data_start, ch.data_len)  # decompressed: the bytes are not needed
        if not sel:
            continue
        entries.append((None if got is not None else b, sel, got))
        size += len(b)
        count += sum(len(off) for off in sel.values())
        full = bool(max_messages) and count >= max_messages
        if full or size >= BATCH_BYTES:
            yield from flush(full)
            entries, size = [], 0
            count = 0 if full else count
    if entries:
        yield from flush(False)


def decoded_batches(scan: Scan, cids: list[int], max_messages: int
                    ) -> Iterator[tuple[dict[int, list[DecodedColumns]], bool]]:
    """Decode the channels ``cids`` in batches of whole chunks, saying where a range ends.

    A batch ends at ``BATCH_BYTES`` of decompressed chunks and at the first chunk that
    brings the messages of ``cids`` since the last range end to ``max_messages``, which
    ends a range; it is decoded at once, the fast way where its records are uniform
    (:func:`_batches`): per chunk, the per-call work of the general decoder costs ten times
    the decoding of a logger's few hundred messages. Yields ``({channel id: columns},
    ends)`` in file order, a batch at once or, where some of its chunks are read the
    general way, in runs of chunks read alike (a channel without a message in the part is
    left out); ``ends`` is True for the last part of a range.
    """
    decoders = {cid: ChannelDecoder(scan, scan.channels[cid]) for cid in cids}
    for buf, sel, ends in _batches(scan, set(cids), decoders, max_messages):
        out: dict[int, list[DecodedColumns]] = {}
        if buf is not None:
            for cid, rec in sel.items():
                out.setdefault(cid, []).append(decoders[cid].decode(buf, rec))
        else:
            for cid, groups in sel.items():
                out[cid] = [shape.columns(rows) for rows, shape in groups]
        yield out, ends


def decode_channels(scan: Scan, cids: list[int]) -> dict[int, DecodedColumns]:
    """Decode the channels ``cids`` of the whole file, chunk by chunk, into columns."""
    decoders = {cid: ChannelDecoder(scan, scan.channels[cid]) for cid in cids}
    # Upper bound of each channel's message count, from the message indexes: the columns are
    # filled chunk by chunk into arrays of that size (one copy of the data, where collecting
    # the chunks' columns and concatenating them held two).
    cap = {cid: len(scan.top_messages.get(cid, ())) + sum(
        len(ch.index.get(cid, ())) for ch in scan.chunks if not ch.bad and ch.index)
        for cid in cids}
    cols: dict[int, list[np.ndarray]] = {}
    fill = dict.fromkeys(cids, 0)
    frames: dict[int, str] = {}  # each channel's first message's, however it was batched
    kinds = dict.fromkeys(cids, "")

    def reserve(cid: int, k: int, like: list[tuple[tuple[int, ...], np.dtype]]
                ) -> list[np.ndarray]:
        """Return the columns of ``cid`` with room for ``k`` more rows (shapes, dtypes)."""
        i = fill[cid]
        if cid not in cols:
            cols[cid] = [np.empty((max(cap[cid], k),) + shape, dtype=dt) for shape, dt in like]
        elif i + k > cols[cid][0].shape[0]:  # more than indexed: grow
            cols[cid] = [np.concatenate([c[:i], np.empty((k,) + c.shape[1:], c.dtype)])
                         for c in cols[cid]]
        return cols[cid]

    def put(cid: int, d: DecodedColumns) -> None:
        k, i = len(d.t_ns), fill[cid]
        parts: tuple[np.ndarray, ...] = (d.t_ns, d.values, d.log_time_ns)
        if d.position is not None:
            parts += (d.position,)
            kinds[cid] = d.position_kind
        for c, a in zip(reserve(cid, k, [(a.shape[1:], a.dtype) for a in parts]), parts,
                        strict=True):
            c[i : i + k] = a
        fill[cid] = i + k
        frames.setdefault(cid, d.frame_id)

    for buf, sel, _ in _batches(scan, set(cids), decoders):
        if buf is not None:
            for cid, rec in sel.items():
                put(cid, decoders[cid].decode(buf, rec))
            continue
        for cid, groups in sel.items():
            for rows, shape in groups:
                put(cid, shape.columns(rows))
    out = {}
    for cid in cids:
        if cid not in cols:
            typ = decoders[cid].type
            if typ in POSITION_TYPES:  # no message: no fix, in the columns of one
                out[cid] = DecodedColumns(np.zeros(0, np.int64), np.zeros((0, 3)),
                                    np.zeros(0, np.int64), position=np.zeros((0, 3)),
                                    position_kind="geodetic")
                continue
            width = {"sensor_msgs/MagneticField": 3, "magalign.Magnetometer": 3}.get(typ, 4)
            shape = (0,) if typ in TURNTABLE_TYPES else (0, width)
            out[cid] = DecodedColumns(np.zeros(0, np.int64), np.zeros(shape), np.zeros(0, np.int64))
            continue
        n = fill[cid]
        t, v, log, *pos = (c if n == c.shape[0] else c[:n].copy() for c in cols[cid])
        out[cid] = DecodedColumns(t, v, log, frames.get(cid, ""), pos[0] if pos else None,
                                  kinds[cid])
    return out


# --------------------------------------------------------------------------- roles
#: what a channel's ``unit`` metadata may say for a turntable angle (none said: degrees)
ANGLE_UNITS = ("", "deg", "degree", "degrees")


def role_of(scan: Scan, ch: ChannelRecord) -> Role:
    """Return the role (magnetometer, attitude, position) a channel's schema type gives it."""
    sch = scan.schemas.get(ch.schema_id)
    t = normalise_type(sch.name) if sch else ""
    if t in MAG_TYPES:
        return Role.MAGNETOMETER
    if t in ATTITUDE_TYPES:
        return Role.ATTITUDE
    if t in TURNTABLE_TYPES:
        # a bare number is a turntable angle unless its channel says it is something else:
        # the field magnitude magalign writes into a corrected recording is a Float64 in nT
        unit = str((ch.metadata or {}).get("unit", "deg")).strip().lower()
        return Role.TURNTABLE if unit in ANGLE_UNITS else Role.OTHER
    if t in POSITION_TYPES:
        return Role.POSITION
    return Role.OTHER


def type_of(scan: Scan, ch: ChannelRecord) -> str:
    """Return the channel's schema name as stored in the file ("?" without a schema)."""
    sch = scan.schemas.get(ch.schema_id)
    return sch.name if sch else "?"


#: keyword of the reader and command-line option that choose each role's channel (None: the
#: command line has no option for it)
_OPTION: dict[Role, tuple[str, str | None]] = {
    Role.MAGNETOMETER: ("mag_topic", "--mag"),
    Role.ATTITUDE: ("attitude_topic", "--attitude"),
    Role.TURNTABLE: ("turntable_topic", "--turntable"),
    Role.POSITION: ("position_topic", None)}


_ROLE_TYPES = {Role.MAGNETOMETER: MAG_TYPES, Role.ATTITUDE: ATTITUDE_TYPES,
               Role.TURNTABLE: TURNTABLE_TYPES, Role.POSITION: POSITION_TYPES}


@overload
def pick_channel(scan: Scan, role: Role, topic: str | None, required: Literal[True]) -> int: ...


@overload
def pick_channel(scan: Scan, role: Role, topic: str | None, required: bool) -> int | None: ...


def pick_channel(scan: Scan, role: Role, topic: str | None, required: bool) -> int | None:
    """Channel id for a role: by explicit topic, else the single channel of a matching type."""
    opt, flag = _OPTION[role]
    if topic is not None:
        hits = [c for c in scan.channels.values() if c.topic == topic]
        if not hits:
            topics = ", ".join(sorted({c.topic for c in scan.channels.values()})) or "none"
            raise ChannelError(f"no channel with topic {topic} (topics: {topics})",
                               role=role.value, path=scan.path)
        c = hits[0]
        if normalise_type(type_of(scan, c)) not in _ROLE_TYPES[role]:
            raise SchemaError(f"channel {topic} has type {type_of(scan, c)}, which is not a "
                              f"supported {role.value} type", path=scan.path,
                              hint=_SUPPORTED_HINT)
        return c.id
    cands = [c for c in scan.channels.values() if role_of(scan, c) is role]
    if len(cands) > 1:
        names = " and ".join(sorted(c.topic for c in cands))
        how = f"{flag} TOPIC ({opt}=...)" if flag is not None else f"{opt}=TOPIC"
        raise ChannelError(f"two or more candidate {role.value} channels: {names}",
                           role=role.value, path=scan.path, hint=f"choose one with {how}")
    if not cands:
        if not required:
            return None
        listing = ", ".join(f"{c.topic} ({type_of(scan, c)})"
                            for c in scan.channels.values()) or "no channels"
        raise ChannelError(f"no {role.value} channel found (channels: {listing})",
                           role=role.value, path=scan.path, hint=_SUPPORTED_HINT)
    return cands[0].id
