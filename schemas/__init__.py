"""Message schemas magalign reads and writes.

Two kinds of file live here, loaded as package resources (they ship in the wheel):

- ``magalign.<Name>.json``: JSON Schemas (draft 2020-12) of magalign's own JSON channels
  (schema encoding ``jsonschema``, message encoding ``json``).
- ``<pkg>.msg.<Type>[.<variant>].msg``: ROS 2 message definitions in the concatenated form
  that MCAP's ``ros2msg`` schema encoding and ``mcap_ros2`` expect (the main definition, then
  one ``====...`` separator and ``MSG: pkg/Type`` block per dependency).

``novatel_oem7_msgs/msg/INSPVA`` has variants: its header layout differs between driver
versions, and readers must take the layout from the schema stored in the file. ``None`` is the
novatel_oem7_driver layout (``std_msgs/Header header``, ``Oem7Header nov_header``, ...);
``"no_nov_header"`` has no NovAtel header; ``"novatel_header"`` carries a differently laid out
NovAtel header (strings, float32 and float64 fields that shift every later offset).
"""

from __future__ import annotations

import functools
import json
from importlib import resources
from typing import Any

from pipeline.errors import SchemaError

#: JSON message types of magalign's own channels.
JSON_TYPES: tuple[str, ...] = (
    "magalign.Magnetometer",
    "magalign.AttitudeQuaternion",
    "magalign.AttitudeEuler",
    "magalign.Turntable",
)

#: ROS 2 message types magalign writes (and reads).
ROS2_TYPES: tuple[str, ...] = (
    "sensor_msgs/msg/MagneticField",
    "sensor_msgs/msg/Imu",
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/QuaternionStamped",
    "std_msgs/msg/Float64",
    "novatel_oem7_msgs/msg/INSPVA",
)

#: Types only magalign's outputs carry (the corrected MCAP), never read as input: the static
#: transform body -> mag (ROS 2) and the field magnitude of JSON recordings.
OUTPUT_ROS2_TYPES: tuple[str, ...] = ("tf2_msgs/msg/TFMessage",)
OUTPUT_JSON_TYPES: tuple[str, ...] = ("magalign.FieldMagnitude",)

#: Layout variants per ROS 2 type (``None`` is the default layout).
VARIANTS: dict[str, tuple[str | None, ...]] = {
    "novatel_oem7_msgs/msg/INSPVA": (None, "no_nov_header", "novatel_header"),
}


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
