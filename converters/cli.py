"""The ``lidarscan`` command line (console script ``lidarscan = converters.cli:main``).

Commands::

    lidarscan demo [--out DIR] [--frames N] [--no-images]
    lidarscan info FILE.mcap
    lidarscan convert IN OUT [--pointcloud2] [--preset P | --fields x,y,z,...]
                             [--slice NAME:ZMIN:ZMAX]... [--frame F] [--extrinsics ...]
                             [--merge] [--merge-topic TOPIC]...
    lidarscan view FILE.mcap --out DIR [--index K]

Exit status: 0 success; 1 the run finished but some messages were bad (each one reported on
stderr with its index, topic, stamp and reason) or, for ``info``, problems were found;
2 usage error or fatal error (unreadable input, invalid option); 130 interrupted by Ctrl-C
(``convert`` still closes its output, which is a valid MCAP of everything written so far).

Only this module prints and exits; everything it calls raises.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

__all__ = ["build_parser", "main"]

EXIT_OK, EXIT_BAD, EXIT_FATAL, EXIT_INTERRUPTED = 0, 1, 2, 130


# ------------------------------------------------------------------------------- utilities

class Progress:
    """A one-line progress bar on stderr (only when stderr is a terminal, at most 10 Hz)."""

    def __init__(self, total: int, label: str, *, stream: IO[str] | None = None,
                 enabled: bool | None = None) -> None:
        self.total = max(int(total), 1)
        self.label = label
        self.stream = stream or sys.stderr
        self.enabled = self.stream.isatty() if enabled is None else enabled
        self._last = 0.0
        self._shown = False

    def update(self, done: int, extra: str = "", *, force: bool = False) -> None:
        if not self.enabled:
            return
        now = time.monotonic()
        if not force and now - self._last < 0.1:
            return
        self._last = now
        fraction = min(max(done / self.total, 0.0), 1.0)
        bar = "#" * int(fraction * 30)
        self.stream.write(f"\r{self.label} [{bar:<30}] {100 * fraction:5.1f}% {extra}\x1b[K")
        self.stream.flush()
        self._shown = True

    def close(self) -> None:
        if self._shown:
            self.stream.write("\n")
            self.stream.flush()
            self._shown = False


def _err(*parts: Any) -> None:
    print(*parts, file=sys.stderr)


def _fmt_stamp(ns: int) -> str:
    return f"{ns // 1_000_000_000}.{ns % 1_000_000_000:09d}"


def _namespace(topic: str) -> str:
    """'/lidar/scan' -> '/lidar'; '/scan' or 'scan' -> ''."""
    head, _, _ = topic.rstrip("/").rpartition("/")
    return head


# ------------------------------------------------------------------------------------ demo

def cmd_demo(args: argparse.Namespace) -> int:
    from converters.demo import run_demo

    progress = Progress(args.frames, "simulating")
    try:
        result = run_demo(args.out, args.frames, images=not args.no_images,
                          noise_m=args.noise, progress=lambda d, t: progress.update(d, f"{d}/{t}"))
    finally:
        progress.close()
    print(result.summary())
    return EXIT_OK


# ------------------------------------------------------------------------------------ info

@dataclass
class _TopicStats:
    msgtype: str
    count: int = 0
    first_ns: int | None = None
    last_ns: int | None = None


def cmd_info(args: argparse.Namespace) -> int:
    import lidarscan
    from lidarscan.geometry import info_key
    from lidarscan.mcap import INFO_TYPE, BadMessage, read_messages, read_scans

    path = Path(args.file)
    if not path.is_file():
        raise FileNotFoundError(f"no such file: {path}")
    topics: dict[str, _TopicStats] = {}
    bad: list[BadMessage] = []
    versions: dict[tuple[str, int], dict[str, Any]] = {}
    total = 0
    for item in read_messages(path):
        if isinstance(item, BadMessage):
            bad.append(item)
            continue
        total += 1
        stats = topics.setdefault(item.topic, _TopicStats(item.msgtype))
        stats.count += 1
        stats.first_ns = item.log_time_ns if stats.first_ns is None else stats.first_ns
        stats.last_ns = item.log_time_ns
        if item.msgtype == INFO_TYPE:
            try:
                info = item.decode()
                lidarscan.validate_info(info)
            except lidarscan.errors.LidarScanError as err:
                bad.append(BadMessage(item.index, item.topic, item.log_time_ns, str(err), err))
                continue
            stamp, digest = info_key(info)
            entry = versions.setdefault((item.topic, stamp), {
                "info": info, "digests": set(), "count": 0})
            entry["digests"].add(digest)
            entry["count"] += 1
    print(f"{path}: {total} messages on {len(topics)} topics")
    width = max([len(t) for t in topics] + [5])
    print(f"  {'topic':<{width}}  {'type':<32} {'count':>7}  first .. last log time (s)")
    for topic, stats in sorted(topics.items()):
        span = (f"{_fmt_stamp(stats.first_ns or 0)} .. {_fmt_stamp(stats.last_ns or 0)}"
                if stats.count else "")
        print(f"  {topic:<{width}}  {stats.msgtype:<32} {stats.count:>7}  {span}")
    problems = len(bad)
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
    paired = sum(1 for _ in read_scans(path, on_error=linkage.append))
    scans = sum(s.count for s in topics.values()
                if s.msgtype == "lidarscan_msgs/msg/LidarScan")
    if scans:
        print(f"LidarScans linked to their LidarInfo: {paired} of {scans}")
    # read_scans also reports undecodable records that read_messages reported: keep them once
    seen = {(b.index, b.reason) for b in bad}
    extra = [b for b in linkage if (b.index, b.reason) not in seen]
    problems += len(extra)
    for item in bad + extra:
        print(f"  problem: message #{item.index} topic '{item.topic}' "
              f"log time {_fmt_stamp(item.log_time_ns)}: {item.reason}")
    print("no problems found" if not problems else f"{problems} problem(s) found")
    return EXIT_OK if not problems else EXIT_BAD


# --------------------------------------------------------------------------------- convert

@dataclass
class ConvertReport:
    """Counters of one ``convert`` run."""

    read: int = 0
    written: int = 0
    converted: int = 0
    bad: list[tuple[int, str, int, str]] = field(default_factory=list)

    def report_bad(self, index: int, topic: str, stamp_ns: int, reason: str,
                   emit: Callable[[str], None]) -> None:
        self.bad.append((index, topic, stamp_ns, reason))
        emit(f"bad message #{index} topic '{topic}' stamp {_fmt_stamp(stamp_ns)}: {reason}")


def _file_topics(path: Path) -> dict[str, str]:
    """topic -> type from the file's summary, or from a quick pass when it has none."""
    from lidarscan.mcap import BadMessage, read_messages

    try:
        from mcap.reader import make_reader

        with open(path, "rb") as stream:
            summary = make_reader(stream).get_summary()
        if summary is not None and summary.channels:
            return {c.topic: summary.schemas[c.schema_id].name
                    for c in summary.channels.values() if c.schema_id in summary.schemas}
    except Exception:  # noqa: BLE001, S110 - damaged summary: fall back to streaming
        pass
    out: dict[str, str] = {}
    for item in read_messages(path):
        if not isinstance(item, BadMessage):
            out.setdefault(item.topic, item.msgtype)
    return out


def _cloud_options(args: argparse.Namespace) -> dict[str, Any]:
    options: dict[str, Any] = {}
    if args.preset:
        options["preset"] = args.preset
    elif args.fields:
        options["fields"] = tuple(f.strip() for f in args.fields.split(",") if f.strip())
    return options


def cmd_convert(args: argparse.Namespace) -> int:
    from lidarscan.errors import ConfigError
    from lidarscan.mcap import McapWriter

    src, dst = Path(args.input), Path(args.output)
    if not src.is_file():
        raise FileNotFoundError(f"no such file: {src}")
    if src.resolve() == dst.resolve():
        raise ConfigError("OUT", str(dst), "a file other than IN")
    from converters.nodes.params import parse_extrinsics, parse_slice_arg

    slices = [parse_slice_arg(s) for s in args.slice]
    if len({s.name for s in slices}) != len(slices):
        raise ConfigError("--slice", [s.name for s in slices], "unique slice names")
    fallback = parse_extrinsics(args.extrinsics) if args.extrinsics is not None else None
    if (args.merge or args.merge_topic) and not (slices or args.merge_topic):
        raise ConfigError("--merge", True, "at least one --slice or --merge-topic to merge")
    if args.merge_topic and not slices and not args.frame:
        raise ConfigError("--frame", "", "the output frame of the merged scan when only "
                          "--merge-topic inputs are merged")
    report = ConvertReport()
    emit = _err  # bad messages are always reported, also with --quiet
    note = _err if not args.quiet else (lambda line: None)
    writer = McapWriter(dst, compression=args.compression, chunk_size=1 << 20)
    progress = Progress(os.path.getsize(src), f"converting {src.name}",
                        enabled=None if not args.quiet else False)
    interrupted = False
    try:
        if src.suffix.lower() in (".pcap", ".osf"):
            _convert_ouster(src, writer, args, slices, fallback, report, emit)
        else:
            topics = _file_topics(src)
            kinds = set(topics.values())
            if "lidarscan_msgs/msg/LidarScan" not in kinds and \
                    "sensor_msgs/msg/PointCloud2" in kinds:
                _convert_clouds(src, writer, args, topics, report, emit, progress)
            else:
                _warn_collisions(topics, args, slices, note)
                _convert_scans(src, writer, args, slices, fallback, report, emit, progress)
    except KeyboardInterrupt:
        interrupted = True
    finally:
        progress.close()
        writer.close()
    if interrupted:
        _err(f"interrupted: {dst} is a valid MCAP file with the {writer.count} messages "
             f"written so far ({report.read} read)")
        return EXIT_INTERRUPTED
    summary = (f"{src} -> {dst}: {report.read} messages read, {report.converted} converted, "
               f"{writer.count} written")
    if report.bad:
        _err(f"{summary}; {len(report.bad)} BAD message(s) skipped (listed above)")
        return EXIT_BAD
    if not args.quiet:
        _err(summary)
    return EXIT_OK


def _warn_collisions(topics: dict[str, str], args: argparse.Namespace, slices: Sequence[Any],
                     emit: Callable[[str], None]) -> None:
    """A note when an output topic already exists in the input (both end up in OUT)."""
    outputs = set()
    for topic, kind in topics.items():
        if kind == "lidarscan_msgs/msg/LidarScan":
            ns = _namespace(topic)
            if args.pointcloud2:
                outputs.add(f"{ns}/points")
            outputs.update(f"{ns}/slices/{s.name}" for s in slices)
    if args.merge or args.merge_topic:
        outputs.add(args.merge_out)
    for topic in sorted(outputs & set(topics) - set(args.exclude)):
        emit(f"note: the input already has {topic}; the new messages are added to it "
             f"(--exclude {topic} drops the old ones)")


class _ScanPipeline:
    """Per linked (scan, info): PointCloud2, slices, merged scan; built lazily per info."""

    def __init__(self, args: argparse.Namespace, slices: Sequence[Any],
                 fallback: Any, tf_buffer: Any) -> None:
        from converters.nodes.converter_node import ConverterCore

        self.args = args
        self.core = ConverterCore(cloud_options=_cloud_options(args), slices=slices,
                                  target_frame=args.frame, max_pending=args.max_pending,
                                  max_wait_ns=None)
        self.slices = list(slices)
        self.fallback = fallback
        self.tf = tf_buffer
        self.merger: Any = None
        self.merge_inputs: list[str] = []

    def extrinsics(self, scan: Any, info: Any) -> Any:
        import numpy as np

        from converters.nodes.tf import TransformLookupError
        from lidarscan.stamps import to_ns

        frame = self.args.frame
        if not frame or frame == info.header.frame_id:
            return None
        try:
            return self.tf.lookup(frame, info.header.frame_id, to_ns(scan.header.stamp))
        except TransformLookupError as err:
            if self.fallback is not None:
                return np.asarray(self.fallback)
            raise TransformLookupError(
                "--frame", frame, f"a transform {frame} <- {info.header.frame_id} in the file's "
                f"/tf or /tf_static, or --extrinsics ({err})") from err


def _merger(args: argparse.Namespace, names: Sequence[str], extrinsics: dict[str, Any],
            frame: str) -> Any:
    import math

    from converters.merger import LaserScanMerger, MergerInput

    inputs = {name: MergerInput(extrinsics=extrinsics[name]) for name in names}
    return LaserScanMerger(inputs, frame_id=frame, angle_min=-math.pi,
                           angle_increment=math.radians(args.merge_increment),
                           range_min=0.0, range_max=args.merge_range_max)


def _convert_scans(src: Path, writer: Any, args: argparse.Namespace, slices: Sequence[Any],
                   fallback: Any, report: ConvertReport, emit: Callable[[str], None],
                   progress: Progress) -> None:
    """LidarScan recording: copy every good message, add the requested outputs."""
    import numpy as np

    from converters.nodes.tf import TransformBuffer
    from lidarscan.errors import LidarScanError
    from lidarscan.mcap import INFO_TYPE, SCAN_TYPE, BadMessage, McapMessage
    from lidarscan.stamps import to_ns

    tf = TransformBuffer(cache_ns=3600 * 10**9, max_per_edge=100_000)
    pipeline = _ScanPipeline(args, slices, fallback, tf)
    merge_topics = list(args.merge_topic)
    merging = bool(args.merge or merge_topics)
    merger: _LazyMerger | None = None
    if merging and args.frame:  # the output frame is known: inputs may come in any order
        merger = _LazyMerger(args, [sl.name for sl in slices] + merge_topics,
                             {**{sl.name: np.eye(4) for sl in slices},
                              **{t: None for t in merge_topics}}, args.frame, tf)
    origin: dict[int, McapMessage] = {}
    want_cloud = bool(args.pointcloud2)
    excluded = set(args.exclude)

    def outputs_for(scan: Any, info: Any, item: McapMessage) -> None:
        nonlocal merger
        ns = _namespace(item.topic)
        extrinsics = pipeline.extrinsics(scan, info) if slices else None
        cloud, out_slices = pipeline.core.convert(scan, info, cloud=want_cloud,
                                                  extrinsics=extrinsics)
        log = item.log_time_ns
        if cloud is not None:
            writer.write(f"{ns}/points", cloud, log_time_ns=log)
        for name, msg in out_slices.items():
            writer.write(f"{ns}/slices/{name}", msg, log_time_ns=log)
        report.converted += 1
        if merging and out_slices:
            if merger is None:
                frame = args.frame or next(iter(out_slices.values())).header.frame_id
                extr: dict[str, Any] = {name: np.eye(4) for name in out_slices}
                extr.update({topic: None for topic in merge_topics})
                merger = _LazyMerger(args, list(out_slices) + merge_topics, extr, frame, tf)
            for name, msg in out_slices.items():
                for merged in merger.push(name, msg):
                    writer.write(args.merge_out, merged, log_time_ns=log)

    for item in _stream(src, progress, report):
        if isinstance(item, BadMessage):
            report.report_bad(item.index, item.topic, item.log_time_ns, item.reason, emit)
            continue
        report.read += 1
        try:
            if item.msgtype in (INFO_TYPE, SCAN_TYPE):
                msg = item.decode()
                if item.msgtype == INFO_TYPE:
                    ready = pipeline.core.resolver.add_info(msg)
                else:
                    ready = pipeline.core.resolver.add_scan(msg)
                    origin[id(msg)] = item
            elif item.msgtype == "tf2_msgs/msg/TFMessage":
                tf.add_message(item.decode(), static=item.topic.endswith("_static"))
                ready = []
            elif merging and item.topic in merge_topics and \
                    item.msgtype == "sensor_msgs/msg/LaserScan":
                scan2d = item.decode()
                ready = []
                if merger is not None:
                    for merged in merger.push(item.topic, scan2d):
                        writer.write(args.merge_out, merged, log_time_ns=item.log_time_ns)
            else:
                ready = []
        except LidarScanError as err:
            report.report_bad(item.index, item.topic, item.log_time_ns, str(err), emit)
            continue
        if item.topic not in excluded:
            writer.write(item.topic, item.payload, msgtype=item.msgtype,
                         log_time_ns=item.log_time_ns, publish_time_ns=item.publish_time_ns)
            report.written += 1
        _drain_drops(pipeline, origin, report, emit)
        for scan, info in ready:
            src_item = origin.pop(id(scan), item)
            try:
                outputs_for(scan, info, src_item)
            except LidarScanError as err:
                report.report_bad(src_item.index, src_item.topic,
                                  to_ns(scan.header.stamp), f"not converted: {err}", emit)
    pipeline.core.resolver.flush()
    _drain_drops(pipeline, origin, report, emit)


def _drain_drops(pipeline: _ScanPipeline, origin: dict[int, Any], report: ConvertReport,
                 emit: Callable[[str], None]) -> None:
    for drop in pipeline.core.resolver.take_dropped():
        item = origin.pop(id(drop.scan), None)
        report.report_bad(item.index if item else -1, item.topic if item else "",
                          drop.stamp_ns, f"not converted: {drop.reason}", emit)


class _LazyMerger:
    """The merger of ``convert --merge``: inputs' extrinsics resolved from the file's TF.

    Scans pushed before every input's mount is known are held (at most ``hold`` of them) and
    replayed once the merger can be built.
    """

    def __init__(self, args: argparse.Namespace, names: Sequence[str],
                 extrinsics: dict[str, Any], frame: str, tf: Any, hold: int = 64) -> None:
        self.args, self.names, self.extrinsics = args, list(names), dict(extrinsics)
        self.frame, self.tf, self.hold = frame, tf, hold
        self._merger: Any = None
        self._held: list[tuple[str, Any]] = []

    def push(self, name: str, scan: Any) -> list[Any]:
        """Queue one scan; returns the merged scans that became ready (usually 0 or 1)."""
        from converters.nodes.tf import TransformLookupError

        if self.extrinsics.get(name) is None:
            source = scan.header.frame_id
            try:
                self.extrinsics[name] = self.tf.lookup(self.frame, source)
            except TransformLookupError as err:
                raise TransformLookupError(
                    "--merge-topic", name, f"a transform {self.frame} <- {source} in the file's "
                    f"/tf_static ({err})") from err
        if self._merger is None:
            self._held.append((name, scan))
            del self._held[:-self.hold]
            if any(self.extrinsics.get(n) is None for n in self.names):
                return []  # wait until every input's mount is known
            self._merger = _merger(self.args, self.names, self.extrinsics, self.frame)
            held, self._held = self._held, []
            out = [self._merger.push(n, s) for n, s in held]
            return [m for m in out if m is not None]
        merged = self._merger.push(name, scan)
        return [] if merged is None else [merged]


def _stream(src: Path, progress: Progress, report: ConvertReport) -> Iterable[Any]:
    """read_messages over an open file, updating the progress bar from the file position."""
    from lidarscan.mcap import read_messages

    with open(src, "rb") as stream:
        for item in read_messages(stream):
            progress.update(stream.tell(), f"{report.read} msgs")
            yield item
        progress.update(progress.total, f"{report.read} msgs", force=True)


def _convert_clouds(src: Path, writer: Any, args: argparse.Namespace, topics: dict[str, str],
                    report: ConvertReport, emit: Callable[[str], None],
                    progress: Progress) -> None:
    """Driver PointCloud2 recording -> LidarScan + LidarInfo (a new info only on change)."""
    from converters.nodes.cloud_to_scan_node import CloudToScanCore
    from lidarscan.errors import LidarScanError
    from lidarscan.mcap import BadMessage

    cloud_topics = [t for t, k in topics.items() if k == "sensor_msgs/msg/PointCloud2"]
    if args.cloud_topic:
        cloud_topics = [t for t in cloud_topics if t in args.cloud_topic]
    cores = {t: CloudToScanCore() for t in cloud_topics}
    for item in _stream(src, progress, report):
        if isinstance(item, BadMessage):
            report.report_bad(item.index, item.topic, item.log_time_ns, item.reason, emit)
            continue
        report.read += 1
        core = cores.get(item.topic)
        if core is not None:
            try:
                scan, info, changed = core.convert(item.decode())
            except LidarScanError as err:
                report.report_bad(item.index, item.topic, item.log_time_ns, str(err), emit)
                continue
            ns = _namespace(item.topic)
            if changed:
                writer.write(f"{ns}/lidar_info", info, log_time_ns=item.log_time_ns)
            writer.write(f"{ns}/lidar_scan", scan, log_time_ns=item.log_time_ns)
            report.converted += 1
            if not args.keep_clouds:
                continue
        if item.topic in args.exclude:
            continue
        writer.write(item.topic, item.payload, msgtype=item.msgtype,
                     log_time_ns=item.log_time_ns, publish_time_ns=item.publish_time_ns)
        report.written += 1


def _convert_ouster(src: Path, writer: Any, args: argparse.Namespace, slices: Sequence[Any],
                    fallback: Any, report: ConvertReport, emit: Callable[[str], None]) -> None:
    """Ouster pcap/OSF (via ouster-sdk) -> LidarInfo + LidarScan (+ the requested outputs)."""
    from converters.nodes.tf import TransformBuffer
    from converters.ouster import scans_from_recording
    from lidarscan.errors import LidarScanError
    from lidarscan.stamps import to_ns

    pipeline = _ScanPipeline(args, slices, fallback, TransformBuffer())
    info_written = None
    for index, (scan, info) in enumerate(scans_from_recording(src, meta=args.metadata)):
        report.read += 1
        stamp = to_ns(scan.header.stamp)
        if info_written is not info:
            writer.write("/lidar/info", info, log_time_ns=stamp)
            info_written = info
        writer.write("/lidar/scan", scan, log_time_ns=stamp)
        try:
            cloud, out_slices = pipeline.core.convert(
                scan, info, cloud=bool(args.pointcloud2),
                extrinsics=pipeline.extrinsics(scan, info) if slices else None)
        except LidarScanError as err:
            report.report_bad(index, "/lidar/scan", stamp, f"not converted: {err}", emit)
            continue
        if cloud is not None:
            writer.write("/lidar/points", cloud, log_time_ns=stamp)
        for name, msg in out_slices.items():
            writer.write(f"/lidar/slices/{name}", msg, log_time_ns=stamp)
        report.converted += 1


# ------------------------------------------------------------------------------------ view

def cmd_view(args: argparse.Namespace) -> int:
    import numpy as np

    from converters import viz
    from converters.nodes.tf import TransformBuffer, TransformLookupError
    from lidarscan.errors import LidarScanError
    from lidarscan.mcap import BadMessage, read_messages, read_scans
    from lidarscan.stamps import to_ns

    path, out = Path(args.file), Path(args.out)
    if not path.is_file():
        raise FileNotFoundError(f"no such file: {path}")
    written: list[Path] = []
    # 1. range images: the index-th linked scan of each LidarScan topic
    seen: dict[str, int] = {}
    chosen_stamp: int | None = None
    for scan, info in read_scans(path):
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
    for item in read_messages(path):
        if isinstance(item, BadMessage):
            continue
        try:
            if item.msgtype == "tf2_msgs/msg/TFMessage":
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
    if not written:
        _err(f"{path}: nothing to draw (no LidarScan with its LidarInfo, LaserScan or "
             f"PointCloud2 at index {args.index})")
        return EXIT_BAD
    for p in written:
        print(p)
    return EXIT_OK


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in name.strip("/")) or "root"


# ---------------------------------------------------------------------------------- parser

def build_parser() -> argparse.ArgumentParser:
    """The argparse parser of ``lidarscan``."""
    parser = argparse.ArgumentParser(
        prog="lidarscan",
        description="Structured lidar scans (LidarScan + LidarInfo) for ROS 2: demo, inspect, "
                    "convert and draw MCAP recordings.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("demo", help="simulate a robot in a room, convert, record and draw",
                       description="Simulated robot with a 3D lidar (real Ouster OS-1-128 "
                                   "geometry) and a 2D lidar in a room with a table and an "
                                   "overhanging shelf. Writes DIR/demo.mcap and PNG views.")
    p.add_argument("--out", default="demo_out", help="output folder (default: ./demo_out)")
    p.add_argument("--frames", type=_positive_int, default=10, help="frames at 10 Hz (10)")
    p.add_argument("--no-images", action="store_true", help="skip the PNG views")
    p.add_argument("--noise", type=float, default=0.0, metavar="M",
                   help="range noise of the 3D lidar, metres (0: exact)")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("info", help="topics, types, counts, LidarInfo versions, linkage",
                       description="Summarise an MCAP recording; exit status 1 if it has "
                                   "problems (bad messages, unlinked scans, conflicting infos).")
    p.add_argument("file", help="an MCAP file")
    p.set_defaults(func=cmd_info)

    p = sub.add_parser(
        "convert", help="offline conversion of a recording",
        description="LidarScan MCAP: copy every message and add PointCloud2 (<ns>/points), "
                    "slices (<ns>/slices/NAME) and a merged scan. A recording of driver "
                    "PointCloud2 (no LidarScan in it): convert the organized clouds to "
                    "<ns>/lidar_scan + <ns>/lidar_info. An Ouster .pcap/.osf (needs "
                    "ouster-sdk): /lidar/info + /lidar/scan (+ outputs). Bad messages are "
                    "reported on stderr with index, topic, stamp and reason; every good one "
                    "is written. Exit status 0 all good, 1 some bad, 2 fatal, 130 Ctrl-C "
                    "(OUT stays readable).")
    p.add_argument("input", help="input recording (.mcap, or .pcap/.osf with --metadata)")
    p.add_argument("output", help="output MCAP file")
    p.add_argument("--pointcloud2", action="store_true", help="add PointCloud2 per scan")
    p.add_argument("--preset", default="", help="PointCloud2 field preset")
    p.add_argument("--fields", default="", help="PointCloud2 fields, e.g. x,y,z,intensity")
    p.add_argument("--slice", action="append", default=[], metavar="NAME:ZMIN:ZMAX",
                   help="add a LaserScan height slice (repeatable), heights in --frame")
    p.add_argument("--frame", default="",
                   help="frame of the slices (default: the scan's); pose from the file's TF")
    p.add_argument("--extrinsics", type=_floats, default=None, metavar="X,Y,Z,R,P,Y",
                   help="FRAME <- sensor when the file has no TF (6, 7 or 16 numbers)")
    p.add_argument("--merge", action="store_true", help="merge the slices into one scan")
    p.add_argument("--merge-topic", action="append", default=[], metavar="TOPIC",
                   help="also merge this LaserScan topic of the input (repeatable)")
    p.add_argument("--merge-out", default="/scan_merged", help="topic of the merged scan")
    p.add_argument("--merge-increment", type=float, default=0.25,
                   help="merged scan angle increment, degrees (0.25)")
    p.add_argument("--merge-range-max", type=float, default=100.0,
                   help="merged scan range_max, metres (100)")
    p.add_argument("--cloud-topic", action="append", default=[],
                   help="PointCloud2 input topic(s) to convert (default: all)")
    p.add_argument("--keep-clouds", action="store_true",
                   help="also copy the input PointCloud2 messages")
    p.add_argument("--exclude", action="append", default=[], metavar="TOPIC",
                   help="do not copy this input topic (repeatable), e.g. to replace it")
    p.add_argument("--metadata", default=None, help="Ouster metadata JSON for a .pcap")
    p.add_argument("--max-pending", type=_positive_int, default=64,
                   help="scans held while waiting for their LidarInfo (64)")
    p.add_argument("--compression", choices=("zstd", "lz4", "none"), default="zstd")
    p.add_argument("-q", "--quiet", action="store_true",
                   help="no progress bar, notes or summary (bad messages are still listed)")
    p.set_defaults(func=cmd_convert)

    p = sub.add_parser("view", help="PNG views of a recording",
                       description="Range images of a LidarScan, a top view of the LaserScans "
                                   "(in --frame via the file's TF) and of each PointCloud2.")
    p.add_argument("file", help="an MCAP file")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--index", type=_non_negative_int, default=0,
                   help="which scan of each topic (0 = first)")
    p.add_argument("--frame", default="", help="frame of the LaserScan top view")
    p.set_defaults(func=cmd_view)
    return parser


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: expected an integer >= 1")
    return value


def _non_negative_int(text: str) -> int:
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"{text!r}: expected an integer >= 0")
    return value


def _floats(text: str) -> list[float]:
    try:
        return [float(v) for v in text.replace(" ", ",").split(",") if v]
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"{text!r}: expected comma-separated numbers") from err


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the exit status (see the module docstring)."""
    from lidarscan.errors import LidarScanError

    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args))
    except KeyboardInterrupt:
        _err("interrupted")
        return EXIT_INTERRUPTED
    except LidarScanError as err:
        _err(f"lidarscan {args.command}: error: {err}")
        return EXIT_FATAL
    except (OSError, ImportError) as err:
        _err(f"lidarscan {args.command}: error: {err}")
        return EXIT_FATAL


if __name__ == "__main__":
    sys.exit(main())
