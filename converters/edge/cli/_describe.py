"""Shared descriptions of ``lidarscan info``: sizes, time spans, the sensor model of raw
packets, and the summary of an Ouster .pcap/.osf (read as ``convert`` reads it)."""

from __future__ import annotations

import datetime
from pathlib import Path
from typing import Any


def human_size(size: int) -> str:
    """``1234567`` -> ``'1.2 MB'`` (decimal units, as ``ros2 bag info`` and ``ls -h --si``)."""
    value = float(size)
    for unit in ("B", "kB", "MB", "GB", "TB"):
        if value < 1000 or unit == "TB":
            return f"{value:.0f} {unit}" if unit == "B" else f"{value:.1f} {unit}"
        value /= 1000
    return f"{size} B"  # pragma: no cover


def utc(ns: int) -> str:
    """int ns since the epoch -> ``'2024-04-19 02:11:17.464078412 UTC'``."""
    seconds, rest = divmod(int(ns), 1_000_000_000)
    when = datetime.datetime.fromtimestamp(seconds, tz=datetime.timezone.utc)
    return f"{when:%Y-%m-%d %H:%M:%S}.{rest:09d} UTC"


def span_line(first_ns: int | None, last_ns: int | None, size: int) -> str:
    """``'size 1.2 MB; 2024-.. UTC .. 2024-.. UTC (duration 0.377 s)'``."""
    text = f"size {human_size(size)}"
    if first_ns is None or last_ns is None:
        return text + "; no messages"
    return (f"{text}; {utc(first_ns)} .. {utc(last_ns)} "
            f"(duration {(last_ns - first_ns) / 1e9:.3f} s)")


def recording_size(source: Any) -> int:
    """Bytes of a recording (every storage file of a bag)."""
    files = source.bag.files if source.bag is not None else [source.path]
    return sum(Path(f).stat().st_size for f in files)


def packet_model(msgtype: str, packets: Any) -> str:
    """The sensor model (and return mode) one packet message's first packet names, e.g.
    ``'Velodyne VLP-32C, strongest'`` or ``'Hesai PandarXT32'``; ``''`` when unknown."""
    from converters.sources.bags import PANDAR_SCAN, VELODYNE_SCAN

    try:
        _, first = packets.packets[0]
    except (IndexError, TypeError, ValueError):
        return ""
    data = bytes(first)
    if msgtype == VELODYNE_SCAN:
        from converters.sources.velodyne import MODELS

        if len(data) < 1206 or data[1205] not in MODELS:
            return f"Velodyne, unknown product id {data[1205]:#04x}" if len(data) >= 1206 else ""
        mode = {0x37: "strongest", 0x38: "last", 0x39: "dual"}.get(data[1204], hex(data[1204]))
        return f"Velodyne {MODELS[data[1205]].name}, {mode}"
    if msgtype == PANDAR_SCAN:
        from converters.sources.hesai import detect_format
        from lidarscan.errors import LidarScanError

        try:
            return f"Hesai {detect_format(data).model}"
        except LidarScanError:
            return "Hesai, unknown model"
    return ""


def ouster_summary(path: Path, meta: str | None) -> tuple[list[str], int]:
    """(lines, problems) of ``lidarscan info`` for an Ouster .pcap/.osf: what ``convert``
    makes of it (the scans, their LidarInfo, time span, size)."""
    from converters.sources.ouster.metadata import scans_from_recording
    from lidarscan.stamps import to_ns

    count, first, last, info = 0, None, None, None
    for scan, info in scans_from_recording(path, meta=meta, as_dataclass=True):
        stamp = to_ns(scan.header.stamp)
        first = stamp if first is None else min(first, stamp)
        last = stamp if last is None else max(last, stamp)
        count += 1
    lines = [(f"{path} (an Ouster recording): {count} scans, read as `lidarscan convert` does "
              "(/lidar/info + /lidar/scan)"),
             f"  {span_line(first, last, path.stat().st_size)}"]
    if info is not None:
        lines.append(f"  sensor: {info.vendor} {info.model} {info.height}x{info.width} frame "
                     f"'{info.header.frame_id}'"
                     + (f", serial {info.serial_number}" if info.serial_number else ""))
    problems = int(count == 0)
    if problems:
        lines.append("  problem: no scan could be read")
    lines.append("no problems found" if not problems else f"{problems} problem(s) found")
    return lines, problems
