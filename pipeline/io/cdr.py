"""Vectorised decoding of ROS 2 CDR messages from the message definition stored in a file.

More in docs/modules.md, ``pipeline.io.cdr``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from pipeline.core.errors import SchemaError

#: primitive ROS 2 types: numpy little-endian dtype string and size in bytes
PRIMITIVES: dict[str, str] = {
    "bool": "u1",
    "byte": "u1",
    "char": "u1",
    "uint8": "u1",
    "int8": "i1",
    "uint16": "<u2",
    "int16": "<i2",
    "uint32": "<u4",
    "int32": "<i4",
    "uint64": "<u8",
    "int64": "<i8",
    "float32": "<f4",
    "float64": "<f8",
}

# builtin_interfaces types that some writers leave out of the stored definition
_BUILTIN_DEFS = {
    "builtin_interfaces/Time": "int32 sec\nuint32 nanosec\n",
    "builtin_interfaces/Duration": "int32 sec\nuint32 nanosec\n",
}

_SEPARATOR = re.compile(r"^=+\s*$", re.M)
_FIELD = re.compile(
    r"^\s*(?P<type>[A-Za-z_][\w/]*)(?:<=\d+)?(?P<array>\[(?P<bound><=)?(?P<n>\d*)\])?"
    r"\s+(?P<name>[A-Za-z_]\w*)\s*(?P<rest>.*)$"
)


@dataclass(frozen=True)
class Field:
    """One field of a message definition.

    Attributes
    ----------
    name : str
    type : str
        Primitive name, ``"string"``/``"wstring"``, or a normalised ``pkg/Type``.
    array : int or None
        ``None`` for a scalar, ``n >= 0`` for a fixed array ``T[n]``, ``-1`` for a sequence
        (``T[]`` or ``T[<=n]``).

    """

    name: str
    type: str
    array: int | None = None


def normalise_type(name: str) -> str:
    """``pkg/msg/Type`` -> ``pkg/Type`` (both spellings occur in stored definitions)."""
    parts = name.split("/")
    if len(parts) == 3 and parts[1] == "msg":
        return f"{parts[0]}/{parts[2]}"
    return name


def _parse_fields(text: str) -> list[Field]:
    fields: list[Field] = []
    for raw in text.splitlines():
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        m = _FIELD.match(line)
        if m is None:
            raise SchemaError(f"cannot parse message definition line {raw.strip()!r}")
        rest = m.group("rest").strip()
        if rest.startswith("="):
            continue  # a constant, not part of the wire format
        if m.group("type") in ("string", "wstring") and "=" in line.split()[0]:
            continue
        arr: int | None = None
        if m.group("array") is not None:
            arr = -1 if (m.group("bound") or m.group("n") == "") else int(m.group("n"))
        fields.append(Field(m.group("name"), m.group("type"), arr))
    return fields


def parse_definition(schema_name: str, text: str) -> dict[str, list[Field]]:
    """Parse a stored ROS 2 message definition into ``{normalised type: fields}``.

    Parameters
    ----------
    schema_name : str
        Name of the top-level type, e.g. ``"sensor_msgs/msg/MagneticField"``.
    text : str
        The concatenated ``.msg`` text (``MSG: pkg/Type`` sections split by ``====`` lines).

    Returns
    -------
    dict
        Every type in the text with its field list; field types are resolved to
        ``pkg/Type`` names (relative names resolved within the referring package).

    """
    top = normalise_type(schema_name)
    sections = _SEPARATOR.split(text)
    raw: dict[str, str] = {top: sections[0]}
    for sec in sections[1:]:
        lines = sec.strip("\n").splitlines()
        while lines and not lines[0].strip():
            lines.pop(0)
        if not lines:
            continue
        head = lines[0].strip()
        if not head.startswith("MSG:"):
            raise SchemaError(f"definition section of {schema_name} without a 'MSG:' line")
        raw[normalise_type(head[4:].strip())] = "\n".join(lines[1:])
    for k, v in _BUILTIN_DEFS.items():
        raw.setdefault(k, v)
    types: dict[str, list[Field]] = {}
    short: dict[str, list[str]] = {}
    for full in raw:
        short.setdefault(full.split("/")[-1], []).append(full)
    for full, body in raw.items():
        pkg = full.split("/")[0] if "/" in full else ""
        resolved = []
        for f in _parse_fields(body):
            t = f.type
            if t not in PRIMITIVES and t not in ("string", "wstring"):
                t = normalise_type(t)
                if "/" not in t:
                    if t == "Header":
                        t = "std_msgs/Header"
                    elif f"{pkg}/{t}" in raw:
                        t = f"{pkg}/{t}"
                    elif len(short.get(t, [])) == 1:
                        t = short[t][0]
                if t not in raw:
                    raise SchemaError(
                        f"{schema_name}: type {f.type} of field {f.name} is not defined in the "
                        "stored message definition"
                    )
            resolved.append(Field(f.name, t, f.array))
        types[full] = resolved
    return types


def gather_le(buf: NDArray[np.uint8], pos: NDArray[np.int64], dt: np.dtype) -> np.ndarray:
    """Read one little-endian ``dt`` value at each byte position ``pos`` of ``buf``.

    ``buf`` is viewed as overlapping ``itemsize``-byte records with a stride of one byte, so a
    single fancy index copies each value's bytes at once (about 4x faster than gathering an
    ``(N, itemsize)`` byte index).
    """
    k = dt.itemsize
    buf = np.ascontiguousarray(buf).reshape(-1)
    if buf.shape[0] < k:
        return np.zeros(0, dtype=dt) if pos.shape[0] == 0 else buf[pos]  # raises IndexError
    n = pos.shape[0]
    if n > 64:
        step = int(pos[1] - pos[0])
        p0 = int(pos[0])
        if (step > 0 and p0 >= 0 and p0 + step * (n - 1) + k <= buf.shape[0]
                and int(pos[-1]) == p0 + step * (n - 1) and bool((np.diff(pos) == step).all())):
            # evenly spaced (fields of records of one size laid side by side): a strided view
            # copied in order, which the caches serve (a fancy index of n values does not)
            return np.ndarray(shape=(n,), dtype=dt, buffer=buf, offset=p0,
                              strides=(step,)).copy()
    records: np.ndarray = np.ndarray(shape=(buf.shape[0] - k + 1,), dtype=f"V{k}", buffer=buf,
                                     strides=(1,))
    return records[pos].view(dt)


def _gather(buf: NDArray[np.uint8], pos: NDArray[np.int64], dtype: str, swap: NDArray[np.bool_]
            | None) -> np.ndarray:
    """Read one value of ``dtype`` at each byte position ``pos`` (vectorised)."""
    dt = np.dtype(dtype)
    k = dt.itemsize
    if k == 1:
        return buf[pos].view(dt.newbyteorder("<"))
    if swap is None or not swap.any():
        return gather_le(buf, pos, dt.newbyteorder("<"))
    raw = buf[pos[:, None] + np.arange(k)]
    if swap is not None and swap.any():
        raw[swap] = raw[swap, ::-1]
    return np.ascontiguousarray(raw).view(dt.newbyteorder("<")).reshape(-1)


class CdrLayout:
    """Field positions of CDR messages computed from a parsed definition.

    Parameters
    ----------
    schema_name : str
    definition : str
        Stored ``ros2msg`` text.

    """

    def __init__(self, schema_name: str, definition: str):
        self.schema_name = schema_name
        self.top = normalise_type(schema_name)
        self.types = parse_definition(schema_name, definition)

    def has_field(self, path: str) -> bool:
        """Whether a dotted field path exists (e.g. ``"header.stamp.sec"``)."""
        t = self.top
        for part in path.split("."):
            fs = {f.name: f for f in self.types.get(t, [])}
            if part not in fs:
                return False
            t = fs[part].type
        return True

    def decode(
        self, buf: NDArray[np.uint8], start: NDArray[np.int64], length: NDArray[np.int64],
        paths: list[str],
    ) -> dict[str, np.ndarray]:
        """Gather primitive fields of every message.

        Parameters
        ----------
        buf : ndarray of uint8
            Buffer holding the payloads (a decompressed chunk or a whole file).
        start : ndarray of int64, shape (N,)
            Offset of each CDR payload (its encapsulation header) in ``buf``.
        length : ndarray of int64, shape (N,)
            Payload lengths in bytes; a message too short for a field raises SchemaError.
        paths : list of str
            Dotted paths of the primitive (or fixed-array) fields wanted, e.g.
            ``["header.stamp.sec", "magnetic_field.x"]``.

        Returns
        -------
        dict
            ``path -> ndarray (N,)`` (or ``(N, n)`` for a fixed array of primitives).

        """
        start = np.asarray(start, dtype=np.int64)
        n = start.shape[0]
        if n == 0:
            return {p: np.zeros(0) for p in paths}
        if int(length.min()) < 4:
            raise SchemaError(f"{self.schema_name}: message shorter than its CDR header")
        kind = buf[start + 1]
        if buf[start].any() or not np.isin(kind, (0, 1)).all():
            raise SchemaError(
                f"{self.schema_name}: unsupported CDR encapsulation "
                f"{bytes(buf[start[0]:start[0] + 2]).hex()} (only plain CDR is read)"
            )
        # kind 1 = CDR little endian, 0 = big endian: swap those rows' bytes on gather
        swap = kind == 0 if (kind == 0).any() else None
        origin = start + 4  # alignment is relative to the end of the encapsulation header
        end = start + length
        wanted = set(paths)
        out: dict[str, np.ndarray] = {}
        pos = np.zeros(n, dtype=np.int64)

        def need_any(prefix: str) -> bool:
            return any(p == prefix or p.startswith(prefix + ".") for p in wanted - out.keys())

        def walk(tname: str, prefix: str, pos: np.ndarray) -> np.ndarray:
            for f in self.types[tname]:
                if not (wanted - out.keys()):
                    return pos
                path = f"{prefix}{f.name}"
                pos = field(f, path, pos)
            return pos

        def check(p_end: np.ndarray, path: str) -> None:
            if (origin + p_end > end).any():
                raise SchemaError(
                    f"{self.schema_name}: messages too short for field {path}: the stored "
                    "definition does not match the data"
                )

        def read(dtype: str, p: np.ndarray) -> np.ndarray:
            return _gather(buf, origin + p, dtype, swap)

        def prim_size(t: str) -> int:
            return np.dtype(PRIMITIVES[t]).itemsize

        def field(f: Field, path: str, pos: np.ndarray) -> np.ndarray:
            t = f.type
            if f.array is None:
                if t in PRIMITIVES:
                    k = prim_size(t)
                    pos = (pos + (k - 1)) // k * k
                    if path in wanted:
                        check(pos + k, path)
                        out[path] = read(PRIMITIVES[t], pos)
                    return pos + k
                if t in ("string", "wstring"):
                    pos = (pos + 3) // 4 * 4
                    check(pos + 4, path)
                    ln = read("<u4", pos).astype(np.int64)
                    if t == "wstring":
                        ln = ln * 4
                    check(pos + 4 + ln, path)
                    if path in wanted:
                        # (N, 2): absolute start in buf and length (with its NUL) of the string
                        out[path] = np.stack([origin + pos + 4, ln], axis=-1)
                    return pos + 4 + ln
                return walk(t, path + ".", pos)
            # arrays
            if f.array >= 0:
                count = None
            else:
                pos = (pos + 3) // 4 * 4
                check(pos + 4, path)
                count = read("<u4", pos).astype(np.int64)
                pos = pos + 4
            if t in PRIMITIVES:
                k = prim_size(t)
                pos = (pos + (k - 1)) // k * k
                if count is None:
                    if path in wanted:
                        check(pos + k * f.array, path)
                        cols = [read(PRIMITIVES[t], pos + k * j) for j in range(f.array)]
                        out[path] = np.stack(cols, axis=-1) if cols else np.zeros((n, 0))
                    return pos + k * f.array
                if path in wanted:
                    raise SchemaError(f"{self.schema_name}: cannot gather sequence field {path}")
                return pos + k * count
            # arrays of strings or messages: only passable when their size is fixed or we
            # are past every wanted field
            if not need_any(path) and not (wanted - out.keys()):
                return pos
            reps = f.array if count is None else None
            if reps is None:
                assert count is not None  # reps is None only for a sequence
                if not (count == count[0]).all():
                    raise SchemaError(
                        f"{self.schema_name}: field {path} is a sequence of varying length "
                        "before a needed field; not supported"
                    )
                reps = int(count[0])
            for _ in range(reps):
                sub = Field(f.name, t, None)
                pos = field(sub, path, pos) if t in ("string", "wstring") else walk(
                    t, path + ".", pos)
            return pos

        walk(self.top, "", pos)
        missing = [p for p in paths if p not in out]
        if missing:
            raise SchemaError(
                f"{self.schema_name}: field(s) {', '.join(missing)} not in the stored definition"
            )
        return out


def stamp_ns(sec: np.ndarray, nanosec: np.ndarray) -> NDArray[np.int64]:
    """``builtin_interfaces/Time`` (int32 sec, uint32 nanosec) -> int64 ns."""
    return sec.astype(np.int64) * 1_000_000_000 + nanosec.astype(np.int64)


@dataclass(frozen=True)
class UniformPlan:
    """Where the wanted fields sit in messages that all share one layout (:meth:`CdrLayout.plan`).

    Offsets are from the end of the encapsulation header. ``fields`` maps a path to
    ``(kind, offset, dtype, count)``: kind ``"prim"`` (count unused), ``"array"`` (a fixed
    array of ``count`` primitives) or ``"string"`` (``count``: its length with the NUL).
    ``invariants`` are the offsets of the ``uint32`` string lengths and sequence counts the
    positions depend on: messages whose values there equal the template's (and whose length
    and encapsulation equal its) have every field at the same place. ``end`` is the offset
    just past the last wanted field.
    """

    fields: dict[str, tuple[str, int, str, int]]
    invariants: tuple[int, ...]
    end: int


class _NoPlan(Exception):
    pass


def uniform_plan(layout: CdrLayout, payload: bytes, paths: list[str]) -> UniformPlan | None:
    """Return the field positions of one little-endian CDR payload, walked as ``decode`` does.

    None when :meth:`CdrLayout.decode` would refuse the message or when a wanted field is not
    a fixed-size primitive, string or fixed array (the caller then uses :meth:`decode`).
    """
    size = len(payload)
    if size < 4 or payload[0] != 0 or payload[1] != 1:
        return None
    wanted = set(paths)
    out: dict[str, tuple[str, int, str, int]] = {}
    inv: list[int] = []

    def check(p_end: int) -> None:
        if 4 + p_end > size:
            raise _NoPlan

    def u4(p: int) -> int:
        return int.from_bytes(payload[4 + p : 8 + p], "little")

    def walk(tname: str, prefix: str, pos: int) -> int:
        for f in layout.types[tname]:
            if not (wanted - out.keys()):
                return pos
            pos = field(f, f"{prefix}{f.name}", pos)
        return pos

    def field(f: Field, path: str, pos: int) -> int:
        t = f.type
        if f.array is None:
            if t in PRIMITIVES:
                k = np.dtype(PRIMITIVES[t]).itemsize
                pos = (pos + (k - 1)) // k * k
                if path in wanted:
                    check(pos + k)
                    out[path] = ("prim", pos, PRIMITIVES[t], 1)
                return pos + k
            if t in ("string", "wstring"):
                pos = (pos + 3) // 4 * 4
                check(pos + 4)
                inv.append(pos)
                ln = u4(pos) * (4 if t == "wstring" else 1)
                check(pos + 4 + ln)
                if path in wanted:
                    out[path] = ("string", pos + 4, "", ln)
                return pos + 4 + ln
            return walk(t, path + ".", pos)
        count = None
        if f.array < 0:
            pos = (pos + 3) // 4 * 4
            check(pos + 4)
            inv.append(pos)
            count = u4(pos)
            pos += 4
        if t in PRIMITIVES:
            k = np.dtype(PRIMITIVES[t]).itemsize
            pos = (pos + (k - 1)) // k * k
            if count is None:
                if path in wanted:
                    check(pos + k * f.array)
                    out[path] = ("array", pos, PRIMITIVES[t], f.array)
                return pos + k * f.array
            if path in wanted:
                raise _NoPlan  # decode refuses a wanted sequence
            return pos + k * count
        if not (wanted - out.keys()):
            return pos
        for _ in range(f.array if count is None else count):
            pos = (field(Field(f.name, t, None), path, pos) if t in ("string", "wstring")
                   else walk(t, path + ".", pos))
        return pos

    try:
        end = walk(layout.top, "", 0)
    except _NoPlan:
        return None
    if any(p not in out for p in paths):
        return None
    return UniformPlan(out, tuple(inv), end)


def decode_uniform(raw: NDArray[np.uint8], n: int, stride: int, origin: int,
                   plan: UniformPlan, paths: list[str]) -> dict[str, np.ndarray]:
    """:meth:`CdrLayout.decode` of ``n`` messages laid ``stride`` bytes apart in ``raw``.

    Every message shares ``plan`` (checked by the caller), the first one's encapsulation
    header ends at ``origin``: each field is one strided copy. The arrays equal
    :meth:`CdrLayout.decode`'s, dtypes included; a string's ``(N, 2)`` start and length
    refer to ``raw``.
    """
    out: dict[str, np.ndarray] = {}
    for path in paths:
        kind, off, dtype, count = plan.fields[path]
        if kind == "string":
            s = np.empty((n, 2), dtype=np.int64)
            s[:, 0] = np.arange(origin + off, origin + off + n * stride, stride,
                                dtype=np.int64)[:n]
            s[:, 1] = count
            out[path] = s
            continue
        dt = np.dtype(dtype).newbyteorder("<")
        k = dt.itemsize

        def col(o: int, dt: np.dtype = dt) -> np.ndarray:
            return np.ndarray(shape=(n,), dtype=dt, buffer=raw, offset=origin + o,
                              strides=(stride,)).copy()

        if kind == "prim":
            out[path] = col(off)
        else:
            cols = [col(off + k * j) for j in range(count)]
            out[path] = np.stack(cols, axis=-1) if cols else np.zeros((n, 0))
    return out
