"""MCAP read/write for ROS 2 messages (profile ``ros2``, schemas ``ros2msg``, messages ``cdr``).

Files written here carry the full ``.msg`` text of every type and its dependencies, named
``pkg/msg/Name``, so ``mcap-ros2-support``, ``rosbags`` and Foxglove decode them.

Reading is sequential and forgiving: every record is checked on its own, a message that cannot be
decoded is reported (:class:`BadMessage`, with its index, topic, stamp and reason) and the others
are still returned; a file cut short (e.g. a writer interrupted by Ctrl-C) yields every message
before the cut and then one :class:`BadMessage` describing the truncation.
"""

from __future__ import annotations

import io
import os
import re
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from lidarscan.cdr import decode, encode
from lidarscan.errors import LidarScanError, McapFormatError, SchemaError
from lidarscan.msgdef import (
    find_msg_text,
    get_msgdef,
    normalize_type,
    parse_msg,
    register_msg_text,
    schema_text,
    split_schema_text,
)
from lidarscan.stamps import to_ns
from lidarscan.types import msgtype_of

__all__ = [
    "McapWriter",
    "McapMessage",
    "BadMessage",
    "read_messages",
    "read_scans",
    "SCAN_TYPE",
    "INFO_TYPE",
]

SCAN_TYPE = "lidarscan_msgs/msg/LidarScan"
INFO_TYPE = "lidarscan_msgs/msg/LidarInfo"


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
        compression: "zstd" (default), "lz4" or "none".
        chunk_size: bytes per chunk; a smaller chunk loses less when a run is interrupted.
        qos: recorded QoS per topic: a name of :data:`lidarscan.rosbag2.QOS_PROFILES`
            ("sensor_data", "best_effort", "reliable", "latched"), a
            :class:`lidarscan.rosbag2.QosProfile`, rosbag2's dict form, or a list of these.
    """

    def __init__(self, output: str | os.PathLike[str] | IO[bytes], *, compression: str = "zstd",
                 chunk_size: int = 4 * 1024 * 1024, qos: dict[str, Any] | None = None) -> None:
        from mcap.writer import CompressionType, Writer

        from lidarscan.rosbag2 import qos_profile

        self._qos = {topic: tuple(qos_profile(p) for p in (
            value if isinstance(value, (list, tuple)) else [value]))
            for topic, value in (qos or {}).items()}
        kinds = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
                 "none": CompressionType.NONE}
        if compression not in kinds:
            from lidarscan.errors import ConfigError
            raise ConfigError("compression", compression, "one of 'zstd', 'lz4', 'none'")
        self._own = not hasattr(output, "write")
        target: Any = output
        self._stream: Any = open(target, "wb") if self._own else target  # noqa: SIM115
        self._writer = Writer(self._stream, chunk_size=chunk_size, compression=kinds[compression])
        self._writer.start(profile="ros2", library="lidarscan")
        self._schemas: dict[str, int] = {}
        self._channels: dict[tuple[str, str], int] = {}
        self._sequence: dict[int, int] = {}
        self._topics: dict[int, tuple[str, str, tuple[Any, ...]]] = {}
        self._times: list[int] = []  # first and last log time
        self.count = 0
        self._closed = False

    def _channel(self, topic: str, msgtype: str, metadata: dict[str, str] | None) -> int:
        key = (topic, msgtype)
        if key not in self._channels:
            from lidarscan.rosbag2 import default_qos, dump_qos, parse_qos

            if msgtype not in self._schemas:
                self._schemas[msgtype] = self._writer.register_schema(
                    name=msgtype, encoding="ros2msg", data=schema_text(msgtype).encode())
            given = dict(metadata or {})
            offered = tuple(parse_qos(given.get("offered_qos_profiles", ""))) \
                or self._qos.get(topic) or (default_qos(topic, msgtype),)
            given["offered_qos_profiles"] = dump_qos(offered)
            self._channels[key] = self._writer.register_channel(
                topic=topic, message_encoding="cdr", schema_id=self._schemas[msgtype],
                metadata=given)
            self._topics[self._channels[key]] = (topic, msgtype, offered)
        return self._channels[key]

    def write(self, topic: str, msg: Any, *, log_time_ns: int | None = None,
              publish_time_ns: int | None = None, msgtype: str | None = None,
              metadata: dict[str, str] | None = None) -> None:
        """Append one message.

        Args:
            topic: topic name.
            msg: an rclpy message, a lidarscan dataclass, or CDR ``bytes`` (then ``msgtype`` is
                required).
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
            payload = encode(msg, full)
        if log_time_ns is None:
            header = getattr(msg, "header", None)
            log_time_ns = to_ns(header.stamp) if header is not None else 0
        channel_id = self._channel(topic, full, metadata)
        sequence = self._sequence.get(channel_id, 0)
        self._sequence[channel_id] = sequence + 1
        self._writer.add_message(channel_id=channel_id, log_time=int(log_time_ns), data=payload,
                                 publish_time=int(publish_time_ns if publish_time_ns is not None
                                                  else log_time_ns), sequence=sequence)
        self.count += 1
        self._times = [min(self._times[0], log_time_ns), max(self._times[1], log_time_ns)] \
            if self._times else [int(log_time_ns), int(log_time_ns)]

    def bag_metadata(self) -> dict[str, Any]:
        """The rosbag2 metadata of what was written so far (see :mod:`lidarscan.rosbag2`)."""
        from lidarscan.rosbag2 import TopicRecord, bag_metadata

        name = getattr(self._stream, "name", "")
        topics = [TopicRecord(topic, msgtype, offered, self._sequence.get(channel_id, 0))
                  for channel_id, (topic, msgtype, offered) in self._topics.items()]
        start, end = self._times or [0, 0]
        return bag_metadata(topics, file_name=os.path.basename(name) if isinstance(name, str)
                            else "", start_ns=start, end_ns=end)

    def close(self) -> None:
        """Write the ``rosbag2`` metadata record, finish the file (summary, footer) and close it
        if we opened it."""
        if self._closed:
            return
        self._closed = True
        from lidarscan.rosbag2 import metadata_yaml

        try:
            self._writer.add_metadata("rosbag2", {
                "serialized_metadata": metadata_yaml(self.bag_metadata(), root=False)})
        finally:
            self._writer.finish()  # type: ignore[no-untyped-call]
        if self._own:
            self._stream.close()

    def __enter__(self) -> McapWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass(frozen=True)
class McapMessage:
    """One message record.

    Attributes:
        index: position of the message in the file (0-based, over all topics).
        topic, msgtype: channel topic and ``pkg/msg/Name``.
        log_time_ns, publish_time_ns, sequence: record fields.
        payload: the CDR bytes.
    """

    index: int
    topic: str
    msgtype: str
    log_time_ns: int
    publish_time_ns: int
    sequence: int
    payload: bytes

    def decode(self) -> Any:
        """Decode the payload into a :mod:`lidarscan.types` dataclass (raises DecodeError)."""
        return decode(self.payload, self.msgtype)


@dataclass(frozen=True)
class BadMessage:
    """A message (or the end of a damaged file) that could not be read; nothing else is lost.

    Attributes:
        index: message index in the file (-1 when it is about the file itself).
        topic: topic name ("" if unknown).
        log_time_ns: record time (0 if unknown).
        reason: what went wrong.
        error: the exception raised.
    """

    index: int
    topic: str
    log_time_ns: int
    reason: str
    error: Exception = field(repr=False)


_TYPE_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]*/msg/[A-Za-z][A-Za-z0-9_]*")


def _register_schema(name: str, text: str) -> str:
    """Make the file's definitions usable; refuse a definition that contradicts a local one."""
    full = normalize_type(name)
    for type_name, msg_text in split_schema_text(full, text).items():
        if not _TYPE_NAME.fullmatch(type_name):  # e.g. a NUL byte in a damaged schema name
            raise McapFormatError(f"schema {name!r}", type_name,
                                  "a type name 'pkg/msg/Name' made of letters, digits and _")
        theirs = parse_msg(msg_text, type_name).fields
        try:
            find_msg_text(type_name)
        except SchemaError:
            register_msg_text(type_name, msg_text)
            continue
        if get_msgdef(type_name).fields != theirs:
            raise McapFormatError(f"schema {name}", type_name,
                                  "the same fields as the local definition of this type",
                                  hint="the file was recorded with another version of the type")
    return full


def _open(source: str | os.PathLike[str] | IO[bytes] | bytes) -> tuple[IO[bytes], bool]:
    if isinstance(source, (bytes, bytearray)):
        return io.BytesIO(source), True
    if hasattr(source, "read"):
        return source, False  # type: ignore[return-value]
    return open(Path(source), "rb"), True  # noqa: SIM115


class _BoundedReader:
    """``read(n)`` that never asks the stream for more than what is left of it.

    A buffered file's ``read(n)`` allocates ``n`` bytes up front, so a corrupt record length
    (up to 4 GiB) would allocate that much before the short read is noticed; clamping ``n`` to
    the bytes left keeps memory bounded by the file size. Streams that cannot seek are passed
    through unchanged.
    """

    def __init__(self, stream: IO[bytes]) -> None:
        self._stream = stream
        self._left: int | None = None
        try:
            if stream.seekable():
                here = stream.tell()
                self._left = stream.seek(0, io.SEEK_END) - here
                stream.seek(here)
        except (OSError, AttributeError, ValueError):
            self._left = None

    def read(self, size: int = -1) -> bytes:
        if self._left is None:
            return self._stream.read(size)
        if size is None or size < 0 or size > self._left:
            size = self._left
        data = self._stream.read(size)
        self._left -= len(data)
        return data


def read_messages(source: str | os.PathLike[str] | IO[bytes] | bytes, *,
                  topics: Iterable[str] | None = None) -> Iterator[McapMessage | BadMessage]:
    """Iterate the messages of an MCAP file in file order.

    Yields :class:`McapMessage` for every record (undecoded: call ``.decode()``), and
    :class:`BadMessage` for a record whose channel/schema is unusable or for a damaged end of
    file; iteration always continues past a bad message when the file structure allows it.

    Args:
        source: path, binary stream or the file's bytes.
        topics: only these topics (default all).
    """
    from mcap.records import Channel, Message, Schema
    from mcap.stream_reader import StreamReader

    wanted = set(topics) if topics is not None else None
    stream, own = _open(source)
    schemas: dict[int, tuple[str, Exception | None]] = {}
    channels: dict[int, tuple[str, str, Exception | None]] = {}
    index = 0
    try:
        bounded: Any = _BoundedReader(stream)
        reader = StreamReader(bounded, record_size_limit=1 << 32)
        records = iter(reader.records)
        while True:
            try:
                record = next(records)
            except StopIteration:
                break
            except Exception as damage:  # damaged or truncated file: report and stop
                yield BadMessage(index, "", 0, f"file damaged after {index} messages: {damage}",
                                 McapFormatError("file", type(damage).__name__,
                                                 "a complete MCAP file"))
                break
            if isinstance(record, Schema):
                try:
                    if record.encoding != "ros2msg":
                        raise McapFormatError(f"schema {record.name}", record.encoding,
                                              "encoding 'ros2msg'")
                    try:
                        text = record.data.decode("utf-8")
                    except UnicodeDecodeError as bad_text:
                        raise McapFormatError(f"schema {record.name}", bytes(record.data[:40]),
                                              "UTF-8 message definition text") from bad_text
                    name = _register_schema(record.name, text)
                    schemas[record.id] = (name, None)
                except LidarScanError as bad_schema:
                    schemas[record.id] = (record.name, bad_schema)
            elif isinstance(record, Channel):
                name, err = schemas.get(record.schema_id, ("", McapFormatError(
                    f"channel {record.topic}", record.schema_id, "a known schema id")))
                if err is None and record.message_encoding != "cdr":
                    err = McapFormatError(f"channel {record.topic}", record.message_encoding,
                                          "message encoding 'cdr'")
                channels[record.id] = (record.topic, name, err)
            elif isinstance(record, Message):
                topic, name, err = channels.get(record.channel_id, ("", "", McapFormatError(
                    "message.channel_id", record.channel_id, "a channel defined before it")))
                if wanted is None or topic in wanted:
                    if err is not None:
                        yield BadMessage(index, topic, record.log_time, str(err), err)
                    else:
                        yield McapMessage(index, topic, name, record.log_time,
                                          record.publish_time, record.sequence, record.data)
                index += 1
    finally:
        if own:
            stream.close()


def read_scans(source: str | os.PathLike[str] | IO[bytes] | bytes, *,
               scan_topics: Iterable[str] | None = None, info_topics: Iterable[str] | None = None,
               on_error: Callable[[BadMessage], None] | None = None,
               max_pending: int = 64) -> Iterator[tuple[Any, Any]]:
    """Iterate ``(scan, info)`` pairs: each LidarScan with the LidarInfo its
    ``lidar_info_time`` names (decoded dataclasses; the scan's data views the file's bytes).

    Scans recorded before their info are held (at most ``max_pending``) until it appears;
    scans whose info never appears, undecodable messages and inconsistent scans are passed to
    ``on_error`` (as :class:`BadMessage`) and skipped; the rest are yielded. In a file the info
    wait is bounded by the file, not by time.
    """
    from lidarscan.linkage import InfoResolver

    scans = set(scan_topics) if scan_topics is not None else None
    infos = set(info_topics) if info_topics is not None else None
    resolver = InfoResolver(max_pending=max_pending, max_wait_ns=None)
    origin: dict[int, McapMessage] = {}

    def report(bad: BadMessage) -> None:
        if on_error is not None:
            on_error(bad)

    def drops() -> None:
        for drop in resolver.take_dropped():
            src = origin.pop(id(drop.scan), None)
            report(BadMessage(src.index if src else -1, src.topic if src else "",
                              src.log_time_ns if src else 0, drop.reason,
                              McapFormatError("lidar_info_time", drop.info_stamp_ns,
                                              "a LidarInfo with this stamp")))

    for item in read_messages(source):
        if isinstance(item, BadMessage):
            report(item)
            continue
        is_scan = item.msgtype == SCAN_TYPE and (scans is None or item.topic in scans)
        is_info = item.msgtype == INFO_TYPE and (infos is None or item.topic in infos)
        if not (is_scan or is_info):
            continue
        try:
            msg = item.decode()
            ready = resolver.add_info(msg) if is_info else resolver.add_scan(msg)
            if is_scan:
                origin[id(msg)] = item
        except LidarScanError as err:
            report(BadMessage(item.index, item.topic, item.log_time_ns, str(err), err))
            continue
        drops()
        for scan, info in ready:
            origin.pop(id(scan), None)
            yield scan, info
    resolver.flush()
    drops()
