"""MCAP reading (see :mod:`lidarscan.mcap`, which re-exports the public names): sequential,
forgiving, every record checked on its own; damage reported as :class:`BadMessage` and read past.
The records themselves are parsed with :mod:`lidarscan.mcap._records`."""

from __future__ import annotations

import io
import os
import struct
import zlib
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import IO, Any

from lidarscan.errors import LidarScanError, McapFormatError
from lidarscan.mcap._records import (
    _FOOTER_SIZE,
    _MAGIC,
    _OP_ATTACHMENT,
    _OP_CHANNEL,
    _OP_CHUNK,
    _OP_CHUNK_INDEX,
    _OP_DATA_END,
    _OP_FOOTER,
    _OP_MESSAGE,
    _OP_MESSAGE_INDEX,
    _OP_SCHEMA,
    _PIECE,
    CODEC_ENCODING,
    INFO_TYPE,
    SCAN_TYPE,
    BadMessage,
    McapMessage,
    _Cursor,
    _decompress,
    _open,
    _register_schema,
    _stamp,
    describe_bytes,
)

__all__ = ["read_messages", "read_scans"]


@dataclass
class _Damage:
    """A damaged chunk, reported once the message indexes after it have been counted."""

    offset: int
    start_ns: int | None
    end_ns: int | None
    why: str
    counts: dict[int, int] = field(default_factory=dict)


class _Reader:
    """One pass over an MCAP file's data section that survives damaged records (see
    :func:`read_messages`)."""

    def __init__(self, stream: IO[bytes], wanted: set[str] | None) -> None:
        self.stream, self.wanted = stream, wanted
        self.schemas: dict[int, tuple[str, Exception | None]] = {}
        self.channels: dict[int, tuple[str, str, Exception | None, dict[str, str], str]] = {}
        self.index = 0
        self.pos = 0
        self.crc = 0
        self.crc_valid = True  # False once bytes were skipped: the data-section CRC is moot
        self.size: int | None = None
        self.chunk_starts: list[int] = []
        self.summary_problem: BadMessage | None = None
        self.pending: _Damage | None = None
        self.reported = False  # some damage was reported already
        self.has_footer = False
        try:
            if stream.seekable():
                self.pos = stream.tell()
                self.size = stream.seek(0, io.SEEK_END)
                stream.seek(self.pos)
        except (OSError, AttributeError, ValueError):
            self.size = None

    # ---------------------------------------------------------------------------- bytes
    def read(self, n: int) -> bytes:
        parts = []
        left = n
        while left > 0:
            part = self.stream.read(min(left, _PIECE))
            if not part:
                break
            parts.append(part)
            left -= len(part)
        data = parts[0] if len(parts) == 1 else b"".join(parts)
        self.pos += len(data)
        if self.crc_valid:
            self.crc = zlib.crc32(data, self.crc)
        return data

    def seek(self, offset: int) -> None:
        self.stream.seek(offset)
        self.pos = offset
        self.crc_valid = False

    # -------------------------------------------------------------------------- reports
    def damage(self, offset: int, why: str, *, log_time_ns: int = 0) -> BadMessage:
        self.reported = True
        reason = f"file damaged at offset {offset}: {why}"
        return BadMessage(-1, "", log_time_ns, reason,
                          McapFormatError(f"record at offset {offset}", why, "a valid record"),
                          offset=offset)

    def flush(self) -> Iterator[BadMessage]:
        damage, self.pending = self.pending, None
        if damage is None:
            return
        self.reported = True
        span = (f"log time {_stamp(damage.start_ns)} .. {_stamp(damage.end_ns)}"
                if damage.start_ns is not None and damage.end_ns is not None
                else "log time unknown")
        lost = sum(damage.counts.values())
        if damage.counts:
            topics = sorted({self.channels.get(c, (f"channel {c}",))[0] for c in damage.counts})
            span += f", {lost} message(s) on {', '.join(topics)}"
        self.index += lost
        yield BadMessage(-1, "", damage.start_ns or 0,
                         f"damaged chunk at offset {damage.offset} ({span}) skipped: "
                         f"{damage.why}",
                         McapFormatError(f"chunk at offset {damage.offset}", damage.why,
                                         "an intact chunk"),
                         offset=damage.offset, end_time_ns=damage.end_ns)

    # ------------------------------------------------------------------------- summary
    def load_summary(self) -> None:
        """Schemas, channels and chunk offsets from a summary whose CRC checks out."""
        size = self.size
        if size is None or size < 8 + _FOOTER_SIZE + 8:
            return
        here = self.stream.tell()
        try:
            footer_at = size - 8 - _FOOTER_SIZE
            self.stream.seek(footer_at)
            tail = self.stream.read(_FOOTER_SIZE + 8)
            if len(tail) != _FOOTER_SIZE + 8 or tail[-8:] != _MAGIC or tail[0] != _OP_FOOTER \
                    or struct.unpack_from("<Q", tail, 1)[0] != 20:
                return  # no footer: reported after the data section
            self.has_footer = True
            start, _offsets, crc = struct.unpack_from("<QQI", tail, 9)
            if start == 0:
                return  # a file written without a summary: nothing to check
            if not 8 <= start <= footer_at:
                self.summary_problem = self.damage(
                    footer_at, f"the footer points to a summary at offset {start}, outside "
                    "the file; the data section was read without it")
                return
            self.stream.seek(start)
            summary = self.stream.read(footer_at - start)
            if crc != 0 and zlib.crc32(tail[:25], zlib.crc32(summary)) != crc:
                self.summary_problem = self.damage(
                    start, "summary CRC mismatch; the data section was read without it")
                return
            self._summary_records(summary, start)
        except LidarScanError as err:
            self.summary_problem = self.damage(size, f"unreadable summary ({err}); the data "
                                               "section was read without it")
        finally:
            self.stream.seek(here)

    def _summary_records(self, summary: bytes, start: int) -> None:
        view = memoryview(summary)
        pos = 0
        while pos < len(view):
            if pos + 9 > len(view):
                raise McapFormatError(f"summary record at offset {start + pos}", len(view) - pos,
                                      "a 9-byte record header")
            op, length = struct.unpack_from("<BQ", view, pos)
            body = _Cursor(view[pos + 9:pos + 9 + length], f"summary record at {start + pos}")
            if len(body.data) != length:
                raise McapFormatError(f"summary record at offset {start + pos}", length,
                                      "a record length within the summary")
            if op == _OP_SCHEMA:
                self.schema(body)
            elif op == _OP_CHANNEL:
                self.channel(body)
            elif op == _OP_CHUNK_INDEX:
                body.take(16)
                self.chunk_starts.append(body.u64())
            pos += 9 + length
        self.chunk_starts.sort()

    # ------------------------------------------------------------------------ records
    def schema(self, body: _Cursor) -> None:
        sid = body.u16()
        name = body.text()
        encoding = body.text()
        data = bytes(body.take(body.u32()))
        try:
            if encoding != "ros2msg":
                raise McapFormatError(f"schema {name}", encoding, "encoding 'ros2msg'")
            try:
                text = data.decode("utf-8")
            except UnicodeDecodeError as bad_text:
                raise McapFormatError(f"schema {name}", data[:40],
                                      "UTF-8 message definition text") from bad_text
            self.schemas[sid] = (_register_schema(name, text), None)
        except LidarScanError as bad_schema:
            self.schemas[sid] = (name, bad_schema)

    def channel(self, body: _Cursor) -> None:
        cid = body.u16()
        schema_id = body.u16()
        topic = body.text()
        encoding = body.text()
        metadata = body.string_map()
        name, err = self.schemas.get(schema_id, ("", McapFormatError(
            f"channel {topic}", schema_id, "a known schema id")))
        if err is None and encoding != "cdr" and not (encoding == CODEC_ENCODING
                                                        and name == SCAN_TYPE):
            err = McapFormatError(f"channel {topic}", encoding,
                                  f"message encoding 'cdr' ({CODEC_ENCODING!r}: {SCAN_TYPE})")
        self.channels[cid] = (topic, name, err, metadata, encoding)

    def message(self, data: bytes | memoryview) -> Iterator[McapMessage | BadMessage]:
        if len(data) < 22:
            raise McapFormatError("message record", len(data), "at least 22 bytes")
        cid, sequence, log_time, publish_time = struct.unpack_from("<HIQQ", data)
        topic, name, err, metadata, encoding = self.channels.get(cid, ("", "", McapFormatError(
            "message.channel_id", cid, "a channel defined before it"), {}, "cdr"))
        if self.wanted is None or topic in self.wanted:
            if err is not None:
                yield BadMessage(self.index, topic, log_time, str(err), err)
            else:
                yield McapMessage(self.index, topic, name, log_time, publish_time, sequence,
                                  bytes(data[22:]), metadata, encoding)
        self.index += 1

    def definitions_and_messages(self, op: int, body: bytes | memoryview
                                 ) -> Iterator[McapMessage | BadMessage]:
        """Schema, Channel and Message records, in a chunk or outside one."""
        if op == _OP_MESSAGE:
            yield from self.message(body)
        elif op == _OP_SCHEMA:
            self.schema(_Cursor(body, "schema record"))
        elif op == _OP_CHANNEL:
            self.channel(_Cursor(body, "channel record"))

    def chunk(self, content: bytes, offset: int) -> Iterator[McapMessage | BadMessage]:
        body = _Cursor(memoryview(content), f"chunk at offset {offset}")  # slices: no copies
        start_ns, end_ns = body.u64(), body.u64()
        try:
            size, crc = body.u64(), body.u32()
            compression = body.text()
            records = body.take(body.u64())
            if body.pos != len(content):
                raise McapFormatError("chunk.records length", len(records),
                                      f"{len(content) - body.pos + len(records)} bytes")
            data = _decompress(compression, records, size)
            if crc != 0 and zlib.crc32(data) != crc:
                raise McapFormatError("chunk CRC", f"{zlib.crc32(data):#010x}",
                                      f"{crc:#010x} (the chunk's bytes were altered)")
        except LidarScanError as err:
            self.pending = _Damage(offset, start_ns, end_ns, str(err))
            return
        view = memoryview(data)
        pos = 0
        while pos < len(view):
            try:
                if pos + 9 > len(view):
                    raise McapFormatError("record header", len(view) - pos, "9 bytes")
                op, length = struct.unpack_from("<BQ", view, pos)
                if length > len(view) - pos - 9:
                    raise McapFormatError("record length", length,
                                          f"at most {len(view) - pos - 9} (the chunk's end)")
                yield from self.definitions_and_messages(op, view[pos + 9:pos + 9 + length])
            except LidarScanError as err:  # intact chunk (or no CRC) but a broken record
                self.pending = _Damage(offset, start_ns, end_ns,
                                       f"record at chunk byte {pos}: {err}; rest of the chunk")
                return
            pos += 9 + length

    def attachment(self, content: bytes, offset: int) -> Iterator[BadMessage]:
        body = _Cursor(content, f"attachment at offset {offset}")
        log_time = body.u64()
        body.u64()
        name = body.text()
        body.text()
        body.take(body.u64())
        stored = body.u32()
        if stored != 0 and zlib.crc32(content[:body.pos - 4]) != stored:
            yield self.damage(offset, f"attachment {name!r} CRC mismatch (its bytes were "
                              "altered)", log_time_ns=log_time)

    # ------------------------------------------------------------------------ resync
    def resync(self, after: int) -> int | None:
        """Offset of the next chunk after ``after`` (from the summary, else found by its
        header's internal consistency), or None."""
        if self.size is None:
            return None
        for start in self.chunk_starts:
            if start > after:
                return start
        self.stream.seek(after)
        base = after
        while base < self.size:
            window = self.stream.read(1 << 20)
            if not window:
                break
            self.stream.seek(base + len(window))
            extra = self.stream.read(64)
            block = window + extra
            hit = block.find(b"\x06")
            while 0 <= hit < len(window):
                if self._looks_like_chunk(block, hit, base + hit):
                    return base + hit
                hit = block.find(b"\x06", hit + 1)
            base += len(window)
            self.stream.seek(base)
        return None

    def _looks_like_chunk(self, block: bytes, at: int, offset: int) -> bool:
        head = block[at:at + 41]
        if len(head) < 41 or self.size is None:
            return False
        length, start, end, size, _crc, clen = struct.unpack_from("<QQQQII", head, 1)
        if length > self.size - offset - 9 or start > end or clen > 8 or size > 1 << 40:
            return False
        tail = block[at + 41:at + 41 + clen + 8]
        if len(tail) < clen + 8 or tail[:clen] not in (b"", b"zstd", b"lz4"):
            return False
        records = struct.unpack_from("<Q", tail, clen)[0]
        return bool(records == length - (8 + 8 + 8 + 4 + 4 + clen + 8))

    # -------------------------------------------------------------------------- main
    def messages(self) -> Iterator[McapMessage | BadMessage]:
        head = self.read(8)
        if head != _MAGIC:
            kind = describe_bytes(head)
            if kind == "an empty file":
                why = "the file is empty"
            elif kind == "an MCAP file":
                why = "an MCAP file cut inside its magic, or its magic is damaged"
            elif kind.startswith("not "):
                why = kind
            else:
                why = f"not an MCAP file: {kind}"
            self.reported = True
            yield BadMessage(-1, "", 0, why, McapFormatError("file", kind, "an MCAP file"),
                             offset=0)
            return
        self.load_summary()
        while True:
            record_at, crc_before = self.pos, self.crc
            header = self.read(9)
            if len(header) < 9:
                yield from self.flush()
                yield self.damage(record_at, "the file ends here without its data-end record, "
                                  "summary and footer (truncated: a writer was interrupted or "
                                  "the copy is incomplete)")
                break
            op, length = struct.unpack("<BQ", header)
            if op != _OP_MESSAGE_INDEX:
                yield from self.flush()
            left = None if self.size is None else self.size - self.pos
            if op == 0 or 0x10 <= op < 0x80 or (left is not None and length > left):
                partial = self.read(min(length, 64)) if op == _OP_CHUNK else b""
                span = ""
                if len(partial) >= 16:
                    a, b = struct.unpack_from("<QQ", partial)
                    span = f" (a chunk, log time {_stamp(a)} .. {_stamp(b)})"
                why = (f"byte {op:#04x} is not a record opcode" if op == 0 or 0x10 <= op < 0x80
                       else f"record{span} declares {length} bytes but only {left} are left "
                       "(truncated or damaged)")
                target = self.resync(record_at + 1)
                yield self.damage(record_at, why + (
                    f"; reading resumes at the next chunk, offset {target}" if target else
                    "; nothing after it could be read"))
                if target is None:
                    break
                self.seek(target)
                continue
            content = self.read(length)
            if len(content) < length:
                yield self.damage(record_at, f"the file ends inside a record of {length} "
                                  f"bytes ({len(content)} present): truncated")
                break
            try:
                if op == _OP_CHUNK:
                    yield from self.chunk(content, record_at)
                elif op in (_OP_MESSAGE, _OP_SCHEMA, _OP_CHANNEL):
                    yield from self.definitions_and_messages(op, content)
                elif op == _OP_MESSAGE_INDEX and self.pending is not None:
                    body = _Cursor(content, "message index")
                    cid = body.u16()
                    entries = body.u32() // 16
                    self.pending.counts[cid] = self.pending.counts.get(cid, 0) + entries
                elif op == _OP_ATTACHMENT:
                    yield from self.attachment(content, record_at)
                elif op == _OP_DATA_END:
                    stored = struct.unpack_from("<I", content)[0] if len(content) >= 4 else 0
                    if stored != 0 and self.crc_valid and crc_before != stored \
                            and not self.reported:
                        yield self.damage(record_at, "data-section CRC mismatch (bytes outside "
                                          "the chunks were altered)")
                    if self.size is not None and not self.has_footer:
                        yield self.damage(self.size, "the file ends without its footer after "
                                          "the data section (summary and footer missing: "
                                          "truncated?)")
                    break
                elif op == _OP_FOOTER:
                    break
            except LidarScanError as err:
                yield from self.flush()
                yield self.damage(record_at, f"unreadable record (opcode {op:#04x}): {err}")
        yield from self.flush()
        if self.summary_problem is not None:
            yield self.summary_problem


def read_messages(source: str | os.PathLike[str] | IO[bytes] | bytes, *,
                  topics: Iterable[str] | None = None) -> Iterator[McapMessage | BadMessage]:
    """Iterate the messages of an MCAP file in file order.

    Yields :class:`McapMessage` for every record (undecoded: call ``.decode()``), and
    :class:`BadMessage` for a record whose channel/schema is unusable and for every damaged
    part of the file; iteration always continues past a bad part when the file structure allows
    it:

    * a chunk whose CRC does not match, whose compressed stream does not decompress or whose
      records are malformed is reported once (offset, log-time range, and the number of messages
      and topics lost when the message indexes after it say so) and reading goes on with the
      next record;
    * a record whose length runs past the end of the file (truncation, or a damaged length) is
      reported and reading resumes at the next chunk: found from the summary's chunk index when
      the summary's CRC checks out, else by scanning for a chunk header that is consistent with
      itself (what ``mcap recover`` does);
    * the summary is only used to recover (channels defined in a damaged chunk, resync points):
      a damaged summary is reported, a missing one is not needed;
    * attachment and data-section CRCs are checked when the writer stored them (non-zero).

    Args:
        source: path, binary stream or the file's bytes.
        topics: only these topics (default all).
    """
    wanted = set(topics) if topics is not None else None
    stream, own = _open(source)
    try:
        yield from _Reader(stream, wanted).messages()
    finally:
        if own:
            stream.close()


def read_scans(source: str | os.PathLike[str] | IO[bytes] | bytes | None, *,
               scan_topics: Iterable[str] | None = None, info_topics: Iterable[str] | None = None,
               on_error: Callable[[BadMessage], None] | None = None,
               max_pending: int = 64, max_infos: int = 256,
               items: Iterable[McapMessage | BadMessage] | None = None
               ) -> Iterator[tuple[Any, Any]]:
    """Iterate ``(scan, info)`` pairs: each LidarScan with the LidarInfo its
    ``lidar_info_time`` names (decoded dataclasses; the scan's data views the file's bytes).

    Scans recorded before their info are held (at most ``max_pending``) until it appears;
    scans whose info never appears, undecodable messages and inconsistent scans are passed to
    ``on_error`` (as :class:`BadMessage`) and skipped; the rest are yielded. In a file the info
    wait is bounded by the file, not by time.

    Which info a scan may take: the topic convention is a namespace per sensor
    (``<ns>/lidar_scan`` + ``<ns>/lidar_info``, as the nodes and ``lidarscan convert`` write
    them). A scan whose namespace has carried a LidarInfo is paired only with the infos of that
    namespace, so two sensors whose infos share a stamp (simulation time, one launch) do not
    make each other ambiguous; a scan of a namespace without one (other topic names) is paired
    with the infos of every topic by stamp alone. Each resolver holds ``max_infos`` versions,
    the least recently published or used evicted first (a recording's latched infos all come
    first, so the fallback must hold one per sensor plus the versions whose stragglers may still
    come). ``items`` (then ``source`` is ignored) reads messages from another reader (e.g. a
    rosbag2 reader of the same items).
    """
    from lidarscan.linkage import InfoResolver

    scans = set(scan_topics) if scan_topics is not None else None
    infos = set(info_topics) if info_topics is not None else None

    def resolver() -> InfoResolver:
        return InfoResolver(max_pending=max_pending, max_infos=max_infos, max_wait_ns=None)

    anywhere = resolver()                       # every topic's infos: by stamp alone
    per_namespace: dict[str, InfoResolver] = {}  # namespaces that carry a LidarInfo
    origin: dict[int, McapMessage] = {}

    def report(bad: BadMessage) -> None:
        if on_error is not None:
            on_error(bad)

    def drops() -> None:
        for res in (anywhere, *per_namespace.values()):
            for drop in res.take_dropped():
                src = origin.pop(id(drop.scan), None)
                report(BadMessage(src.index if src else -1, src.topic if src else "",
                                  src.log_time_ns if src else 0, drop.reason,
                                  McapFormatError("lidar_info_time", drop.info_stamp_ns,
                                                  "a LidarInfo with this stamp")))

    for item in (items if items is not None else read_messages(source)):  # type: ignore[arg-type]
        if isinstance(item, BadMessage):
            report(item)
            continue
        is_scan = item.msgtype == SCAN_TYPE and (scans is None or item.topic in scans)
        is_info = item.msgtype == INFO_TYPE and (infos is None or item.topic in infos)
        if not (is_scan or is_info):
            continue
        namespace = item.topic.rpartition("/")[0]
        try:
            msg = item.decode()
            if is_info:
                own = per_namespace.get(namespace) or per_namespace.setdefault(namespace,
                                                                               resolver())
                ready = own.add_info(msg) + anywhere.add_info(msg)
            else:
                ready = per_namespace.get(namespace, anywhere).add_scan(msg)
                origin[id(msg)] = item
        except LidarScanError as err:
            report(BadMessage(item.index, item.topic, item.log_time_ns, str(err), err))
            continue
        drops()
        for scan, info in ready:
            origin.pop(id(scan), None)
            yield scan, info
    for res in (anywhere, *per_namespace.values()):
        res.flush()
    drops()
