"""What a recording is, without reading its samples: channels, topics, encoding, frame names.

For a recording processed chunk by chunk (:mod:`pipeline.run`), whose samples
never sit in memory at once: :func:`read_recording_header` picks the channels as
:func:`pipeline.io.mcap_read.read_recording` does, counts their messages from the chunk
indexes and decodes the first chunk that holds each (for the frame names and rates only,
and whether the recording has positions).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.core.recording import (
    AttitudeSeries,
    EncodingFamily,
    Frame,
    Problem,
    Recording,
    Role,
    VectorSeries,
)
from pipeline.io.mcap_decode import ChannelDecoder, DecodedColumns, pick_channel, type_of
from pipeline.io.mcap_read import channel_infos, pick_position, position_series
from pipeline.io.mcap_scan import index_chunks, iter_blocks, scan_file


def read_recording_header(
    path: str | Path,
    *,
    mag_topic: str | None = None,
    attitude_topic: str | None = None,
    position_topic: str | None = None,
) -> Recording:
    """Return the recording's channels, topics, encoding and frame names (no samples).

    Parameters
    ----------
    path : path
        MCAP file (never modified).
    mag_topic, attitude_topic, position_topic : str, optional
        Channels, as for :func:`pipeline.io.mcap_read.read_recording`.

    Returns
    -------
    Recording
        ``mag`` and ``attitude`` hold the first decoded chunk's samples only (they give the
        frame names); ``position`` tells whether the recording has positions: the position
        channel's (``NavSatFix``) first chunk, NaN rows kept even when none of them is a
        valid fix yet (a receiver still acquiring), else the attitude's positions of its
        first chunk, else None. ``channels`` carry the message counts of the whole file
        (from its indexes), their roles, and the rates of that first chunk; ``problems``
        holds ``position_ambiguous`` when two or more position channels are not chosen
        between.

    Raises
    ------
    NotMcapError, CorruptRecordingError, ChannelError, SchemaError

    """
    scan = scan_file(path)
    index_chunks(scan)
    mag_id = pick_channel(scan, Role.MAGNETOMETER, mag_topic, True)
    att_id = pick_channel(scan, Role.ATTITUDE, attitude_topic, False)
    problems: list[Problem] = []
    pos_id = pick_position(scan, position_topic, problems)
    ids = [i for i in (mag_id, att_id, pos_id) if i is not None]
    counts: dict[int, int] = {}
    for ch in scan.chunks:
        if not ch.bad and ch.index:
            for cid, offs in ch.index.items():
                counts[cid] = counts.get(cid, 0) + len(offs)
    first: dict[int, DecodedColumns] = {}
    for buf, sel in iter_blocks(scan, set(ids)):
        for cid, rec in sel.items():
            if cid not in first and len(rec):
                first[cid] = ChannelDecoder(scan, scan.channels[cid]).decode(buf, rec)
        if len(first) == len(ids):
            break
    stamps = {cid: d.t_ns for cid, d in first.items()}
    d_mag = first.get(mag_id)
    mag_ch = scan.channels[mag_id]
    att_frame = ""
    attitude = position = None
    if att_id is not None and att_id in first:
        if type_of(scan, scan.channels[att_id]).replace("/msg/", "/") == "sensor_msgs/Imu":
            att_frame = first[att_id].frame_id
        attitude = AttitudeSeries(first[att_id].t_ns, first[att_id].values)
        position = position_series(first[att_id])
    if pos_id is not None and pos_id in first:
        # sorted by stamp as read_recording sorts (the origin is the first valid fix)
        d = first[pos_id].take(np.argsort(first[pos_id].t_ns, kind="stable"))
        fixes = position_series(d, fixes=True, keep_lost=True)
        if fixes is not None:  # the position channel wins, as in read_recording
            position = fixes
    return Recording(
        path=scan.path,
        channels=channel_infos(scan, counts, stamps),
        mag=VectorSeries(np.zeros(0, np.int64) if d_mag is None else d_mag.t_ns,
                         np.zeros((0, 3)) if d_mag is None else d_mag.values, Frame.MAG, "nT"),
        mag_topic=mag_ch.topic,
        attitude=attitude,
        attitude_topic=None if att_id is None else scan.channels[att_id].topic,
        encoding=EncodingFamily.JSON if mag_ch.message_encoding == "json"
        else EncodingFamily.ROS2,
        mag_frame_id="" if d_mag is None else d_mag.frame_id,
        attitude_frame_id=att_frame,
        problems=tuple(problems),
        position=position,
    )
