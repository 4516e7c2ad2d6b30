"""Message schemas magalign reads and writes.

More in docs/modules.md, ``schemas``.
"""

from __future__ import annotations

import enum
import functools
import json
from dataclasses import dataclass
from importlib import resources
from typing import Any

from pipeline.core.errors import SchemaError


class MessageRole(str, enum.Enum):
    """What a message type carries for magalign."""

    MAGNETOMETER = "magnetometer"
    ATTITUDE = "attitude"
    TURNTABLE = "turntable"
    POSITION = "position"  # geodetic fixes of the platform (a GNSS receiver)
    OUTPUT = "output"  # written into the corrected MCAP only, never read as input


@dataclass(frozen=True)
class MessageType:
    """One supported message type: the single table every reader, writer and check uses.

    Attributes
    ----------
    name : str
        Full name as stored in an MCAP schema (``pkg/msg/Type``, or ``magalign.Name`` for
        magalign's JSON channels).
    role : MessageRole
    encoding : str
        ``"ros2"`` (CDR, schema ``ros2msg``) or ``"json"`` (schema ``jsonschema``).
    columns : tuple of str
        Columns the encoder (:func:`pipeline.io.messages.encode`) needs, with their units in the
        name (``mag_T``, ``q_xyzw``, ``roll_deg``...).
    quaternion, position : str or None
        Dotted CDR paths of the orientation and of a local position (metres, the source's
        own frame) the reader takes.
    geodetic : (str, str, str) or None
        CDR paths of a WGS-84 fix: latitude (deg), longitude (deg), ellipsoidal height (m);
        the reader converts it to local ENU metres about the first valid fix.
    fix_status : str or None
        CDR path of a fix status whose negative values mean "no fix" (``NavSatStatus``):
        those rows are read as lost positions.
    variants : tuple of (str or None)
        Layout variants with a stored definition (``None`` is the default layout).
    written : bool
        Whether magalign writes it (a stored schema ships in this package); read-only types
        (``nav_msgs/msg/Odometry``) are decoded from the definition stored in the file.

    """

    name: str
    role: MessageRole
    encoding: str
    columns: tuple[str, ...] = ()
    quaternion: str | None = None
    position: str | None = None
    geodetic: tuple[str, str, str] | None = None
    fix_status: str | None = None
    variants: tuple[str | None, ...] = (None,)
    written: bool = True

    @property
    def short_name(self) -> str:
        """``pkg/Type`` (the ``/msg/`` dropped), the form the reader matches schema names in."""
        return self.name.replace("/msg/", "/")


_R = MessageRole
#: Every message type magalign reads or writes, by name.
MESSAGE_TYPES: dict[str, MessageType] = {t.name: t for t in (
    MessageType("sensor_msgs/msg/MagneticField", _R.MAGNETOMETER, "ros2", ("mag_T",)),
    MessageType("magalign.Magnetometer", _R.MAGNETOMETER, "json", ("mag_nT",)),
    MessageType("sensor_msgs/msg/Imu", _R.ATTITUDE, "ros2", ("q_xyzw",),
                quaternion="orientation"),
    MessageType("geometry_msgs/msg/PoseStamped", _R.ATTITUDE, "ros2", ("q_xyzw",),
                quaternion="pose.orientation", position="pose.position"),
    MessageType("geometry_msgs/msg/QuaternionStamped", _R.ATTITUDE, "ros2", ("q_xyzw",),
                quaternion="quaternion"),
    MessageType("novatel_oem7_msgs/msg/INSPVA", _R.ATTITUDE, "ros2",
                ("roll_deg", "pitch_deg", "azimuth_deg"),
                geodetic=("latitude", "longitude", "height"),
                variants=(None, "no_nov_header", "novatel_header")),
    MessageType("nav_msgs/msg/Odometry", _R.ATTITUDE, "ros2", quaternion="pose.pose.orientation",
                position="pose.pose.position", written=False),
    MessageType("magalign.AttitudeQuaternion", _R.ATTITUDE, "json", ("q_xyzw",)),
    MessageType("magalign.AttitudeEuler", _R.ATTITUDE, "json",
                ("heading_deg", "pitch_deg", "roll_deg")),
    MessageType("std_msgs/msg/Float64", _R.TURNTABLE, "ros2", ("value",)),
    MessageType("sensor_msgs/msg/NavSatFix", _R.POSITION, "ros2",
                ("latitude_deg", "longitude_deg", "height_m"),
                geodetic=("latitude", "longitude", "altitude"), fix_status="status.status"),
    MessageType("magalign.Turntable", _R.TURNTABLE, "json", ("angle_deg",)),
    MessageType("tf2_msgs/msg/TFMessage", _R.OUTPUT, "ros2"),
    MessageType("magalign.FieldMagnitude", _R.OUTPUT, "json"),
)}


def types_of(role: MessageRole, encoding: str | None = None, *,
             written: bool | None = None) -> tuple[str, ...]:
    """Names of the message types of ``role`` (optionally of one encoding, written or not)."""
    return tuple(t.name for t in MESSAGE_TYPES.values()
                 if t.role is role and encoding in (None, t.encoding)
                 and written in (None, t.written))


_INPUT_ROLES = (_R.MAGNETOMETER, _R.ATTITUDE, _R.TURNTABLE, _R.POSITION)
#: JSON message types of magalign's own channels.
JSON_TYPES: tuple[str, ...] = tuple(n for r in _INPUT_ROLES for n in types_of(r, "json"))
#: ROS 2 message types magalign writes (and reads).
ROS2_TYPES: tuple[str, ...] = tuple(n for r in _INPUT_ROLES
                                    for n in types_of(r, "ros2", written=True))
#: Types only magalign's outputs carry (the corrected MCAP), never read as input: the static
#: transform body -> mag (ROS 2) and the field magnitude of JSON recordings.
OUTPUT_ROS2_TYPES: tuple[str, ...] = types_of(_R.OUTPUT, "ros2")
OUTPUT_JSON_TYPES: tuple[str, ...] = types_of(_R.OUTPUT, "json")
#: Layout variants per ROS 2 type (``None`` is the default layout).
VARIANTS: dict[str, tuple[str | None, ...]] = {
    t.name: t.variants for t in MESSAGE_TYPES.values() if t.variants != (None,)}


def _resource_name(msg_type: str, variant: str | None) -> str:
    if msg_type in OUTPUT_JSON_TYPES + OUTPUT_ROS2_TYPES and variant is None:
        stem = msg_type.replace("/", ".")
        return f"{stem}.json" if msg_type in OUTPUT_JSON_TYPES else f"{stem}.msg"
    if msg_type in JSON_TYPES:
        if variant is not None:
            raise SchemaError(f"JSON type {msg_type} has no variant {variant!r}")
        return f"{msg_type}.json"
    if msg_type in ROS2_TYPES:
        if variant not in VARIANTS.get(msg_type, (None,)):
            raise SchemaError(
                f"{msg_type} has no layout variant {variant!r}",
                hint=f"known: {VARIANTS.get(msg_type, (None,))}",
            )
        stem = msg_type.replace("/", ".")
        return f"{stem}.msg" if variant is None else f"{stem}.{variant}.msg"
    raise SchemaError(
        f"unknown message type {msg_type!r}",
        hint=f"supported: {', '.join(ROS2_TYPES + JSON_TYPES)}",
    )


@functools.cache
def schema_text(msg_type: str, variant: str | None = None) -> bytes:
    """Return the stored schema of ``msg_type`` as bytes (JSON Schema or ros2msg text).

    Parameters
    ----------
    msg_type : str
        ``"sensor_msgs/msg/MagneticField"``, ``"magalign.Magnetometer"``, ...
    variant : str, optional
        Layout variant (see :data:`VARIANTS`); ``None`` for the default.

    Raises
    ------
    SchemaError
        Unknown type or variant.

    """
    name = _resource_name(msg_type, variant)
    return resources.files(__name__).joinpath(name).read_bytes()


def schema_for(msg_type: str, variant: str | None = None) -> tuple[str, str, bytes, str]:
    """Return ``(schema_name, schema_encoding, schema_data, message_encoding)`` for MCAP.

    ROS 2 types give ``(msg_type, "ros2msg", definition, "cdr")``; magalign's JSON types give
    ``(msg_type, "jsonschema", json_schema, "json")``.
    """
    data = schema_text(msg_type, variant)
    if msg_type in JSON_TYPES + OUTPUT_JSON_TYPES:
        return msg_type, "jsonschema", data, "json"
    return msg_type, "ros2msg", data, "cdr"


@functools.cache
def json_schema(msg_type: str) -> dict[str, Any]:
    """Return the parsed JSON Schema of one of magalign's JSON types (shared: do not modify)."""
    if msg_type not in JSON_TYPES:
        raise SchemaError(f"{msg_type!r} is not one of magalign's JSON types")
    return json.loads(schema_text(msg_type))
