"""MCAP read/write for ROS 2 messages (profile ``ros2``, schemas ``ros2msg``, messages ``cdr``).

Files written here carry the full ``.msg`` text of every type and its dependencies, named
``pkg/msg/Name``, so ``mcap-ros2-support``, ``rosbags`` and Foxglove decode them.

Reading is sequential and forgiving: every record is checked on its own, a message that cannot be
decoded is reported (:class:`BadMessage`, with its index, topic, stamp and reason) and the others
are still returned. Damage to the file itself is reported and read past: a chunk whose CRC does
not match or that does not decompress is skipped with its offset and log-time range, a damaged
record length or a missing/damaged summary is recovered from by scanning the data section for
the next chunk; a file cut short (e.g. a writer interrupted by Ctrl-C) yields every message
before the cut and then one :class:`BadMessage` describing the truncation.

Layers (each module imports only those below it): the file layer, :mod:`lidarscan.mcap._records`
(message records, names, opcodes, the field reader, chunk decompression) and
:mod:`lidarscan.mcap._file` (the record-level writer: chunks, indexes, CRCs, summary); the
rosbag2 metadata, :mod:`lidarscan.mcap._rosbag2` (re-exported by :mod:`lidarscan.rosbag2`);
reading, :mod:`lidarscan.mcap._reader`, and writing, :mod:`lidarscan.mcap._writer`; this module,
the public face of both. :class:`lidarscan.rosbag2.BagWriter` builds on it.
"""

from __future__ import annotations

from lidarscan.mcap._reader import read_messages, read_scans
from lidarscan.mcap._records import (
    CODEC_ENCODING,
    INFO_TYPE,
    SCAN_TYPE,
    BadMessage,
    McapMessage,
    describe_bytes,
)
from lidarscan.mcap._writer import McapWriter

__all__ = [
    "McapWriter",
    "McapMessage",
    "BadMessage",
    "read_messages",
    "read_scans",
    "describe_bytes",
    "SCAN_TYPE",
    "INFO_TYPE",
    "CODEC_ENCODING",
]
