"""``lidarscan view``: PNG views of a recording (range images, LaserScans, clouds)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from converters.edge.cli._common import EXIT_BAD, EXIT_OK, _describe_bad, _err, _open_input


def cmd_view(args: argparse.Namespace) -> int:
    import numpy as np

    from converters.edge.demo import viz
    from converters.sources.bags import PACKET_TYPES
    from converters.edge.nodes.tf import TransformBuffer, TransformLookupError
    from lidarscan.errors import LidarScanError
    from lidarscan.mcap import BadMessage, read_scans
    from lidarscan.stamps import to_ns

    source = _open_input(args.file, "FILE")
    path, out = source.path, Path(args.out)
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"--out {out}: exists and is not a directory")
    written: list[Path] = []
    damage: dict[str, BadMessage] = {}  # damaged parts of the input, once each

    def note_damage(item: BadMessage) -> None:
        if item.index < 0:
            damage.setdefault(item.reason, item)
    # 1. range images: the index-th linked scan of each LidarScan topic
    seen: dict[str, int] = {}
    chosen_stamp: int | None = None
    for scan, info in read_scans(None, on_error=note_damage, items=source.items()):
        topic = scan.header.frame_id
        k = seen.get(topic, 0)
        seen[topic] = k + 1
        if k == args.index:
            name = f"range_image_{_safe(topic)}.png"
            written.append(viz.range_image(scan, info, out / name,
                                           title=f"LidarScan (frame '{topic}') #{k}"))
            chosen_stamp = chosen_stamp or to_ns(scan.header.stamp)
    # 2. LaserScans and clouds near that time, TF from the file
    tf = TransformBuffer(cache_ns=3600 * 10**9, max_per_edge=100_000)
    lasers: dict[str, Any] = {}
    clouds: dict[str, Any] = {}
    counts: dict[str, int] = {}
    packets: set[str] = set()  # raw packet topics (nothing to draw before `convert`)
    for item in source.items():
        if isinstance(item, BadMessage):
            note_damage(item)
            continue
        try:
            if item.msgtype in PACKET_TYPES:
                packets.add(item.topic)
            elif item.msgtype == "tf2_msgs/msg/TFMessage":
                tf.add_message(item.decode(), static=item.topic.endswith("_static"))
            elif item.msgtype in ("sensor_msgs/msg/LaserScan", "sensor_msgs/msg/PointCloud2"):
                k = counts.get(item.topic, 0)
                counts[item.topic] = k + 1
                target = lasers if item.msgtype.endswith("LaserScan") else clouds
                msg = item.decode()
                stamp = to_ns(msg.header.stamp)
                if chosen_stamp is None:
                    if k == args.index:
                        target[item.topic] = msg
                else:
                    best = target.get(item.topic)
                    if best is None or abs(stamp - chosen_stamp) < \
                            abs(to_ns(best.header.stamp) - chosen_stamp):
                        target[item.topic] = msg
        except LidarScanError:
            continue
    frame = args.frame
    if lasers:
        if not frame:
            frames = [m.header.frame_id for m in lasers.values()]
            frame = "base_link" if "base_link" in frames or "base_link" in tf.frames() \
                else frames[0]
        layers = []
        colors = ["tab:red", "tab:green", "tab:orange", "tab:blue", "tab:purple", "tab:brown",
                  "tab:pink", "tab:olive", "tab:cyan"]
        for (topic, msg), color in zip(sorted(lasers.items()), colors * 10):
            try:
                extr = tf.lookup(frame, msg.header.frame_id, to_ns(msg.header.stamp))
            except TransformLookupError:
                try:
                    extr = tf.lookup(frame, msg.header.frame_id)
                except TransformLookupError:
                    extr = np.eye(4)
                    _err(f"note: no transform {frame} <- {msg.header.frame_id}; "
                         f"{topic} drawn in its own frame")
            layers.append(viz.Layer(topic, viz.laserscan_xy(msg, extr), color))
        panels = [(f"{layer.label} (in '{frame}')", [layer]) for layer in layers]
        written.append(viz.birdseye(out / "laserscans.png", panels, columns=3))
    for topic, msg in sorted(clouds.items()):
        written.append(viz.cloud_topview(msg, out / f"cloud_{_safe(topic)}.png",
                                         title=f"{topic} ('{msg.header.frame_id}')"))
    for item in damage.values():
        _err(_describe_bad(item))
    if not written:
        _err(f"{path} ({source.kind.description}): nothing to draw (no LidarScan with its "
             f"LidarInfo, LaserScan or PointCloud2 at index {args.index}"
             + (", and the input is damaged" if damage else "") + ")"
             + (f"; raw packets on {', '.join(sorted(packets))}: `lidarscan convert` them to "
                "LidarScans first, then view the output" if packets else ""))
        return EXIT_BAD
    for p in written:
        print(p)
    if damage:
        _err(f"{path}: {len(damage)} damaged part(s) of the input (listed above); the views "
             "show what could be read")
        return EXIT_BAD
    return EXIT_OK


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in name.strip("/")) or "root"
