"""The MCAP file layer of reading (below :mod:`lidarscan.mcap._reader`): what a message record
is (:class:`McapMessage`, :class:`BadMessage`), the project's names (:data:`SCAN_TYPE`,
:data:`INFO_TYPE`, :data:`CODEC_ENCODING`), the magic and opcodes, the field reader of one record,
chunk decompression that never trusts a stated size, and schema registration. The record
writer (chunks, indexes, CRCs, summary) is :mod:`lidarscan.mcap._file`."""

from __future__ import annotations

import io
import os
import re
import struct
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from lidarscan.cdr import decode
from lidarscan.errors import McapFormatError, SchemaError
from lidarscan.msgdef import (
    find_msg_text,
    get_msgdef,
    normalize_type,
    parse_msg,
    register_msg_text,
    split_schema_text,
)

__all__ = ["McapMessage", "BadMessage", "describe_bytes", "SCAN_TYPE", "INFO_TYPE",
           "CODEC_ENCODING"]

SCAN_TYPE = "lidarscan_msgs/msg/LidarScan"
#: MCAP message encoding of a LidarScan channel whose messages are :mod:`lidarscan.codec`
#: buffers (magic "LSCZ" + format version) instead of CDR; the schema stays the LidarScan's.
CODEC_ENCODING = "lidarscan.codec"
INFO_TYPE = "lidarscan_msgs/msg/LidarInfo"


@dataclass(frozen=True)
class McapMessage:
    """One message record.

    Attributes:
        index: position of the message in the file (0-based, over all topics).
        topic, msgtype: channel topic and ``pkg/msg/Name``.
        log_time_ns, publish_time_ns, sequence: record fields.
        payload: the encoded bytes: CDR, or a :mod:`lidarscan.codec` buffer when
            ``encoding`` is :data:`CODEC_ENCODING`.
        metadata: the channel's metadata (e.g. ``offered_qos_profiles``), shared by the
            messages of a channel.
        encoding: the channel's message encoding ("cdr" or :data:`CODEC_ENCODING`).
    """

    index: int
    topic: str
    msgtype: str
    log_time_ns: int
    publish_time_ns: int
    sequence: int
    payload: bytes
    metadata: Mapping[str, str] = field(default_factory=dict, compare=False, repr=False)
    encoding: str = "cdr"

    def decode(self, coder: Any = "auto") -> Any:
        """Decode the payload into a :mod:`lidarscan.types` dataclass (raises DecodeError);
        a compressed LidarScan is decompressed (``coder``: as ``McapWriter``'s
        ``codec_coder``, by default the compiled coder when numba is installed)."""
        if self.encoding == CODEC_ENCODING:
            from lidarscan import codec
            return codec.decompress_scan(self.payload, coder=coder)
        return decode(self.payload, self.msgtype)


@dataclass(frozen=True)
class BadMessage:
    """A message (or the end of a damaged file) that could not be read; nothing else is lost.

    Attributes:
        index: message index in the file (-1 when it is about the file itself).
        topic: topic name ("" if unknown).
        log_time_ns: record time (0 if unknown).
        reason: what went wrong.
        error: the exception raised (always a :class:`LidarScanError`).
        offset: byte offset of the damaged record in the file (-1 for a single message).
        end_time_ns: for a damaged chunk, the last log time it covered (``log_time_ns`` is
            the first).
    """

    index: int
    topic: str
    log_time_ns: int
    reason: str
    error: Exception = field(repr=False)
    offset: int = -1
    end_time_ns: int | None = None


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


_MAGIC = b"\x89MCAP0\r\n"
_SQLITE_MAGIC = b"SQLite format 3\x00"
(_OP_HEADER, _OP_FOOTER, _OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK, _OP_MESSAGE_INDEX,
 _OP_CHUNK_INDEX, _OP_ATTACHMENT, _OP_ATTACHMENT_INDEX, _OP_STATISTICS, _OP_METADATA,
 _OP_METADATA_INDEX, _OP_SUMMARY_OFFSET, _OP_DATA_END) = range(1, 16)
_FOOTER_SIZE = 1 + 8 + 8 + 8 + 4  # opcode, length, summary_start, summary_offset_start, crc
_PIECE = 16 << 20  # read large records in pieces: memory follows the bytes actually there


def _stamp(ns: int) -> str:
    return f"{ns // 1_000_000_000}.{ns % 1_000_000_000:09d}"


def describe_bytes(head: bytes) -> str:
    """What the first bytes of a file look like, for error messages ("an SQLite database")."""
    if not head:
        return "an empty file"
    if head.startswith(_MAGIC[:4]) or _MAGIC.startswith(head[:8]):
        return "an MCAP file"
    if head.startswith(_SQLITE_MAGIC):
        return "an SQLite database (a rosbag2 .db3 file?)"
    if head.startswith(b"\xd4\xc3\xb2\xa1") or head.startswith(b"\xa1\xb2\xc3\xd4") or \
            head.startswith(b"\x0a\x0d\x0d\x0a"):
        return "a pcap capture"
    if head.startswith(b"#ROSBAG"):
        return "a ROS 1 bag"
    if head.lstrip()[:1] in (b"{", b"["):
        return "a JSON file"
    return f"not an MCAP file (starts with {head[:8]!r})"


class _Cursor:
    """Little-endian field reader over one record's bytes; raises McapFormatError when short."""

    __slots__ = ("data", "pos", "what")

    def __init__(self, data: bytes | memoryview, what: str) -> None:
        self.data, self.pos, self.what = data, 0, what

    def take(self, n: int) -> bytes | memoryview:
        end = self.pos + n
        if n < 0 or end > len(self.data):
            raise McapFormatError(self.what, len(self.data) - self.pos,
                                  f"at least {n} more bytes at record byte {self.pos}")
        out = self.data[self.pos:end]
        self.pos = end
        return out

    def u16(self) -> int:
        return int(struct.unpack_from("<H", self.take(2))[0])

    def u32(self) -> int:
        return int(struct.unpack_from("<I", self.take(4))[0])

    def u64(self) -> int:
        return int(struct.unpack_from("<Q", self.take(8))[0])

    def text(self) -> str:
        raw = bytes(self.take(self.u32()))
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError as err:
            raise McapFormatError(self.what, raw[:40], "UTF-8 text") from err

    def string_map(self) -> dict[str, str]:
        inner = _Cursor(self.take(self.u32()), self.what)
        out: dict[str, str] = {}
        while inner.pos < len(inner.data):
            key = inner.text()
            out[key] = inner.text()
        return out


def _decompress(compression: str, data: bytes | memoryview, size: int) -> bytes:
    """A chunk's records; the output is read in pieces up to the declared ``size`` (+1 to see
    a longer stream), so a damaged size field costs no more memory than the real output."""
    if compression == "":
        return bytes(data)
    stream = io.BytesIO(data)
    errors: tuple[type[BaseException], ...]
    if compression == "zstd":
        import zstandard
        try:  # the frame header states the size too (when the writer stored it): compare
            stated = zstandard.frame_content_size(stream.getbuffer())
        except zstandard.ZstdError as err:
            raise McapFormatError("chunk", "zstd", f"a valid zstd frame header ({err})") from err
        if stated >= 0 and stated != size:
            raise McapFormatError("chunk.uncompressed_size", size,
                                  f"the size the zstd frame header states ({stated})")
        reader: Any = zstandard.ZstdDecompressor().stream_reader(stream)
        errors = (zstandard.ZstdError,)
    elif compression == "lz4":
        import lz4.frame
        try:
            stated = int(lz4.frame.get_frame_info(stream.getvalue())["content_size"])
        except (RuntimeError, KeyError, TypeError, ValueError) as err:
            raise McapFormatError("chunk", "lz4", f"a valid lz4 frame header ({err})") from err
        if stated > 0 and stated != size:  # 0: not stated
            raise McapFormatError("chunk.uncompressed_size", size,
                                  f"the size the lz4 frame header states ({stated})")
        reader = lz4.frame.LZ4FrameFile(stream)
        errors = (RuntimeError, EOFError, ValueError, OSError)
    else:
        raise McapFormatError("chunk.compression", compression, "'zstd', 'lz4' or ''")
    parts: list[bytes] = []
    total = 0
    try:
        while total <= size:
            piece = reader.read(min(_PIECE // 4, size + 1 - total))
            if not piece:
                break
            parts.append(piece)
            total += len(piece)
    except errors as err:
        raise McapFormatError("chunk", compression,
                              f"a valid {compression} stream ({err})") from err
    if total != size:
        raise McapFormatError("chunk.uncompressed_size", size,
                              f"the size of the decompressed records ({total}"
                              f"{' or more' if total > size else ''})")
    return parts[0] if len(parts) == 1 else b"".join(parts)
