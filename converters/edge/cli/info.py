"""``lidarscan info``: topics, types, counts, LidarInfo versions, linkage and problems of a
recording (exit 1 when it has problems)."""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field
from typing import Any

from converters.edge.cli._common import EXIT_BAD, EXIT_OK, _fmt_stamp, _open_input, decode_item


@dataclass
class _TopicStats:
    msgtype: str
    count: int = 0
    first_ns: int | None = None
    last_ns: int | None = None
    types: set[str] = field(default_factory=set)
    layout: tuple[str, str, int] | None = None  # (frame_id, shape, message index) of the first
    changes: list[str] = field(default_factory=list)


def _layout(msgtype: str, msg: Any) -> tuple[str, str] | None:
    """(frame_id, shape) of the messages whose layout must stay constant on a topic."""
    import numpy as np

    if msgtype == "lidarscan_msgs/msg/LidarScan":
        names = ",".join(c.name for c in msg.channels)
        return msg.header.frame_id, f"{msg.height}x{msg.width} [{names}]"
    if msgtype == "sensor_msgs/msg/LaserScan":
        return msg.header.frame_id, f"{len(np.asarray(msg.ranges))} rays"
    if msgtype == "sensor_msgs/msg/PointCloud2":
        names = ",".join(f.name for f in msg.fields)
        return msg.header.frame_id, f"{msg.height}x{msg.width} [{names}]"
    if msgtype == "lidarscan_msgs/msg/LidarInfo":
        return msg.header.frame_id, ""  # a new version may change the grid, not the frame
    return None


def _check_layout(stats: _TopicStats, topic: str, index: int, layout: tuple[str, str]) -> None:
    """Note (once per kind) a frame or shape that differs from the topic's first message."""
    if stats.layout is None:
        stats.layout = (layout[0], layout[1], index)
        return
    frame, shape, first = stats.layout
    for what, old, now in (("frame_id", frame, layout[0]), ("shape", shape, layout[1])):
        if old != now and not any(c.startswith(what) for c in stats.changes):
            stats.changes.append(f"{what} changes mid-recording: '{old}' (message #{first}) "
                                 f"then '{now}' (message #{index}): one topic must carry one "
                                 f"{'frame' if what == 'frame_id' else 'layout'}")


def cmd_info(args: argparse.Namespace) -> int:
    import lidarscan
    from converters.sources.bags import PACKET_TYPES
    from lidarscan.geometry import info_key
    from lidarscan.mcap import INFO_TYPE, SCAN_TYPE, BadMessage, read_scans

    source = _open_input(args.file, "FILE")
    path = source.path
    topics: dict[str, _TopicStats] = {}
    bad: list[BadMessage] = []
    versions: dict[tuple[str, int], dict[str, Any]] = {}
    packets: dict[str, int] = {}
    encodings: dict[str, str] = {}  # topic -> a message encoding other than CDR
    total = 0
    for item in source.items():
        if isinstance(item, BadMessage):
            bad.append(item)
            continue
        total += 1
        if getattr(item, "encoding", "cdr") != "cdr":
            encodings[item.topic] = item.encoding
        stats = topics.setdefault(item.topic, _TopicStats(item.msgtype))
        stats.count += 1
        stats.types.add(item.msgtype)
        stats.first_ns = item.log_time_ns if stats.first_ns is None else stats.first_ns
        stats.last_ns = item.log_time_ns
        try:
            layout = None
            if item.msgtype in PACKET_TYPES:
                scan = PACKET_TYPES[item.msgtype][1](item.payload)
                packets[item.topic] = packets.get(item.topic, 0) + len(scan.stamps)
                layout = (scan.frame_id, "")
            elif item.msgtype in (INFO_TYPE, SCAN_TYPE, "sensor_msgs/msg/LaserScan",
                                  "sensor_msgs/msg/PointCloud2"):
                msg = decode_item(item)
                layout = _layout(item.msgtype, msg)
                if item.msgtype == INFO_TYPE:
                    lidarscan.validate_info(msg)
                    stamp, digest = info_key(msg)
                    entry = versions.setdefault((item.topic, stamp), {
                        "info": msg, "digests": set(), "count": 0})
                    entry["digests"].add(digest)
                    entry["count"] += 1
            if layout is not None:
                _check_layout(stats, item.topic, item.index, layout)
        except lidarscan.errors.LidarScanError as err:
            bad.append(BadMessage(item.index, item.topic, item.log_time_ns, str(err), err))
    print(f"{path} ({source.kind.description}): {total} messages on {len(topics)} topics")
    for note in getattr(source.bag, "notes", []):
        print(f"  note: {note}")
    width = max([len(t) for t in topics] + [5])
    print(f"  {'topic':<{width}}  {'type':<32} {'count':>7}  first .. last log time (s)")
    for topic, stats in sorted(topics.items()):
        span = (f"{_fmt_stamp(stats.first_ns or 0)} .. {_fmt_stamp(stats.last_ns or 0)}"
                if stats.count else "")
        extra = f"  ({packets[topic]} packets)" if topic in packets else ""
        extra += f"  (compressed: {encodings[topic]})" if topic in encodings else ""
        print(f"  {topic:<{width}}  {stats.msgtype:<32} {stats.count:>7}  {span}{extra}")
    problems = len(bad)
    topic_problems = []
    for topic, stats in sorted(topics.items()):
        if len(stats.types) > 1:
            topic_problems.append(f"topic '{topic}' carries several types: "
                                  f"{', '.join(sorted(stats.types))}")
        topic_problems += [f"topic '{topic}': {change}" for change in stats.changes]
    problems += len(topic_problems)
    if versions:
        print("LidarInfo versions:")
        for (topic, stamp), entry in sorted(versions.items()):
            info = entry["info"]
            conflict = len(entry["digests"]) > 1
            problems += int(conflict)
            print(f"  {topic} stamp {_fmt_stamp(stamp)}: {info.height}x{info.width} "
                  f"{info.vendor} {info.model} frame '{info.header.frame_id}', "
                  f"published {entry['count']}x"
                  + ("  CONFLICT: same stamp, different geometry" if conflict else ""))
    linkage: list[BadMessage] = []
    scans = sum(s.count for s in topics.values() if s.msgtype == SCAN_TYPE)
    if scans:
        paired = sum(1 for _ in read_scans(None, on_error=linkage.append,
                                           items=source.items()))
        print(f"LidarScans linked to their LidarInfo: {paired} of {scans}")
    # read_scans also reports undecodable records that were reported above: keep them once
    seen = {(b.index, b.reason) for b in bad}
    extra = [b for b in linkage if (b.index, b.reason) not in seen]
    problems += len(extra)
    for line in topic_problems:
        print(f"  problem: {line}")
    for item in bad + extra:
        if item.index < 0:
            print(f"  problem: {item.reason}")
        else:
            print(f"  problem: message #{item.index} topic '{item.topic}' "
                  f"log time {_fmt_stamp(item.log_time_ns)}: {item.reason}")
    print("no problems found" if not problems else f"{problems} problem(s) found")
    return EXIT_OK if not problems else EXIT_BAD
