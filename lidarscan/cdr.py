"""CDR (XCDR1, as used by ROS 2 / Fast DDS) encode and zero-copy decode, driven by ``.msg`` files.

Rules implemented (alignment counts from the end of the 4-byte encapsulation header):

* a primitive of size n is aligned to n (int64/float64/uint64 to 8); bool is one byte;
* a string is a uint32 length that counts the terminating NUL, the UTF-8 bytes and the NUL;
* a sequence is a uint32 element count followed by its elements (the first element aligned to its
  own size; an empty sequence adds no padding); a fixed array has no count;
* nested messages add no alignment of their own; a message without fields (``std_msgs/Empty``)
  is one uint8 (rosidl's ``structure_needs_at_least_one_member``, always 0).

:func:`encode` writes every padding byte as zero; rclpy's ``serialize_message`` leaves them
uninitialised (and may append a few trailing bytes), so the two agree except on padding.
:func:`decode` returns dataclasses from :mod:`lidarscan.types`; numeric arrays are read-only numpy
arrays that *view* the payload (no copy) when it is little-endian, and copies when big-endian.
Every read is bounds-checked: truncated or inflated payloads raise :class:`DecodeError` and a
declared length larger than the payload is never allocated.
"""

from __future__ import annotations

import array
import struct
from collections.abc import Callable
from functools import lru_cache
from typing import Any

import numpy as np

from lidarscan.errors import DecodeError, EncodeError, LidarScanError, SchemaError
from lidarscan.msgdef import FieldDef, get_msgdef, normalize_type, on_definitions_changed
from lidarscan.types import message_class, msgtype_of

__all__ = ["encode", "decode", "decode_scan", "decode_info", "CDR_LE_HEADER"]

CDR_LE_HEADER = b"\x00\x01\x00\x00"
CDR_BE_HEADER = b"\x00\x00\x00\x00"

_SIZES = {"?": 1, "b": 1, "B": 1, "h": 2, "H": 2, "i": 4, "I": 4, "q": 8, "Q": 8, "f": 4, "d": 8}
_PRIM = {"bool": "?", "byte": "B", "char": "B", "int8": "b", "uint8": "B", "int16": "h",
         "uint16": "H", "int32": "i", "uint32": "I", "int64": "q", "uint64": "Q",
         "float32": "f", "float64": "d"}
_NP = {code: np.dtype(code) for code in _SIZES}
_NP["?"] = np.dtype(np.uint8)  # decoded as uint8 then compared != 0
_U32 = {"<": struct.Struct("<I"), ">": struct.Struct(">I")}

Reader = Callable[[memoryview, int, str], tuple[Any, int]]
Writer = Callable[[Any, list[bytes], int], int]


# ----------------------------------------------------------------------------------- decoding

def _need(buf: memoryview, pos: int, size: int, what: str) -> None:
    if pos + size > len(buf):
        raise DecodeError(what, len(buf) + 4,
                          f"at least {pos + size + 4} bytes of CDR (field needs {size} bytes "
                          f"at payload offset {pos})", hint="truncated or corrupt message")


def _read_count(buf: memoryview, pos: int, bo: str, what: str,
                bound: int | None = None) -> tuple[int, int]:
    """A uint32 length (aligned to 4) and the position after it; at most ``bound``."""
    pos += -pos % 4
    _need(buf, pos, 4, what)
    n = _U32[bo].unpack_from(buf, pos)[0]
    if bound is not None and n > bound:
        raise DecodeError(what, n, f"at most {bound} elements (bounded sequence)")
    return n, pos + 4


def _scalar_reader(code: str, what: str) -> Reader:
    size = _SIZES[code]
    structs = {bo: struct.Struct(bo + code) for bo in "<>"}

    def read(buf: memoryview, pos: int, bo: str) -> tuple[Any, int]:
        pos += -pos % size
        if pos + size > len(buf):
            _need(buf, pos, size, what)
        value = structs[bo].unpack_from(buf, pos)[0]
        return (value != 0 if code == "?" else value), pos + size

    return read


def _string_reader(what: str) -> Reader:
    def read(buf: memoryview, pos: int, bo: str) -> tuple[Any, int]:
        length, pos = _read_count(buf, pos, bo, what)
        if length == 0:  # tolerated (some writers), means ""
            return "", pos
        _need(buf, pos, length, what)
        raw = bytes(buf[pos:pos + length - 1])
        try:
            return raw.decode("utf-8"), pos + length
        except UnicodeDecodeError as err:
            raise DecodeError(what, raw[:40], "UTF-8 text") from err

    return read


def _array_reader(code: str, count: int | None, bound: int | None, what: str) -> Reader:
    """Primitive array: fixed ``count`` or a sequence (count read from the payload)."""
    size = _SIZES[code]
    dtypes = {"<": _NP[code].newbyteorder("<"), ">": _NP[code].newbyteorder(">")}

    def read(buf: memoryview, pos: int, bo: str) -> tuple[Any, int]:
        n = count
        if n is None:
            n, pos = _read_count(buf, pos, bo, what, bound)
        if n:
            pos += -pos % size
        _need(buf, pos, n * size, what)
        arr = np.frombuffer(buf, dtypes[bo], n, pos)
        if bo == ">" and size > 1:
            arr = arr.astype(dtypes["<"])
        if code == "?":
            arr = arr != 0
        arr.flags.writeable = False
        return arr, pos + n * size

    return read


def _list_reader(elem: Reader, count: int | None, bound: int | None, what: str) -> Reader:
    def read(buf: memoryview, pos: int, bo: str) -> tuple[Any, int]:
        n = count
        if n is None:
            n, pos = _read_count(buf, pos, bo, what, bound)
            if n > len(buf) - pos:  # every element takes at least one byte
                raise DecodeError(what, n, f"at most {len(buf) - pos} elements "
                                  "(the rest of the payload)", hint="corrupt length")
        items = []
        for _ in range(n):
            item, pos = elem(buf, pos, bo)
            items.append(item)
        return tuple(items), pos

    return read


def _field_codec(field: FieldDef, what: str, scalar: Any, string: Any, struct_: Any,
                 array: Any, sequence: Any) -> Any:
    """Build the reader or writer of one field from the five constructors of one direction."""
    if field.type == "wstring":
        raise SchemaError(what, "wstring",
                          "string fields (wstring, UTF-16 in CDR, is not supported)")
    code = _PRIM.get(field.type)
    fixed = field.array if field.array is not None and field.array > 0 else None
    bound = -field.array - 2 if field.array is not None and field.array < -1 else None
    if code is not None:
        return scalar(code, what) if field.array is None else array(code, fixed, bound, what)
    element = string(what) if field.type == "string" else struct_(field.type)
    return element if field.array is None else sequence(element, fixed, bound, what)


def _field_reader(field: FieldDef, what: str) -> Reader:
    reader: Reader = _field_codec(field, what, _scalar_reader, _string_reader, _struct_reader,
                                  _array_reader, _list_reader)
    return reader


def _run_reader(codes: list[str], what: str) -> Reader:
    """Consecutive scalar fields read with one ``struct`` call.

    Their padding depends only on the start position modulo 8, so one layout per phase is
    built on first use and cached.
    """
    layouts: dict[tuple[str, int], tuple[struct.Struct, int]] = {}
    bools = [i for i, code in enumerate(codes) if code == "?"]

    def layout(bo: str, phase: int) -> tuple[struct.Struct, int]:
        fmt, pos = bo, phase
        for code in codes:
            pad = -pos % _SIZES[code]
            fmt += "x" * pad + code
            pos += pad + _SIZES[code]
        packer = struct.Struct(fmt)
        layouts[(bo, phase)] = (packer, packer.size)
        return packer, packer.size

    def read(buf: memoryview, pos: int, bo: str) -> tuple[Any, int]:
        packer, size = layouts.get((bo, pos & 7)) or layout(bo, pos & 7)
        if pos + size > len(buf):
            _need(buf, pos, size, what)
        values = packer.unpack_from(buf, pos)
        if bools:
            values = tuple(v != 0 if i in bools else v for i, v in enumerate(values))
        return values, pos + size

    return read


@lru_cache(maxsize=None)
def _struct_reader(msgtype: str) -> Reader:
    msgdef = get_msgdef(msgtype)
    cls = message_class(msgtype)
    short = msgtype.split("/")[-1]
    # Segments: (True, run reader) yields several values, (False, reader) yields one.
    segments: list[tuple[bool, Reader]] = []
    run: list[str] = []
    for field in msgdef.fields:
        code = _PRIM.get(field.type)
        if field.array is None and code is not None:
            run.append(code)
            continue
        if run:
            segments.append((True, _run_reader(run, f"{short}.{field.name}")))
            run = []
        segments.append((False, _field_reader(field, f"{short}.{field.name}")))
    if run:
        segments.append((True, _run_reader(run, f"{short} (last fields)")))

    if not msgdef.fields:  # rosidl gives an empty struct one uint8 member (always 0)
        def read_empty(buf: memoryview, pos: int, bo: str) -> tuple[Any, int]:
            _need(buf, pos, 1, short)
            return cls(), pos + 1

        return read_empty

    def read(buf: memoryview, pos: int, bo: str) -> tuple[Any, int]:
        values: list[Any] = []
        for many, reader in segments:
            value, pos = reader(buf, pos, bo)
            if many:
                values.extend(value)
            else:
                values.append(value)
        return cls(*values), pos

    return read


def decode(payload: bytes | bytearray | memoryview, msgtype: str, *, strict: bool = False) -> Any:
    """Decode one CDR payload (with its 4-byte encapsulation header) into a dataclass.

    Args:
        payload: the serialized message, e.g. from an MCAP record or ``raw=True`` subscription.
            It is viewed, not copied: numeric arrays in the result alias it (read-only).
        msgtype: ``pkg/msg/Name`` (or ``pkg/Name``).
        strict: also reject trailing bytes beyond the padding a serializer may append.

    Raises:
        DecodeError: bad encapsulation header, truncated payload, impossible lengths, bad UTF-8.
    """
    try:
        view = memoryview(payload)
        if view.format != "B" or view.ndim != 1:
            view = view.cast("B")
    except TypeError as err:
        raise DecodeError("payload", type(payload).__name__,
                          "a contiguous bytes-like object (bytes, bytearray, memoryview)") from err
    if len(view) < 4:
        raise DecodeError("payload", bytes(view[:4]), "a 4-byte CDR encapsulation header",
                          hint="message is shorter than 4 bytes")
    kind = bytes(view[:4])
    if kind[:2] == b"\x00\x01":
        bo = "<"
    elif kind[:2] == b"\x00\x00":
        bo = ">"
    else:
        raise DecodeError("encapsulation", kind.hex(), "00 01 (CDR little-endian) or 00 00 (CDR "
                          "big-endian)")
    reader = _struct_reader(normalize_type(msgtype))
    try:
        msg, end = reader(view[4:], 0, bo)
    except LidarScanError:
        raise
    except (struct.error, ValueError, OverflowError) as err:  # defensive: should not happen
        raise DecodeError(msgtype, len(view), "a well-formed CDR payload") from err
    if strict and len(view) - 4 - end > 3:
        slack = 3 + 8 * _empty_wide_sequences(msg, normalize_type(msgtype))
        if len(view) - 4 - end > slack:
            raise DecodeError("payload length", len(view),
                              f"{end + 4} bytes (+ at most {slack} trailing bytes)")
    return msg


def _empty_wide_sequences(msg: Any, msgtype: str) -> int:
    """Number of empty 8-byte-element sequences in ``msg``.

    rclpy (Fast DDS type support) sizes its output buffer with an estimate that aligns every
    sequence's elements, even of an empty one, and rounds the total up to 4, so it may append up
    to a few bytes per empty int64/uint64/float64 sequence; ``strict`` tolerates exactly that.
    """
    total = 0
    for field in get_msgdef(msgtype).fields:
        code = _PRIM.get(field.type)
        value = getattr(msg, field.name)
        if code is not None:
            if field.array is not None and field.array < 0 and _SIZES[code] == 8 \
                    and len(value) == 0:
                total += 1
        elif field.type not in ("string", "wstring"):
            for item in ((value,) if field.array is None else value):
                total += _empty_wide_sequences(item, field.type)
    return total


def decode_scan(payload: bytes | bytearray | memoryview) -> Any:
    """Decode a ``lidarscan_msgs/LidarScan`` payload into the frozen dataclass
    :class:`lidarscan.types.LidarScan` (not the rclpy message :func:`lidarscan.make_scan` makes
    by default); ``data`` views the payload (zero-copy)."""
    return decode(payload, "lidarscan_msgs/msg/LidarScan")


def decode_info(payload: bytes | bytearray | memoryview) -> Any:
    """Decode a ``lidarscan_msgs/LidarInfo`` payload into :class:`lidarscan.types.LidarInfo`."""
    return decode(payload, "lidarscan_msgs/msg/LidarInfo")


# ----------------------------------------------------------------------------------- encoding

def _pad(out: list[bytes], pos: int, size: int) -> int:
    pad = -pos % size
    if pad:
        out.append(b"\x00" * pad)
    return pos + pad


def _scalar_writer(code: str, what: str) -> Writer:
    packer = struct.Struct("<" + code)
    size = _SIZES[code]

    def write(value: Any, out: list[bytes], pos: int) -> int:
        pos = _pad(out, pos, size)
        if code == "B" and isinstance(value, (bytes, bytearray)) and len(value) == 1:
            value = value[0]  # rclpy represents a ``byte`` field as a 1-byte bytes object
        try:
            out.append(packer.pack(bool(value) if code == "?" else value))
        except (struct.error, TypeError, OverflowError) as err:  # float32 overflow: OverflowError
            raise EncodeError(what, value, f"a value of CDR type '{code}'") from err
        return pos + size

    return write


def _string_writer(what: str) -> Writer:
    def write(value: Any, out: list[bytes], pos: int) -> int:
        if not isinstance(value, str):
            raise EncodeError(what, value, "a str")
        try:
            raw = value.encode("utf-8") + b"\x00"
        except UnicodeEncodeError as err:
            raise EncodeError(what, value, "text encodable as UTF-8 (no lone surrogates)") from err
        pos = _pad(out, pos, 4)
        out.append(struct.pack("<I", len(raw)))
        out.append(raw)
        return pos + 4 + len(raw)

    return write


_ARRAY_TYPECODES = {"b": "b", "B": "B", "h": "h", "H": "H", "i": "i", "I": "I", "q": "q",
                    "Q": "Q", "f": "f", "d": "d"}


def _as_le_bytes(value: Any, code: str, what: str) -> tuple[bytes | bytearray | memoryview, int]:
    """Raw little-endian bytes and element count of a primitive array (no copy if possible)."""
    if code == "B" and isinstance(value, (bytes, bytearray)):
        return value, len(value)
    if isinstance(value, array.array) and value.typecode == _ARRAY_TYPECODES.get(code) \
            and value.itemsize == _SIZES[code]:
        return memoryview(value).cast("B"), len(value)
    if isinstance(value, memoryview) and code == "B":
        view = value.cast("B") if value.format != "B" or value.ndim != 1 else value
        return view, len(view)
    target = np.dtype(np.uint8) if code == "?" else _NP[code].newbyteorder("<")
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError) as err:
        raise EncodeError(what, type(value).__name__, f"a sequence of '{code}' numbers") from err
    if code == "B" and arr.dtype == np.dtype("S1"):  # rclpy ``byte[]``: a list of 1-byte bytes
        arr = arr.view(np.uint8)
    if arr.dtype.kind not in "biuf":
        raise EncodeError(what, str(arr.dtype), f"a sequence of '{code}' numbers")
    if arr.dtype != target:
        if target.kind in "iu" and arr.dtype.kind == "f":
            raise EncodeError(what, str(arr.dtype), f"integers for an array of '{code}'")
        if target.kind in "iu" and arr.size and arr.dtype.kind in "iu":
            info = np.iinfo(target)
            low, high = int(arr.min()), int(arr.max())
            if low < info.min or high > info.max:
                raise EncodeError(what, low if low < info.min else high,
                                  f"values in [{info.min}, {info.max}] for '{code}'")
        if code == "?":
            arr = arr.astype(bool).astype(target)
        elif target.kind == "f" and arr.dtype.kind == "f" and target.itemsize < arr.dtype.itemsize:
            with np.errstate(over="ignore"):
                narrow = arr.astype(target)
            if np.isinf(narrow).sum() != np.isinf(arr).sum():
                bad = arr[np.isinf(narrow) & ~np.isinf(arr)].reshape(-1)[0]
                raise EncodeError(what, float(bad), f"values within the range of '{code}' "
                                  "(float32 overflows to inf)")
            arr = narrow
        else:
            arr = arr.astype(target)
    arr = np.ascontiguousarray(arr.reshape(-1))
    return arr.data.cast("B"), arr.size


def _array_writer(code: str, count: int | None, bound: int | None, what: str) -> Writer:
    size = _SIZES[code]

    def write(value: Any, out: list[bytes], pos: int) -> int:
        raw, n = _as_le_bytes(value, code, what)
        if count is not None and n != count:
            raise EncodeError(what, n, f"exactly {count} elements (fixed-size array)")
        if bound is not None and n > bound:
            raise EncodeError(what, n, f"at most {bound} elements (bounded sequence)")
        if count is None:
            pos = _pad(out, pos, 4)
            out.append(struct.pack("<I", n))
            pos += 4
        if n:
            pos = _pad(out, pos, size)
        out.append(raw)  # type: ignore[arg-type]
        return pos + n * size

    return write


def _list_writer(elem: Writer, count: int | None, bound: int | None, what: str) -> Writer:
    def write(value: Any, out: list[bytes], pos: int) -> int:
        items = list(value)
        if count is not None and len(items) != count:
            raise EncodeError(what, len(items), f"exactly {count} elements (fixed-size array)")
        if bound is not None and len(items) > bound:
            raise EncodeError(what, len(items), f"at most {bound} elements (bounded sequence)")
        if count is None:
            pos = _pad(out, pos, 4)
            out.append(struct.pack("<I", len(items)))
            pos += 4
        for item in items:
            pos = elem(item, out, pos)
        return pos

    return write


def _field_writer(field: FieldDef, what: str) -> Writer:
    writer: Writer = _field_codec(field, what, _scalar_writer, _string_writer, _struct_writer,
                                  _array_writer, _list_writer)
    return writer


@lru_cache(maxsize=None)
def _struct_writer(msgtype: str) -> Writer:
    msgdef = get_msgdef(msgtype)
    short = msgtype.split("/")[-1]
    writers = [(f.name, _field_writer(f, f"{short}.{f.name}")) for f in msgdef.fields]

    if not writers:  # rosidl gives an empty struct one uint8 member (always 0)
        def write_empty(value: Any, out: list[bytes], pos: int) -> int:
            out.append(b"\x00")
            return pos + 1

        return write_empty

    def write(value: Any, out: list[bytes], pos: int) -> int:
        for name, writer in writers:
            try:
                field_value = getattr(value, name)
            except AttributeError:
                raise EncodeError(f"{short}.{name}", type(value).__name__,
                                  f"a {msgtype} message with field '{name}'") from None
            pos = writer(field_value, out, pos)
        return pos

    return write


def _clear_codecs() -> None:
    _struct_reader.cache_clear()
    _struct_writer.cache_clear()


on_definitions_changed(_clear_codecs)


def encode(msg: Any, msgtype: str | None = None) -> bytes:
    """Serialize a message to CDR little-endian bytes (encapsulation header included).

    Args:
        msg: an rclpy message instance or a :mod:`lidarscan.types` dataclass (any object with the
            message's attributes works when ``msgtype`` is given).
        msgtype: ``pkg/msg/Name``; taken from ``msg`` when omitted.

    Returns:
        bytes equal to ``rclpy.serialization.serialize_message(msg)`` except for alignment
        padding, which is always zero here.

    Raises:
        EncodeError: a value does not fit its field (range, length of a fixed array, type).
    """
    return b"".join(encode_pieces(msg, msgtype))


def encode_pieces(msg: Any, msgtype: str | None = None) -> list[Any]:
    """:func:`encode` as the list of pieces its bytes join from (bytes, and buffers that *view*
    the message's arrays: no copy of them), for writers that keep the pieces until they write
    them (the message must then not change). Raises as :func:`encode`."""
    full = normalize_type(msgtype) if msgtype else msgtype_of(msg)
    out: list[Any] = [CDR_LE_HEADER]
    _struct_writer(full)(msg, out, 0)
    return out
