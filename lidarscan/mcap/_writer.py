"""MCAP writing (see :mod:`lidarscan.mcap`, which re-exports :class:`McapWriter`): ROS 2 messages
to a rosbag2-compatible MCAP file through :class:`lidarscan.mcap._file.ChunkedMcapWriter`, with
the rosbag2 metadata of :mod:`lidarscan.mcap._rosbag2`."""

from __future__ import annotations

import contextlib
import os
import signal
import threading
from collections.abc import Iterator
from typing import IO, Any

from lidarscan.cdr import decode, encode, encode_pieces
from lidarscan.errors import ConfigError, SchemaError
from lidarscan.mcap._file import COMPRESSIONS, ChunkedMcapWriter
from lidarscan.mcap._records import CODEC_ENCODING, INFO_TYPE, SCAN_TYPE
from lidarscan.mcap._rosbag2 import (
    TopicRecord,
    bag_metadata,
    default_qos,
    dump_qos,
    metadata_yaml,
    parse_qos,
    qos_profile,
)
from lidarscan.msgdef import normalize_type, schema_text
from lidarscan.scan import return_of
from lidarscan.stamps import to_ns
from lidarscan.types import msgtype_of

__all__ = ["McapWriter"]

#: serialised pieces of at least this many bytes that are read-only (a decoder's data block,
#: arrays decoded from a recording) are kept by reference until their chunk is written
_BORROW = 1 << 16


def _payload(pieces: list[Any]) -> Any:
    """CDR pieces (:func:`lidarscan.cdr.encode_pieces`) -> the payload the chunk writer keeps:
    small pieces joined, large read-only buffers by reference, large writable ones copied (the
    caller may change them after :meth:`McapWriter.write` returns)."""
    out: list[Any] = []
    run: list[Any] = []
    for piece in pieces:
        if not isinstance(piece, bytes):
            view = memoryview(piece)
            if view.nbytes >= _BORROW:
                if run:
                    out.append(b"".join(run))
                    run = []
                out.append(view if view.readonly else bytes(view))
                continue
        run.append(piece)
    if run:
        out.append(b"".join(run))
    return out[0] if len(out) == 1 else out


def _local(msg: Any, msgtype: str) -> bool:
    """Whether a message's CDR repeats its bytes only nearby (see
    :meth:`lidarscan.mcap._file.ChunkedMcapWriter.add_message`): a LidarInfo, or a LidarScan
    without an N-th return channel (``range2``, ``intensity2``, ... by
    :func:`lidarscan.scan.return_of`: its grid repeats the first return's a whole grid back
    wherever there is no second return). Encoded bytes: unknown (False)."""
    if isinstance(msg, (bytes, bytearray, memoryview)):
        return False
    if msgtype == INFO_TYPE:
        return True
    if msgtype != SCAN_TYPE:
        return False
    names = [str(c.name) for c in msg.channels]
    return all(return_of(n, names)[1] == 1 for n in names)


@contextlib.contextmanager
def _interrupts_deferred() -> Iterator[None]:
    """Hold SIGINT (Ctrl-C) until the block is done, then deliver it as the previous handler
    would (KeyboardInterrupt by default): a record and the statistics that count it are written
    together, so an interrupted writer still finishes a consistent file. Only in the main
    thread (the only one Python delivers signals to); elsewhere a no-op."""
    if (threading.current_thread() is not threading.main_thread()
            or signal.getsignal(signal.SIGINT) is None):   # a handler Python cannot restore
        yield
        return
    caught: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: caught.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if caught:
            if callable(previous):
                previous(signal.SIGINT, None)       # default_int_handler: KeyboardInterrupt
            elif previous == signal.SIG_DFL:
                os.kill(os.getpid(), signal.SIGINT)


class McapWriter:
    """Write ROS 2 messages to an MCAP file.

    Use as a context manager (the file is finalised with its summary on exit, also on errors):

        with McapWriter("out.mcap") as writer:
            writer.write("/lidar/info", info)          # rclpy message or lidarscan dataclass
            writer.write("/lidar/scan", scan)

    The file is a rosbag2 recording (:mod:`lidarscan.rosbag2`): each channel records the QoS
    its publishers offer (``offered_qos_profiles``: LidarInfo and /tf_static latched, scans and
    clouds sensor-data, others reliable, unless ``qos`` says otherwise) and the file ends with
    the ``rosbag2`` metadata record, so ``ros2 bag play`` replays latched topics as latched.

    Args:
        output: path or binary stream.
        compression: "zstd" (default), "lz4" or "none" (of the chunks).
        level: zstd level of the chunks; default :data:`lidarscan.mcap._file.DEFAULT_ZSTD_LEVEL`
            (2: fast, see bench/README.md; chunks of LidarInfos and scans without a second
            return with a smaller hash table, :data:`lidarscan.mcap._file.LOCAL_HASH_LOG`); up
            to 22 for smaller files, negative for faster.
        chunk_size: bytes per chunk; a smaller chunk loses less when a run is interrupted.
        scan_encoding: message encoding of the LidarScan channels: "cdr" (default) or
            :data:`CODEC_ENCODING` (every scan compressed by :func:`lidarscan.codec.compress_scan`
            with its default settings and the LidarInfo its ``lidar_info_time`` names when that
            was written before it; channel metadata ``lidarscan.codec.version``). Scans given
            in the other encoding are converted; ``ros2 bag play`` and CDR-only readers cannot
            read a :data:`CODEC_ENCODING` channel (``lidarscan convert`` back to CDR first).
        codec_coder: the residual coder of that compression, as ``coder=`` of
            :func:`lidarscan.codec.compress_scan`: "auto" (default: the compiled coder when
            numba is installed, else the numpy reference), "numba", "numpy" or None (the
            numpy reference), or a :class:`lidarscan.codec.ResidualCoder`; the same bytes.
        qos: recorded QoS per topic: a name of :data:`lidarscan.rosbag2.QOS_PROFILES`
            ("sensor_data", "best_effort", "reliable", "latched"), a
            :class:`lidarscan.rosbag2.QosProfile`, rosbag2's dict form, or a list of these.
        threads: 1 (default): everything in the caller's thread; 2: the chunks are compressed
            and written by one background thread (overlapping the caller's work on a second
            core); N > 2: N - 1 threads compress chunks side by side (a further one only when
            the others fall behind), written in order. Same file bytes for every N; at most a
            few chunks queued, then :meth:`write` waits; an error of those threads is raised by
            a later :meth:`write` or by :meth:`close`.
        crc: compute each chunk's CRC-32 (default); False writes 0 ("not computed" in MCAP:
            readers skip the check).
        file_name: the storage file name the rosbag2 metadata record lists (default: the
            output's; a caller writing to a temporary name gives the final one).

    Serialised arrays of 64 KiB or more that are read-only (a packet decoder's scan data, a
    recording's decoded arrays) are kept by reference until their chunk is written: they
    must not be changed (writable ones are copied by :meth:`write`).
    """

    def __init__(self, output: str | os.PathLike[str] | IO[bytes], *, compression: str = "zstd",
                 chunk_size: int = 4 * 1024 * 1024, qos: dict[str, Any] | None = None,
                 scan_encoding: str = "cdr", level: int | None = None,
                 codec_coder: Any = "auto", threads: int = 1, crc: bool = True,
                 file_name: str | None = None) -> None:
        self._qos = {topic: tuple(qos_profile(p) for p in (
            value if isinstance(value, (list, tuple)) else [value]))
            for topic, value in (qos or {}).items()}
        if compression not in COMPRESSIONS:
            raise ConfigError("compression", compression, "one of 'zstd', 'lz4', 'none'")
        if level is not None and not (isinstance(level, int) and -131072 <= level <= 22):
            raise ConfigError("level", level, "a zstd level: an integer from -131072 to 22")
        if not isinstance(threads, int) or not 1 <= threads <= 64:
            raise ConfigError("threads", threads, "an integer from 1 (no thread) to 64")
        if scan_encoding not in ("cdr", CODEC_ENCODING):
            raise ConfigError("scan_encoding", scan_encoding, f"'cdr' or {CODEC_ENCODING!r}")
        self.scan_encoding = scan_encoding
        self._file_name = file_name
        self._coder = codec_coder
        self._infos: dict[int, Any] = {}  # info stamp ns -> LidarInfo, for compress_scan
        self._own = not hasattr(output, "write")
        target: Any = output
        self._stream: Any = open(target, "wb") if self._own else target  # noqa: SIM115
        self._writer = ChunkedMcapWriter(self._stream, chunk_size=chunk_size,
                                         compression=compression, level=level,
                                         threads=threads, crc=crc)
        self._writer.start(profile="ros2", library="lidarscan")
        self._schemas: dict[str, int] = {}
        self._channels: dict[tuple[str, str, str], int] = {}
        self._sequence: dict[int, int] = {}
        self._topics: dict[int, tuple[str, str, tuple[Any, ...], str]] = {}
        self._times: list[int] = []  # first and last log time
        self.count = 0
        self._closed = False

    def _channel(self, topic: str, msgtype: str, metadata: dict[str, str] | None,
                 encoding: str = "cdr") -> int:
        key = (topic, msgtype, encoding)
        if key not in self._channels:
            if msgtype not in self._schemas:
                self._schemas[msgtype] = self._writer.register_schema(
                    name=msgtype, encoding="ros2msg", data=schema_text(msgtype).encode())
            given = dict(metadata or {})
            offered = tuple(parse_qos(given.get("offered_qos_profiles", "")))
            if not offered:   # a caller's own profiles are kept verbatim, else ours are written
                offered = self._qos.get(topic) or (default_qos(topic, msgtype),)
                given["offered_qos_profiles"] = dump_qos(offered)
            if encoding == CODEC_ENCODING:
                from lidarscan import codec
                given["lidarscan.codec.version"] = str(codec.VERSION)
            else:
                given.pop("lidarscan.codec.version", None)
            self._channels[key] = self._writer.register_channel(
                topic=topic, message_encoding=encoding, schema_id=self._schemas[msgtype],
                metadata=given)
            self._topics[self._channels[key]] = (topic, msgtype, offered, encoding)
        return self._channels[key]

    def write(self, topic: str, msg: Any, *, log_time_ns: int | None = None,
              publish_time_ns: int | None = None, msgtype: str | None = None,
              metadata: dict[str, str] | None = None, encoding: str = "cdr") -> None:
        """Append one message.

        Args:
            topic: topic name.
            msg: an rclpy message, a lidarscan dataclass, or encoded ``bytes`` (then ``msgtype``
                is required and ``encoding`` names their encoding: "cdr", or
                :data:`CODEC_ENCODING` for a compressed LidarScan).
            log_time_ns: record time; default the message's ``header.stamp`` (0 if it has none).
            publish_time_ns: default ``log_time_ns``.
            msgtype: ``pkg/msg/Name``; default from the message.
            metadata: channel metadata, used on first write; its ``offered_qos_profiles``
                (e.g. copied from another recording) wins over ``qos`` and the defaults.
        """
        if isinstance(msg, (bytes, bytearray, memoryview)):
            if msgtype is None:
                raise SchemaError("msgtype", None, "the message type when writing raw CDR bytes")
            full, payload = normalize_type(msgtype), bytes(msg)
        else:
            full = normalize_type(msgtype) if msgtype else msgtype_of(msg)
            payload, encoding = _payload(encode_pieces(msg, full)), "cdr"
        if encoding not in ("cdr", CODEC_ENCODING) or (encoding != "cdr" and full != SCAN_TYPE):
            raise SchemaError("encoding", encoding,
                              f"'cdr', or {CODEC_ENCODING!r} for a {SCAN_TYPE}")
        if full == INFO_TYPE and self.scan_encoding == CODEC_ENCODING:
            info = msg if not isinstance(msg, (bytes, bytearray, memoryview)) else \
                decode(payload, full)
            self._infos[to_ns(info.header.stamp)] = info
            while len(self._infos) > 64:
                del self._infos[next(iter(self._infos))]
        if full == SCAN_TYPE and encoding != self.scan_encoding:
            from lidarscan import codec
            if encoding == "cdr":
                source = msg if not isinstance(msg, (bytes, bytearray, memoryview)) else \
                    decode(payload, full)
                payload = codec.compress_scan(
                    source, self._infos.get(to_ns(source.lidar_info_time)), coder=self._coder)
            else:
                payload = encode(codec.decompress_scan(payload, coder=self._coder), full)
            encoding = self.scan_encoding
        if log_time_ns is None:
            header = getattr(msg, "header", None)
            log_time_ns = to_ns(header.stamp) if header is not None else 0
        with _interrupts_deferred():     # Ctrl-C never splits a record from its statistics
            channel_id = self._channel(topic, full, metadata, encoding)
            sequence = self._sequence.get(channel_id, 0)
            self._sequence[channel_id] = sequence + 1
            self._writer.add_message(channel_id=channel_id, log_time=int(log_time_ns),
                                     data=payload, sequence=sequence,
                                     publish_time=int(publish_time_ns if publish_time_ns
                                                      is not None else log_time_ns),
                                     local=encoding == "cdr" and _local(msg, full))
            self.count += 1
            self._times = [min(self._times[0], log_time_ns), max(self._times[1], log_time_ns)] \
                if self._times else [int(log_time_ns), int(log_time_ns)]

    def bag_metadata(self) -> dict[str, Any]:
        """The rosbag2 metadata of what was written so far (see :mod:`lidarscan.rosbag2`)."""
        name = self._file_name if self._file_name is not None else \
            getattr(self._stream, "name", "")
        topics = [TopicRecord(topic, msgtype, offered, self._sequence.get(channel_id, 0),
                              serialization_format=encoding)
                  for channel_id, (topic, msgtype, offered, encoding) in self._topics.items()]
        start, end = self._times or [0, 0]
        return bag_metadata(topics, file_name=os.path.basename(name) if isinstance(name, str)
                            else "", start_ns=start, end_ns=end)

    def close(self) -> None:
        """Write the ``rosbag2`` metadata record, finish the file (summary, footer) and close it
        if we opened it."""
        if self._closed:
            return
        self._closed = True
        try:
            with _interrupts_deferred():
                try:
                    self._writer.add_metadata("rosbag2", {
                        "serialized_metadata": metadata_yaml(self.bag_metadata(), root=False)})
                finally:
                    self._writer.finish()
        finally:
            if self._own:
                self._stream.close()

    def __enter__(self) -> McapWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
