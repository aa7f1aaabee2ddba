"""rosbag2 recordings in, and the raw-packet messages of Velodyne, Hesai and Ouster drivers.

A *bag* here is a rosbag2 directory (``metadata.yaml`` plus sqlite3 ``.db3`` or MCAP storage
files), a single ``.db3`` file, or a single ``.mcap`` file. :func:`open_bag` reads it into
:class:`Bag`: its topics (type, message count, serialization format, offered QoS profiles) and
:meth:`Bag.messages`, the messages of every storage file merged in log-time order as
:class:`lidarscan.mcap.McapMessage` (raw CDR ``payload``, ``log_time_ns`` = the rosbag2 receive
time, int64 ns) with :class:`lidarscan.mcap.BadMessage` for what cannot be read.

Real-bag quirks handled: an empty ``serialization_format`` (read as CDR), an empty
``storage_identifier`` (the storage is told by each file's first bytes), ``offered_qos_profiles``
given as ``""``, as a YAML string or as a list; no ``metadata.yaml`` (every ``.db3``, else every
``.mcap`` of the directory is read); the sqlite3 schema of every rosbag2 version (the ``schema``,
``metadata`` and ``message_definitions`` tables of newer ones are optional); per-message zstd
compression (``compression_mode: MESSAGE``). A damaged or undecodable row is reported and reading
goes on; a file whose time index is damaged is read in row (recording) order; a file sqlite
cannot open at all (e.g. truncated) is one report. The ``.db3`` files are opened read-only and immutable (nothing is written next to
them) with the standard library's :mod:`sqlite3`.

Packet messages (CDR, alignment relative to the payload after the 4-byte encapsulation header,
byte order from that header): :func:`velodyne_packets` for ``velodyne_msgs/msg/VelodyneScan``
(``std_msgs/Header header``, ``VelodynePacket[] packets``; ``VelodynePacket`` =
``builtin_interfaces/Time stamp``, ``uint8[1206] data``) and :func:`pandar_packets` for
``pandar_msgs/msg/PandarScan`` (``PandarPacket`` = ``Time stamp``, ``uint8[1500] data``,
``uint32 size``: the bytes of ``data`` used). Both return views into the message bytes.
:func:`ouster_packets` for ouster-ros's ``PacketMsg`` (``uint8[] buf``: one UDP payload per
message, no header; the recording's metadata topic: :mod:`converters.sources.ouster.bag`).
"""

from __future__ import annotations

import functools
import heapq
import os
import sqlite3
import struct
from collections.abc import Iterable, Iterator
from contextlib import closing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lidarscan.errors import ConversionError, DecodeError, McapFormatError
from lidarscan.mcap import BadMessage, McapMessage, describe_bytes

__all__ = [
    "InputKind",
    "detect_input",
    "TopicInfo",
    "Bag",
    "open_bag",
    "PacketScan",
    "velodyne_packets",
    "pandar_packets",
    "ouster_packets",
    "OUSTER_PACKET_TYPES",
    "is_packet_topic",
    "VELODYNE_SCAN",
    "PANDAR_SCAN",
    "PACKET_TYPES",
    "register_packet_types",
]

VELODYNE_SCAN = "velodyne_msgs/msg/VelodyneScan"
PANDAR_SCAN = "pandar_msgs/msg/PandarScan"
#: ouster-ros's packet message (current package name, then the older one)
OUSTER_PACKET_TYPES = ("ouster_sensor_msgs/msg/PacketMsg", "ouster_msgs/msg/PacketMsg")


def is_packet_topic(topic: str, msgtype: str) -> bool:
    """Whether a topic holds lidar packets to decode: a packet message type, except
    ouster-ros's IMU packets (``<ns>/imu_packets``, the same PacketMsg type)."""
    if msgtype in OUSTER_PACKET_TYPES:
        return not topic.rstrip("/").endswith("imu_packets")
    return msgtype in PACKET_TYPES
_SQLITE_MAGIC = b"SQLite format 3\x00"
# sqlite3 raises UnicodeDecodeError when a damaged file's error message is not UTF-8
_SQL_ERRORS = (sqlite3.Error, UnicodeDecodeError)
_MCAP_MAGIC = b"\x89MCAP0\r\n"


# ------------------------------------------------------------------------------ input kind

@dataclass(frozen=True)
class InputKind:
    """What a path is.

    Attributes:
        kind: ``"mcap"``, ``"db3"`` (an SQLite file), ``"rosbag2"`` (a directory with
            ``metadata.yaml`` or storage files), ``"missing"``, ``"empty"``, ``"directory"``
            (a directory without a bag in it) or ``"other"``.
        description: a phrase for messages ("an SQLite database (a rosbag2 .db3 file?)").
    """

    kind: str
    description: str

    @property
    def is_bag(self) -> bool:
        """A rosbag2 directory or ``.db3`` file (MCAP files are read directly)."""
        return self.kind in ("rosbag2", "db3")


def detect_input(path: str | os.PathLike[str]) -> InputKind:
    """Tell an MCAP file, a rosbag2 directory or ``.db3``, an empty, missing or other file
    apart by their contents (not by their names)."""
    p = Path(path)
    if p.is_dir():
        if (p / "metadata.yaml").is_file():
            return InputKind("rosbag2", "a rosbag2 directory")
        if any(p.glob("*.db3")) or any(p.glob("*.mcap")):
            return InputKind("rosbag2", "a rosbag2 directory without metadata.yaml")
        return InputKind("directory", "a directory without metadata.yaml, .db3 or .mcap files")
    if not p.exists():
        return InputKind("missing", "missing (no such file or directory)")
    try:
        with open(p, "rb") as stream:
            head = stream.read(16)
    except OSError as err:
        return InputKind("other", f"unreadable ({err.strerror or err})")
    if not head:
        return InputKind("empty", "an empty file")
    if head.startswith(_SQLITE_MAGIC):
        return InputKind("db3", "an SQLite database (rosbag2 .db3)")
    if head.startswith(_MCAP_MAGIC[:5]):
        return InputKind("mcap", "an MCAP file")
    return InputKind("other", describe_bytes(head))


# ------------------------------------------------------------------------------------ bags

@dataclass
class TopicInfo:
    """One topic of a bag.

    Attributes:
        name, msgtype: topic name and ``pkg/msg/Name``.
        count: messages recorded (from ``metadata.yaml`` or the storage files).
        serialization_format: ``"cdr"`` (an empty value in the metadata reads as ``"cdr"``).
        offered_qos_profiles: the QoS profiles as recorded (YAML text, may be ``""``).
    """

    name: str
    msgtype: str
    count: int = 0
    serialization_format: str = "cdr"
    offered_qos_profiles: str = ""

    @property
    def metadata(self) -> dict[str, str]:
        """MCAP channel metadata preserving the recorded QoS (empty when none was recorded)."""
        return {"offered_qos_profiles": self.offered_qos_profiles} \
            if self.offered_qos_profiles else {}


@dataclass
class Bag:
    """A rosbag2 recording opened by :func:`open_bag`.

    Attributes:
        path: what was opened.
        files: the storage files, in order.
        topics: topic name -> :class:`TopicInfo`.
        notes: quirks found in the metadata (e.g. an empty ``serialization_format``).
    """

    path: Path
    files: list[Path]
    topics: dict[str, TopicInfo]
    notes: list[str] = field(default_factory=list)
    compression: str = ""  # "zstd" when each message is compressed (compression_mode MESSAGE)

    @property
    def message_count(self) -> int:
        return sum(t.count for t in self.topics.values())

    def messages(self, topics: Iterable[str] | None = None
                 ) -> Iterator[McapMessage | BadMessage]:
        """Every message of every storage file in log-time order (ties: file, then row order);
        ``index`` counts over the whole bag. Unreadable rows and files come as BadMessage."""
        wanted = set(topics) if topics is not None else None
        streams = [_tagged(k, self._file_messages(path, wanted))
                   for k, path in enumerate(self.files)]
        index = 0
        for _, _, _, item in heapq.merge(*streams):
            if isinstance(item, McapMessage):
                item = McapMessage(index, item.topic, item.msgtype, item.log_time_ns,
                                   item.publish_time_ns, item.sequence, item.payload,
                                   item.metadata, item.encoding)
            elif item.index >= 0:
                item = BadMessage(index, item.topic, item.log_time_ns, item.reason, item.error,
                                  item.offset, item.end_time_ns)
            index += 1 if item.index >= 0 else 0
            yield item

    def _file_messages(self, path: Path, wanted: set[str] | None
                       ) -> Iterator[McapMessage | BadMessage]:
        with open(path, "rb") as stream:
            head = stream.read(16)
        if head.startswith(_SQLITE_MAGIC):
            yield from _db3_messages(path, self.topics, wanted, self.compression)
        elif head.startswith(_MCAP_MAGIC[:5]):
            from lidarscan.mcap import read_messages

            for item in read_messages(path, topics=wanted):
                if isinstance(item, McapMessage) and not item.metadata:
                    known = self.topics.get(item.topic)
                    if known is not None and known.metadata:
                        item = McapMessage(item.index, item.topic, item.msgtype,
                                           item.log_time_ns, item.publish_time_ns,
                                           item.sequence, item.payload, known.metadata,
                                           item.encoding)
                yield item
        else:
            err = McapFormatError(str(path), describe_bytes(head),
                                  "an sqlite3 .db3 or an MCAP storage file")
            yield BadMessage(-1, "", 0, f"{path.name}: {err}", err)


def _tagged(file_no: int, items: Iterator[McapMessage | BadMessage]
            ) -> Iterator[tuple[int, int, int, McapMessage | BadMessage]]:
    """(log time, file, position, item) keys for heapq.merge (never compares the items)."""
    for position, item in enumerate(items):
        yield item.log_time_ns, file_no, position, item


def open_bag(path: str | os.PathLike[str]) -> Bag:
    """Open a rosbag2 directory, ``.db3`` or ``.mcap`` file (see the module docstring).

    Raises:
        McapFormatError: not a bag, or a storage file that cannot be opened (the message says
            what the path is and why).
        ConversionError: a bag compressed per file (``compression_mode: FILE``).
    """
    p = Path(path)
    kind = detect_input(p)
    if kind.kind == "rosbag2":
        meta = p / "metadata.yaml"
        if meta.is_file():
            return _bag_from_metadata(p, meta)
        files = sorted(p.glob("*.db3")) or sorted(p.glob("*.mcap"))
        bag = Bag(p, files, {}, [f"{p}: no metadata.yaml; read {len(files)} storage file(s)"])
        _topics_from_files(bag)
        return bag
    if kind.kind in ("db3", "mcap"):
        bag = Bag(p, [p], {})
        _topics_from_files(bag)
        return bag
    raise McapFormatError(str(p), kind.description,
                          "a rosbag2 directory, a .db3 or an MCAP file")


def _bag_from_metadata(folder: Path, meta: Path) -> Bag:
    import yaml
    from lidarscan import _yaml

    try:
        doc = _yaml.safe_load(meta.read_text(encoding="utf-8"))
        info = doc["rosbag2_bagfile_information"]
        if not isinstance(info, dict):
            raise TypeError("rosbag2_bagfile_information is not a mapping")
    except (OSError, UnicodeDecodeError, yaml.YAMLError, KeyError, TypeError) as err:
        raise McapFormatError(str(meta), f"{type(err).__name__}: {err}",
                              "a rosbag2 metadata.yaml with rosbag2_bagfile_information") from err
    notes: list[str] = []
    mode = str(info.get("compression_mode") or "").upper()
    fmt = str(info.get("compression_format") or "")
    if mode == "FILE":
        raise ConversionError("compression_mode", "FILE", "an uncompressed bag or per-message "
                              "compression", hint="run `ros2 bag decompress` first")
    if mode == "MESSAGE" and fmt != "zstd":
        raise ConversionError("compression_format", fmt, "'zstd' for per-message compression")
    names = info.get("relative_file_paths") or [f.get("path") for f in info.get("files") or []
                                                if isinstance(f, dict)]
    files = [folder / str(n) for n in names if n]
    missing = [f.name for f in files if not f.is_file()]
    if missing or not files:
        found = sorted(folder.glob("*.db3")) or sorted(folder.glob("*.mcap"))
        notes.append(f"{meta}: storage file(s) {missing or 'none listed'}; read "
                     f"{[f.name for f in found]} found in the directory")
        files = found
    if not files:
        raise McapFormatError(str(folder), "no storage file",
                              "the .db3 or .mcap files metadata.yaml lists")
    storage = info.get("storage_identifier")
    if not storage:
        notes.append(f"{meta}: empty storage_identifier; storage told by each file's contents")
    topics: dict[str, TopicInfo] = {}
    for entry in info.get("topics_with_message_count") or []:
        try:
            tm = entry["topic_metadata"]
            name, msgtype = str(tm["name"]), str(tm["type"])
        except (KeyError, TypeError):
            notes.append(f"{meta}: unreadable topic entry {entry!r:.80}")
            continue
        fmt_ = str(tm.get("serialization_format") or "")
        if not fmt_:
            notes.append(f"{meta}: {name}: empty serialization_format, read as cdr")
        topics[name] = TopicInfo(name, msgtype, _int(entry.get("message_count")),
                                 fmt_ or "cdr", _qos_text(tm.get("offered_qos_profiles")))
    bag = Bag(folder, files, topics, notes, "zstd" if mode == "MESSAGE" else "")
    if not topics:
        _topics_from_files(bag)
    return bag


def _int(value: Any) -> int:
    try:
        return int(value)
    except (TypeError, ValueError):
        return 0


def _qos_text(value: Any) -> str:
    """offered_qos_profiles as the YAML text rosbag2 stores ("" / text / a parsed list)."""
    if value is None or value == "":
        return ""
    if isinstance(value, str):
        return value
    import yaml

    return str(yaml.safe_dump(value, sort_keys=False))


def _topics_from_files(bag: Bag) -> None:
    """Topics and counts from the storage files themselves (no metadata.yaml)."""
    for path in bag.files:
        with open(path, "rb") as stream:
            head = stream.read(16)
        if head.startswith(_SQLITE_MAGIC):
            with closing(_connect(path)) as con:
                for t in _db3_topics(con, path).values():
                    known = bag.topics.setdefault(t.name, TopicInfo(
                        t.name, t.msgtype, 0, t.serialization_format, t.offered_qos_profiles))
                    known.count += t.count
        elif head.startswith(_MCAP_MAGIC[:5]):
            _mcap_topics(path, bag.topics)
        else:
            raise McapFormatError(str(path), describe_bytes(head),
                                  "an sqlite3 .db3 or an MCAP storage file")


def _mcap_topics(path: Path, topics: dict[str, TopicInfo]) -> None:
    try:
        from mcap.reader import make_reader

        with open(path, "rb") as stream:
            summary = make_reader(stream).get_summary()
        if summary is not None and summary.channels and summary.statistics is not None:
            for cid, ch in summary.channels.items():
                schema = summary.schemas.get(ch.schema_id)
                known = topics.setdefault(ch.topic, TopicInfo(
                    ch.topic, schema.name if schema else "", 0, ch.message_encoding,
                    ch.metadata.get("offered_qos_profiles", "")))
                known.count += summary.statistics.channel_message_counts.get(cid, 0)
            return
    except Exception:  # noqa: BLE001, S110 - damaged summary: count by reading the file
        pass
    from lidarscan.mcap import read_messages

    for item in read_messages(path):
        if isinstance(item, McapMessage):
            known = topics.setdefault(item.topic, TopicInfo(
                item.topic, item.msgtype, 0, "cdr",
                item.metadata.get("offered_qos_profiles", "")))
            known.count += 1


# ---------------------------------------------------------------------------------- sqlite3

def _connect(path: Path) -> sqlite3.Connection:
    """Read-only, immutable (no journal or lock files next to a bag on a read-only disk; the
    file must not change while it is read, as for any rosbag2 reader)."""
    try:
        con = sqlite3.connect(f"{path.resolve().as_uri()}?mode=ro&immutable=1", uri=True)
        # damaged text must not raise UnicodeDecodeError; names stay readable, BLOBs are bytes
        con.text_factory = lambda raw: raw.decode("utf-8", "replace")
        # BLOBs read through a memory map: half the CPU of read() copies (bench_convert)
        con.execute("PRAGMA mmap_size=1073741824")
        con.execute("SELECT count(*) FROM sqlite_master").fetchone()
    except _SQL_ERRORS as err:
        raise McapFormatError(str(path), str(err), "a readable sqlite3 database") from err
    return con


def _db3_topics(con: sqlite3.Connection, path: Path) -> dict[int, TopicInfo]:
    """topic id -> TopicInfo (count from the messages table) of one .db3 file."""
    try:
        tables = {r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type='table'")}
        if not {"topics", "messages"} <= tables:
            raise McapFormatError(str(path), sorted(tables),
                                  "the rosbag2 tables 'topics' and 'messages'")
        columns = {r[1] for r in con.execute("PRAGMA table_info(topics)")}
        qos = "offered_qos_profiles" if "offered_qos_profiles" in columns else "''"
        fmt = "serialization_format" if "serialization_format" in columns else "''"
        query = f"SELECT id, name, type, {fmt}, {qos} FROM topics"  # noqa: S608 - fixed names
        rows = con.execute(query).fetchall()
        try:
            counts = dict(con.execute("SELECT topic_id, count(*) FROM messages "
                                      "GROUP BY topic_id").fetchall())
        except _SQL_ERRORS:
            counts = {}  # damaged rows: counted while they are read (and reported there)
        if "message_definitions" in tables:
            _register_definitions(con)
    except _SQL_ERRORS as err:
        raise McapFormatError(str(path), str(err), "a readable rosbag2 database") from err
    # a damaged topic row (no integer id, no name or type) is left out: its messages are then
    # reported as rows of an unknown topic
    return {tid: TopicInfo(str(name), str(msgtype), int(counts.get(tid) or 0),
                           str(sfmt or "cdr"), _qos_text(qp))
            for tid, name, msgtype, sfmt, qp in rows
            if isinstance(tid, int) and name is not None and msgtype is not None}


def _register_definitions(con: sqlite3.Connection) -> None:
    """Make the .msg texts stored by newer rosbag2 versions usable (unknown types only)."""
    from lidarscan.errors import LidarScanError
    from lidarscan.msgdef import find_msg_text, register_msg_text, split_schema_text

    rows = con.execute("SELECT topic_type, encoding, encoded_message_definition "
                       "FROM message_definitions").fetchall()
    for name, encoding, text in rows:
        if encoding != "ros2msg" or not text:
            continue
        try:
            for type_name, msg_text in split_schema_text(str(name), str(text)).items():
                try:
                    find_msg_text(type_name)
                except LidarScanError:
                    register_msg_text(type_name, msg_text)
        except LidarScanError:
            continue  # a type we cannot parse is reported when a message needs it


#: bytes of message data read through one sqlite3 connection before the next rows are read
#: through a new one: the pages a connection reads through its memory map stay mapped (and in
#: the process's RSS) until it is closed, so a bag read through one connection grew the RSS by
#: its whole size (bench/README.md, bench_fleet memory)
CHUNK_BYTES = 32 << 20


def _rows(con: sqlite3.Connection, path: Path | None = None,
          chunk_bytes: int = CHUNK_BYTES) -> Iterator[Any]:
    """(id, topic_id, timestamp, data) in time order; when the time order cannot be read (a
    damaged or truncated file), in row order, i.e. as recorded, as far as the rows can be read
    (an error after the first row is raised to the caller).

    The rows are streamed, one at a time from the cursor. With ``path`` (the file of ``con``)
    they are read through connections of this function's own: after every ``chunk_bytes`` of
    data the cursor and its connection are closed and the rest is read through a new one, from
    the last row's key on, so what stays memory-mapped is about one chunk whatever the file's
    size (only when the time order comes from an index, as in rosbag2's files: without one
    every chunk would sort the rest again, and one cursor reads it all). ``con`` is the
    caller's (never closed here; with ``path`` only asked how the rows can be ordered)."""
    query = "SELECT id, topic_id, timestamp, data FROM messages "
    order, where, key, last_id = "ORDER BY timestamp, id", "", (), 0
    try:
        probe = con.execute(query + order + " LIMIT 1")
        probe.fetchone()
        probe.close()
    except _SQL_ERRORS:
        order = "ORDER BY id"
    if order != "ORDER BY id" and not _time_indexed(con):
        path = None   # each chunk would sort the rest of the table again: one cursor
    while True:
        own = _connect(path) if path is not None else None
        cursor = (own or con).execute(query + where + order, key)
        try:
            size, last = 0, None
            for row in cursor:
                # ties of the timestamp resumed from: the rows up to the last id were given
                if key and order != "ORDER BY id" and row[2] == key[0] \
                        and isinstance(row[0], int) and row[0] <= last_id:
                    continue
                yield row
                size += len(row[3]) if isinstance(row[3], bytes) else 0
                # a chunk ends only after a row with integer keys (damaged rows stay in it)
                if own is not None and size >= chunk_bytes and isinstance(row[0], int) \
                        and (isinstance(row[2], int) or order == "ORDER BY id"):
                    last = row
                    break
        finally:
            cursor.close()   # before its connection: close() of a connection with a live
            if own is not None:   # statement only marks it (its map stays)
                own.close()
        if last is None:
            return
        if order == "ORDER BY id":
            where, key = "WHERE id > ? ", (last[0],)
        else:
            where, key, last_id = "WHERE timestamp >= ? ", (last[2],), last[0]


def _time_indexed(con: sqlite3.Connection) -> bool:
    """Whether the messages table has an index that starts with timestamp (rosbag2's
    ``timestamp_idx``): then the rows from a timestamp on come without a sort."""
    try:
        for index in con.execute("PRAGMA index_list(messages)").fetchall():
            first = con.execute(f"PRAGMA index_info('{index[1]}')").fetchone()
            if first is not None and first[2] == "timestamp":
                return True
    except _SQL_ERRORS:
        pass
    return False


def _db3_messages(path: Path, known: dict[str, TopicInfo], wanted: set[str] | None,
                  compression: str) -> Iterator[McapMessage | BadMessage]:
    """The rows of one .db3 file in (timestamp, id) order."""
    try:
        con = _connect(path)
    except McapFormatError as err:
        yield BadMessage(-1, "", 0, f"{path.name}: {err}", err)
        return
    try:
        topics = _db3_topics(con, path)
    except McapFormatError as err:
        con.close()
        yield BadMessage(-1, "", 0, f"{path.name}: {err}", err)
        return
    decompress = None
    if compression == "zstd":
        import zstandard

        decompress = zstandard.ZstdDecompressor().decompress
    ids = {tid for tid, t in topics.items() if wanted is None or t.name in wanted}
    done = 0
    try:
        for row_id, topic_id, stamp, data in _rows(con, path):
            done += 1
            topic = topics.get(topic_id)
            if topic is not None and topic_id not in ids:
                continue
            name = topic.name if topic is not None else ""
            log_time = stamp if isinstance(stamp, int) else 0
            problem = None
            if topic is None:
                problem = McapFormatError(f"messages.topic_id (row {row_id})", topic_id,
                                          "the id of a row of the topics table")
            elif not isinstance(stamp, int):
                problem = McapFormatError(f"messages.timestamp (row {row_id})", stamp,
                                          "an integer (ns)")
            elif not isinstance(data, bytes):
                problem = McapFormatError(f"messages.data (row {row_id})", type(data).__name__,
                                          "a BLOB of serialized message bytes")
            else:
                fmt = (known.get(name) or topic).serialization_format or "cdr"
                if fmt != "cdr":
                    problem = McapFormatError(f"topic {name} serialization_format", fmt, "cdr")
            if problem is None and decompress is not None:
                try:
                    data = decompress(data)
                except Exception as err:  # noqa: BLE001 - zstd raises its own error type
                    problem = McapFormatError(f"messages.data (row {row_id})", str(err),
                                              "a zstd-compressed message")
            if problem is not None or topic is None:
                yield BadMessage(int(row_id) if isinstance(row_id, int) else 0, name,
                                 log_time, str(problem), problem or McapFormatError(
                                     "messages.topic_id", topic_id, "a known topic"))
                continue
            meta = (known.get(name) or topic).metadata
            yield McapMessage(0, name, topic.msgtype, stamp, stamp, 0, data, meta)
    except _SQL_ERRORS as err:
        bad = McapFormatError(str(path), str(err), "a readable rosbag2 database")
        yield BadMessage(-1, "", 0, f"{path.name}: database damaged after {done} rows "
                         f"({err}); the rest of this file could not be read", bad)
    finally:
        con.close()


# ---------------------------------------------------------------------------------- packets

@dataclass(frozen=True)
class PacketScan:
    """The packets of one VelodyneScan / PandarScan message, as views of the message bytes.

    Attributes:
        frame_id: ``header.frame_id``.
        stamp_ns: ``header.stamp`` (int64 ns).
        stamps: (N,) int64 ns, each packet's recorded stamp.
        data: (N, 1206 or 1500) uint8, read-only strided view of each packet's ``data`` array.
        sizes: (N,) int64 bytes of ``data`` in use (VelodyneScan: 1206; PandarScan: ``size``).
    """

    frame_id: str
    stamp_ns: int
    stamps: Any
    data: Any
    sizes: Any

    @functools.cached_property
    def payloads(self) -> Any:
        """(N, size) uint8 view for ``PacketDecoder.push_many`` when every packet has the same
        size, else None (PandarScan with mixed ``size``). Computed once (``convert`` asks for
        it in its reading thread: the size test is a numpy loop that lets go of the GIL)."""
        n = len(self.sizes)
        if n == 0 or not bool((self.sizes == self.sizes[0]).all()):
            return None
        return self.data[:, :int(self.sizes[0])]

    @property
    def packets(self) -> list[tuple[int, memoryview]]:
        """``(stamp_ns, payload)`` per packet, payload a memoryview of ``data[i, :sizes[i]]``
        (built on demand: the batch path never needs it)."""
        return [(t, memoryview(row[:m])) for t, row, m in
                zip(self.stamps.tolist(), self.data, self.sizes.tolist())]


class _Cdr:
    """Reads CDR fields; alignment is relative to the byte after the encapsulation header."""

    def __init__(self, data: bytes | bytearray | memoryview, what: str) -> None:
        self.view = memoryview(data).cast("B")
        self.what = what
        if len(self.view) < 4:
            raise DecodeError(what, len(self.view), "at least the 4-byte CDR encapsulation header")
        kind = self.view[1]
        if self.view[0] != 0 or kind not in (0, 1):
            raise DecodeError(f"{what} encapsulation", bytes(self.view[:2]),
                              "plain CDR (00 00 big-endian or 00 01 little-endian)")
        self.order = "<" if kind == 1 else ">"
        self.pos = 4

    def align(self, n: int) -> None:
        self.pos += -(self.pos - 4) % n

    def take(self, n: int, field_: str) -> memoryview:
        end = self.pos + n
        if end > len(self.view):
            raise DecodeError(f"{self.what}.{field_}", len(self.view),
                              f"at least {end} bytes (message truncated)")
        out = self.view[self.pos:end]
        self.pos = end
        return out

    def u32(self, field_: str) -> int:
        self.align(4)
        return int(struct.unpack(self.order + "I", self.take(4, field_))[0])

    def time(self, field_: str) -> int:
        self.align(4)
        sec, nanosec = struct.unpack(self.order + "iI", self.take(8, field_))
        if nanosec >= 1_000_000_000:
            raise DecodeError(f"{self.what}.{field_}.nanosec", nanosec, "< 1e9")
        return int(sec) * 1_000_000_000 + int(nanosec)

    def header(self) -> tuple[str, int]:
        stamp = self.time("header.stamp")
        size = self.u32("header.frame_id length")
        raw = bytes(self.take(size, "header.frame_id"))
        if size == 0 or raw[-1:] != b"\x00":
            raise DecodeError(f"{self.what}.header.frame_id", raw[:40],
                              "a NUL-terminated string")
        try:
            return raw[:-1].decode("utf-8"), stamp
        except UnicodeDecodeError as err:
            raise DecodeError(f"{self.what}.header.frame_id", raw[:40], "UTF-8 text") from err

    def count(self, field_: str, item_size: int) -> int:
        n = self.u32(field_ + " length")
        if n * item_size > len(self.view) - self.pos:
            raise DecodeError(f"{self.what}.{field_} length", n,
                              f"at most {(len(self.view) - self.pos) // item_size} packets in "
                              f"the {len(self.view)}-byte message")
        return n


def _packet_arrays(reader: _Cdr, what: str, n: int, stride: int, data_at: int, size: int,
                   size_at: int | None = None) -> tuple[Any, Any, Any]:
    """Stamps (n,) int64 ns, payloads (n, size) uint8 and (PandarScan) the ``size`` fields of a
    CDR sequence of n fixed-stride packet structs starting at ``reader.pos`` (4-aligned): each
    struct is a Time at 0, the data at ``data_at``, a uint32 at ``size_at``. Views, no copy."""
    import numpy as np

    reader.align(4)
    start, view = reader.pos, reader.view
    end = start + (n - 1) * stride + (size_at + 4 if size_at is not None else data_at + size)
    if n and end > len(view):
        raise DecodeError(f"{what}.packets", len(view), f"at least {end} bytes (message "
                          "truncated)")
    order = reader.order
    buf = np.frombuffer(view, np.uint8)
    words = np.ndarray((n, 2), np.dtype(order + "u4"), buf, start, (stride, 4)) if n else \
        np.zeros((0, 2), np.uint32)
    sec, nanosec = words[:, 0].view(order + "i4").astype(np.int64), words[:, 1].astype(np.int64)
    bad = np.flatnonzero(nanosec >= 1_000_000_000)
    if bad.size:
        k = int(bad[0])
        raise DecodeError(f"{what}.packets[{k}].stamp.nanosec", int(nanosec[k]), "< 1e9")
    payloads = np.ndarray((n, size), np.uint8, buf, start + data_at, (stride, 1))
    payloads.flags.writeable = False
    sizes = None
    if size_at is not None:
        sizes = np.ndarray((n,), np.dtype(order + "u4"), buf, start + size_at, (stride,)) \
            .astype(np.int64) if n else np.zeros(0, np.int64)
    reader.pos = max(reader.pos, end)
    return sec * 1_000_000_000 + nanosec, payloads, sizes


def velodyne_packets(cdr: bytes | bytearray | memoryview) -> PacketScan:
    """``velodyne_msgs/msg/VelodyneScan`` CDR -> :class:`PacketScan` (1206-byte payloads).

    Each VelodynePacket is a Time (8 bytes) and ``uint8[1206]``, padded to 1216 bytes so that
    the next Time is 4-aligned: the packets are read as one strided array.

    Raises:
        DecodeError: truncated message, bad encapsulation, count larger than the message.
    """
    import numpy as np

    reader = _Cdr(cdr, "VelodyneScan")
    frame_id, stamp = reader.header()
    n = reader.count("packets", 8 + 1206)
    stamps, payloads, _ = _packet_arrays(reader, "VelodyneScan", n, 1216, 8, 1206)
    return PacketScan(frame_id, stamp, stamps, payloads, np.full(n, 1206, np.int64))


def pandar_packets(cdr: bytes | bytearray | memoryview) -> PacketScan:
    """``pandar_msgs/msg/PandarScan`` CDR -> :class:`PacketScan` (payload = ``data[:size]``).

    Each PandarPacket is a Time (8 bytes), ``uint8[1500]`` and a uint32 ``size``: 1512 bytes,
    no padding, read as one strided array.

    Raises:
        DecodeError: truncated message, bad encapsulation, count larger than the message,
            ``size`` > 1500.
    """
    import numpy as np

    reader = _Cdr(cdr, "PandarScan")
    frame_id, stamp = reader.header()
    n = reader.count("packets", 8 + 1500 + 4)
    stamps, data, sizes = _packet_arrays(reader, "PandarScan", n, 1512, 8, 1500, 1508)
    big = np.flatnonzero(sizes > 1500)
    if big.size:
        raise DecodeError(f"PandarScan.packets[{big[0]}].size", int(sizes[big[0]]),
                          "at most 1500 bytes")
    return PacketScan(frame_id, stamp, stamps, data, sizes)


def ouster_packets(cdr: bytes | bytearray | memoryview) -> PacketScan:
    """ouster-ros ``PacketMsg`` CDR (``uint8[] buf``) -> :class:`PacketScan` of its one
    packet: frame_id "", stamps 0 (the message has no header; Ouster packets carry their own
    times), ``data`` (1, len(buf)) read-only view of ``buf``.

    Raises:
        DecodeError: truncated message, bad encapsulation, a length beyond the message.
    """
    import numpy as np

    reader = _Cdr(cdr, "PacketMsg")
    n = reader.count("buf", 1)
    data = np.frombuffer(reader.take(n, "buf"), np.uint8)[None, :]
    data.flags.writeable = False
    return PacketScan("", 0, np.zeros(1, np.int64), data, np.array([n], np.int64))


#: packet message type -> (module providing ``PacketDecoder``, parser of the message's CDR);
#: an Ouster PacketMsg holds one packet, and its decoder needs the sensor's metadata
#: (``lidarscan convert`` finds it in the recording)
PACKET_TYPES: dict[str, tuple[str, Any]] = {
    VELODYNE_SCAN: ("converters.sources.velodyne", velodyne_packets),
    PANDAR_SCAN: ("converters.sources.hesai.decoder", pandar_packets),
    **{name: ("converters.sources.ouster.decoder", ouster_packets)
       for name in OUSTER_PACKET_TYPES},
}

_PACKET_MSGS = {
    "velodyne_msgs/msg/VelodyneScan": "std_msgs/Header header\nVelodynePacket[] packets\n",
    "velodyne_msgs/msg/VelodynePacket": "builtin_interfaces/Time stamp\nuint8[1206] data\n",
    "pandar_msgs/msg/PandarScan": "std_msgs/Header header\nPandarPacket[] packets\n",
    "pandar_msgs/msg/PandarPacket": "builtin_interfaces/Time stamp\nuint8[1500] data\n"
                                   "uint32 size\n",
    **{name: "uint8[] buf\n" for name in OUSTER_PACKET_TYPES},
}


def register_packet_types() -> None:
    """Make the packet message definitions known (to copy packet topics into an MCAP file
    with their schema) unless this installation already has them."""
    from lidarscan.errors import LidarScanError
    from lidarscan.msgdef import find_msg_text, register_msg_text

    for name, text in _PACKET_MSGS.items():
        try:
            find_msg_text(name)
        except LidarScanError:
            register_msg_text(name, text)
