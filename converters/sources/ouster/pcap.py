"""UDP datagrams out of packet captures: classic pcap and pcapng, IPv4 fragments reassembled.

Reads what ``tcpdump`` / Wireshark / ouster-sdk write: classic pcap (magic a1b2c3d4 with
microsecond or a1b23c4d with nanosecond times, either byte order) and pcapng (section header,
interface description with ``if_tsresol``, enhanced and simple packet blocks, every section's
byte order). Link layers: Ethernet (with 802.1Q/802.1ad VLAN tags), BSD loopback (null/loop),
raw IP, Linux cooked capture v1/v2. IPv4 datagrams split into fragments are put back together
(by source, destination, protocol and identification; a datagram with a fragment missing is
dropped and counted); IPv6 UDP without extension headers is read too. Other frames (ARP, TCP,
...) are skipped.

Times are int64 ns since the epoch of the capture's clock. Nothing here is Ouster-specific
except :func:`lidar_packets`, which picks one sensor's lidar packets (its UDP port from the
metadata, else the port whose payloads have the lidar packet size).
"""

from __future__ import annotations

import os
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

from lidarscan.errors import DecodeError

__all__ = ["Datagram", "PcapStats", "lidar_packets", "read_pcap", "scans_from_pcap"]

_ETHERNET, _NULL, _RAW, _LOOP, _SLL, _SLL2 = 1, 0, 101, 108, 113, 276
_RAW_ALIASES = {12, 14}                       # raw IP on some BSDs
_PCAPNG_SHB = 0x0A0D0D0A


@dataclass(frozen=True)
class Datagram:
    """One UDP datagram: capture time (int64 ns), addresses (bytes), ports, payload (a
    read-only memoryview of the capture's bytes, or bytes for a reassembled datagram)."""

    stamp_ns: int
    src: bytes
    dst: bytes
    src_port: int
    dst_port: int
    payload: Any


@dataclass
class PcapStats:
    """Counters of one read: frames read, UDP datagrams, datagrams reassembled from fragments,
    datagrams dropped with fragments missing, frames skipped (not UDP over IP)."""

    frames: int = 0
    datagrams: int = 0
    reassembled: int = 0
    incomplete: int = 0
    skipped: int = 0
    ports: dict[int, dict[int, int]] = field(default_factory=dict)   # port -> size -> count


def read_pcap(path: str | os.PathLike[str], stats: PcapStats | None = None
              ) -> Iterator[Datagram]:
    """The UDP datagrams of a pcap or pcapng file, in capture order.

    Args:
        path: the capture file.
        stats: filled while reading (optional).

    Raises:
        DecodeError: not a pcap/pcapng file, an unsupported link type, a truncated header.
    """
    stats = stats if stats is not None else PcapStats()
    with open(os.fspath(path), "rb") as fh:
        magic = fh.read(4)
        if len(magic) < 4:
            raise DecodeError(f"pcap {path}", len(magic), "a pcap or pcapng file (too short)")
        frames = _pcapng(fh, magic, path) if struct.unpack("<I", magic)[0] == _PCAPNG_SHB \
            else _classic(fh, magic, path)
        assembler = _Fragments(stats)
        for stamp, link, frame in frames:
            stats.frames += 1
            datagram = _udp(stamp, link, frame, assembler)
            if datagram is None:
                continue
            stats.datagrams += 1
            sizes = stats.ports.setdefault(datagram.dst_port, {})
            sizes[len(datagram.payload)] = sizes.get(len(datagram.payload), 0) + 1
            yield datagram
        stats.incomplete += len(assembler.pending)


class _Blocks:
    """Reads a file in 4 MiB blocks and hands out views of them (no copy per record)."""

    def __init__(self, fh: BinaryIO) -> None:
        self.fh = fh
        self.buf = memoryview(b"")
        self.pos = 0

    def read(self, n: int) -> memoryview:
        """The next ``n`` bytes (fewer at the end of the file)."""
        if self.pos + n > len(self.buf):
            rest = bytes(self.buf[self.pos:])
            self.buf = memoryview(rest + self.fh.read(max(n, 1 << 22)))
            self.pos = 0
        out = self.buf[self.pos:self.pos + n]
        self.pos += len(out)
        return out


def _classic(fh: BinaryIO, magic: bytes, path: Any) -> Iterator[tuple[int, int, Any]]:
    formats = {b"\xd4\xc3\xb2\xa1": ("<", 1000), b"\xa1\xb2\xc3\xd4": (">", 1000),
               b"\x4d\x3c\xb2\xa1": ("<", 1), b"\xa1\xb2\x3c\x4d": (">", 1)}
    if magic not in formats:
        raise DecodeError(f"pcap {path} magic", magic.hex(),
                          "a pcap (a1b2c3d4 / a1b23c4d, either byte order) or pcapng file")
    order, unit = formats[magic]
    head = fh.read(20)
    if len(head) < 20:
        raise DecodeError(f"pcap {path}", "truncated global header", "24 bytes")
    link = struct.unpack(order + "I", head[16:20])[0] & 0x0FFFFFFF
    record = struct.Struct(order + "IIII")
    blocks = _Blocks(fh)
    while True:
        rec = blocks.read(16)
        if len(rec) < 16:
            return
        sec, frac, caplen, _ = record.unpack(rec)
        data = blocks.read(caplen)
        if len(data) < caplen:
            return                                   # a capture cut short: keep what is whole
        yield sec * 1_000_000_000 + frac * unit, link, data


def _pcapng(fh: BinaryIO, magic: bytes, path: Any) -> Iterator[tuple[int, int, Any]]:
    order = "<"
    fh = _Blocks(fh)  # type: ignore[assignment]
    interfaces: list[tuple[int, int, int]] = []    # (link type, ticks numerator, per second)
    block = magic
    while True:
        if block is None:
            block = bytes(fh.read(4))
        if len(block) < 4:
            return
        rest = fh.read(4)
        if len(rest) < 4:
            return
        if struct.unpack("<I", block)[0] == _PCAPNG_SHB:
            bom = bytes(fh.read(4))
            order = "<" if bom == b"\x4d\x3c\x2b\x1a" else ">"
            if bom not in (b"\x4d\x3c\x2b\x1a", b"\x1a\x2b\x3c\x4d"):
                raise DecodeError(f"pcapng {path} byte-order magic", bom.hex(), "1a2b3c4d")
            length = struct.unpack(order + "I", rest)[0]
            body = bom + fh.read(length - 12)
            interfaces = []
        else:
            length = struct.unpack(order + "I", rest)[0]
            body = fh.read(length - 8) if length >= 12 else b""
        kind = struct.unpack(order + "I", block)[0]
        block = None
        if length < 12 or len(body) < length - 8:
            return
        body = body[:-4]                             # the trailing copy of the length
        if kind == 1:                                # interface description
            link = struct.unpack(order + "H", body[:2])[0]
            interfaces.append((link, *_tsresol(body[8:], order)))
        elif kind in (6, 2):                         # enhanced (and obsolete) packet block
            iface, high, low, caplen = struct.unpack(order + "IIII", body[:16])
            if kind == 2:
                iface &= 0xFFFF
            if iface >= len(interfaces):
                raise DecodeError(f"pcapng {path} interface id", iface,
                                  f"< {len(interfaces)} (the interfaces described before)")
            link, num, per = interfaces[iface]
            ticks = (high << 32) | low
            yield ticks * num * 1_000_000_000 // per, link, body[20:20 + caplen]
        elif kind == 3:                              # simple packet block: no time
            if interfaces:
                caplen = struct.unpack(order + "I", body[:4])[0]
                yield 0, interfaces[0][0], body[4:4 + caplen]


def _tsresol(options: bytes, order: str) -> tuple[int, int]:
    """(numerator, ticks per second) of an interface's ``if_tsresol`` (default microseconds)."""
    at = 0
    while at + 4 <= len(options):
        code, size = struct.unpack(order + "HH", options[at:at + 4])
        if code == 0:
            break
        if code == 9 and size >= 1:
            value = options[at + 4]
            return (1, 10 ** (value & 0x7F)) if not value & 0x80 else (1, 2 ** (value & 0x7F))
        at += 4 + size + (-size % 4)
    return 1, 1_000_000


class _Fragments:
    """IPv4 fragments waiting for the rest of their datagram."""

    def __init__(self, stats: PcapStats) -> None:
        self.pending: dict[tuple[bytes, bytes, int, int], dict[int, tuple[Any, bool]]] = {}
        self.stats = stats

    def add(self, key: tuple[bytes, bytes, int, int], offset: int, more: bool, data: Any
            ) -> bytes | None:
        parts = self.pending.setdefault(key, {})
        parts[offset] = (bytes(data), more)     # a copy: a view would pin its 4 MiB block
        if len(self.pending) > 256:                   # old datagrams that never completed
            oldest = next(iter(self.pending))
            del self.pending[oldest]
            self.stats.incomplete += 1
        if all(more for _, more in parts.values()):
            return None                               # the last fragment is still to come
        out, at = [], 0
        for start in sorted(parts):
            if start != at:                           # a hole (or an overlap): wait
                return None
            chunk, _ = parts[start]
            out.append(chunk)
            at += len(chunk)
        if parts[max(parts)][1]:
            return None
        del self.pending[key]
        self.stats.reassembled += 1
        return b"".join(out)


def _udp(stamp: int, link: int, frame: Any, frags: _Fragments) -> Datagram | None:
    """The UDP datagram of one link-layer frame (None: not UDP, or a fragment kept)."""
    frame = memoryview(frame)                         # slices below are views, not copies
    at, ethertype = 0, None
    if link == _ETHERNET:
        at, ethertype = 14, frame[12:14]
        while ethertype in (b"\x81\x00", b"\x88\xa8") and len(frame) >= at + 4:
            ethertype, at = frame[at + 2:at + 4], at + 4
    elif link in (_NULL, _LOOP):
        at = 4
    elif link == _SLL:
        at, ethertype = 16, frame[14:16]
    elif link == _SLL2:
        at, ethertype = 20, frame[0:2]
    elif link not in (_RAW, *_RAW_ALIASES):
        raise DecodeError("pcap link type", link, "Ethernet (1), null/loop (0, 108), raw IP "
                          "(101) or Linux cooked capture (113, 276)")
    if ethertype is not None and ethertype not in (b"\x08\x00", b"\x86\xdd"):
        frags.stats.skipped += 1
        return None
    ip = frame[at:]
    if len(ip) < 20:
        frags.stats.skipped += 1
        return None
    version = ip[0] >> 4
    if version == 6:
        if len(ip) < 48 or ip[6] != 17:
            frags.stats.skipped += 1
            return None
        return _datagram(stamp, ip[8:24], ip[24:40], ip[40:40 + struct.unpack(
            ">H", ip[4:6])[0]])
    if version != 4 or ip[9] != 17:
        frags.stats.skipped += 1
        return None
    ihl = (ip[0] & 0x0F) * 4
    total = struct.unpack(">H", ip[2:4])[0]
    body = ip[ihl:total]
    src, dst = ip[12:16], ip[16:20]
    flags = struct.unpack(">H", ip[6:8])[0]
    more, offset = bool(flags & 0x2000), (flags & 0x1FFF) * 8
    if more or offset:
        key = (bytes(src), bytes(dst), ip[9], struct.unpack(">H", ip[4:6])[0])
        whole = frags.add(key, offset, more, body)
        if whole is None:
            return None
        body = whole
    return _datagram(stamp, src, dst, body)


def _datagram(stamp: int, src: Any, dst: Any, udp: Any) -> Datagram | None:
    if len(udp) < 8:
        return None
    sport, dport, length = struct.unpack(">HHH", udp[:6])
    end = length if 8 <= length <= len(udp) else len(udp)
    return Datagram(stamp, bytes(src), bytes(dst), sport, dport, udp[8:end])


def lidar_packets(path: str | os.PathLike[str], metadata: Any, *, port: int | None = None,
                  stats: PcapStats | None = None) -> Iterator[tuple[int, Any]]:
    """(capture time ns, UDP payload: bytes-like) of one Ouster sensor's lidar packets in a
    capture.

    Args:
        path: the pcap/pcapng file.
        metadata: the sensor's metadata (path, JSON text, dict) or a
            :class:`~converters.sources.ouster.packet_format.PacketLayout`.
        port: the lidar UDP port; default the metadata's ``udp_port_lidar``; when the
            metadata gives none, or no datagram of the capture went to it, every datagram of
            the lidar packet size (IMU packets, 48 bytes, never match).

    Datagrams to that port of another size are skipped (counted in ``stats``).
    """
    from converters.sources.ouster.packet_format import PacketLayout, layout_from_metadata

    layout = metadata if isinstance(metadata, PacketLayout) else layout_from_metadata(metadata)
    want = port if port is not None else (layout.udp_port or None)
    size = layout.packet_bytes
    found = False
    for datagram in read_pcap(Path(os.fspath(path)), stats):
        if len(datagram.payload) == size and (want is None or datagram.dst_port == want):
            found = True
            yield datagram.stamp_ns, datagram.payload
    if not found and port is None and want is not None:
        # the metadata's port was not used in this capture: take the lidar packets by size
        for datagram in read_pcap(Path(os.fspath(path))):
            if len(datagram.payload) == size:
                yield datagram.stamp_ns, datagram.payload


def scans_from_pcap(path: str | os.PathLike[str], metadata: Any, *, port: int | None = None,
                    **kw: Any) -> Iterator[tuple[Any, Any]]:
    """(LidarScan, LidarInfo) per frame of one Ouster sensor's capture: :func:`lidar_packets`
    through :class:`converters.sources.ouster.decoder.PacketDecoder` (options ``kw``)."""
    from converters.sources.ouster.decoder import decode_packets

    yield from decode_packets(lidar_packets(path, metadata, port=port), metadata, **kw)
