"""The MCAP file format's constants, shared by the reader and the writer.

From the MCAP specification (https://mcap.dev/spec): the magic bytes that open and close a
file, and the opcode of each record type. Everything magalign reads or writes byte by byte
(``pipeline.io.mcap_read``, ``pipeline.io.mcap_write``, the CLI's first-bytes check) takes them from
here.
"""

from __future__ import annotations

import enum

MAGIC = b"\x89MCAP0\r\n"
"""The 8 bytes at the start and at the end of every MCAP file (format version 0)."""


class Opcode(enum.IntEnum):
    """MCAP record opcodes (one byte before each record's uint64 length)."""

    HEADER = 0x01
    FOOTER = 0x02
    SCHEMA = 0x03
    CHANNEL = 0x04
    MESSAGE = 0x05
    CHUNK = 0x06
    MESSAGE_INDEX = 0x07
    CHUNK_INDEX = 0x08
    ATTACHMENT = 0x09
    ATTACHMENT_INDEX = 0x0A
    STATISTICS = 0x0B
    METADATA = 0x0C
    METADATA_INDEX = 0x0D
    SUMMARY_OFFSET = 0x0E
    DATA_END = 0x0F


MAX_OPCODE = max(Opcode)
"""Opcodes above this and below 0x80 are reserved; 0x80-0xFF are user records (skipped)."""
