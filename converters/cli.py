"""The ``lidarscan`` command line (console script ``lidarscan = converters.cli:main``).

Commands::

    lidarscan --version
    lidarscan demo [--out DIR] [--frames N] [--no-images]
    lidarscan info REC
    lidarscan convert REC OUT.mcap [--pointcloud2] [--preset P | --fields x,y,z,...]
                                   [--slice NAME:ZMIN:ZMAX[:holes[:KEY=VALUE]...]]...
                                   [--frame F] [--extrinsics ...]
                                   [--merge] [--merge-topic TOPIC]... [--calibration FILE]
                                   [--cut-angle DEG] [--replace] [--keep-packets] [--progress]
                                   [--compress] [--chunk-compression C] [--zstd-level N] [-q]
    lidarscan view REC --out DIR [--index K]

REC is an MCAP file, a rosbag2 directory (``metadata.yaml`` + ``.db3`` or ``.mcap`` storage) or a
single rosbag2 ``.db3`` file; ``convert`` also takes an Ouster ``.pcap``/``.osf``. What a path is
is told from its contents and said in every error about it.

Exit status: 0 success; 1 the run finished but some messages or parts of the input were bad
(each one reported on stderr: index, topic, stamp and reason, or for a damaged part of the file
its offset and time range) or, for ``info``, problems were found; 2 usage error or fatal error
(missing, empty or unreadable input, input of the wrong kind, an invalid option value, an option
that does not fit the recording, an output topic that clashes with an input topic): nothing is
written; 130 interrupted by Ctrl-C (``convert`` still closes its output, which is a valid MCAP of
everything written so far).

``convert`` writes OUT under a temporary name next to it and renames it only when the run ends
(also with bad messages, exit 1): a failed run never leaves a partial or empty OUT.

Only this module prints and exits; everything it calls raises.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

__all__ = ["build_parser", "main"]

EXIT_OK, EXIT_BAD, EXIT_FATAL, EXIT_INTERRUPTED = 0, 1, 2, 130


# ------------------------------------------------------------------------------- utilities

class Progress:
    """Progress on stderr: a one-line bar at most 10 Hz on a terminal; when enabled on a
    stream that is not a terminal (``--progress``), one line per 10 %."""

    def __init__(self, total: int, label: str, *, stream: IO[str] | None = None,
                 enabled: bool | None = None) -> None:
        self.total = max(int(total), 1)
        self.label = label
        self.stream = stream or sys.stderr
        tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.enabled = tty if enabled is None else enabled
        self.lines = self.enabled and not tty
        self._last = 0.0
        self._step = -1
        self._shown = False

    def update(self, done: int, extra: str = "", *, force: bool = False) -> None:
        if not self.enabled:
            return
        fraction = min(max(done / self.total, 0.0), 1.0)
        if self.lines:
            step = int(fraction * 10)
            if step != self._step:
                self._step = step
                self.stream.write(f"{self.label}: {100 * fraction:3.0f}% {extra}\n")
                self.stream.flush()
            return
        now = time.monotonic()
        if not force and now - self._last < 0.1:
            return
        self._last = now
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


_TRUE, _FALSE = ("1", "true", "yes", "on"), ("0", "false", "no", "off")


def parse_slice(text: str) -> Any:
    """``NAME:ZMIN:ZMAX[:KEY[=VALUE]]...`` -> :class:`converters.nodes.params.SliceConfig`.

    KEYs are the hole options of a slice (:data:`converters.options.HOLE_KEYS`): ``holes``
    (alone: on), ``floor_height`` (metres, in --frame), ``hole_depth`` (metres, > 0),
    ``hole_range_max`` (metres, > 0, ``inf``), ``hole_no_return`` (true/false), e.g.
    ``floor:0.05:0.5:holes:floor_height=0:hole_depth=0.08``.

    Raises:
        ConfigError: naming the bad part of ``text`` and what was expected.
    """
    from converters.nodes.params import SliceConfig, parse_slice_arg
    from converters.options import HOLE_KEYS, number
    from lidarscan.errors import ConfigError

    parts = str(text).split(":")
    base = parse_slice_arg(":".join(parts[:3]))
    extra: dict[str, Any] = {}
    for part in parts[3:]:
        key, has_value, value = part.partition("=")
        key, value = key.strip(), value.strip().lower()
        where = f"--slice {text}: {key or part!r}"
        if key not in HOLE_KEYS:
            raise ConfigError(where, part,
                              f"KEY or KEY=VALUE with KEY among {', '.join(HOLE_KEYS)}")
        if key in extra:
            raise ConfigError(where, part, "each key once")
        if key in ("holes", "hole_no_return"):
            if not has_value or value in _TRUE:
                extra[key] = True
            elif value in _FALSE:
                extra[key] = False
            else:
                raise ConfigError(where, value, "true or false")
            continue
        try:
            amount = float(value)
        except ValueError:
            raise ConfigError(where, value or None, "a number of metres") from None
        extra[key] = number(where, amount, positive=key != "floor_height",
                            allow_inf=key == "hole_range_max")
    if not extra.get("holes") and extra:
        raise ConfigError(f"--slice {text}", sorted(extra)[0], "'holes' among the keys (the "
                          "other hole options only apply with holes on)")
    return SliceConfig(base.name, base.min_height, base.max_height, extra=extra)


# ---------------------------------------------------------------------------------- inputs

@dataclass
class _Input:
    """A recording named on the command line: an MCAP file, a rosbag2 bag or an Ouster file.

    Attributes:
        path: as given.
        kind: :class:`converters.bags.InputKind` (``kind.kind`` is ``"ouster"`` for .pcap/.osf).
        bag: the :class:`converters.bags.Bag` of a rosbag2 directory or .db3 file.
    """

    path: Path
    kind: Any
    bag: Any = None

    def topics(self) -> dict[str, str]:
        """topic -> message type."""
        if self.bag is not None:
            return {t.name: t.msgtype for t in self.bag.topics.values()}
        return _file_topics(self.path)

    def items(self, progress: Progress | None = None) -> Iterator[Any]:
        """Every message (McapMessage) and damaged part (BadMessage), updating ``progress``."""
        from lidarscan.mcap import read_messages

        if self.bag is not None:
            if progress is not None:
                progress.total = max(self.bag.message_count, 1)
            count = 0
            for item in self.bag.messages():
                count += 1
                if progress is not None:
                    progress.update(count, f"{count} msgs")
                yield item
        else:
            with open(self.path, "rb") as stream:
                for item in read_messages(stream):
                    count = item.index + 1
                    if progress is not None:
                        progress.update(stream.tell(), f"{count} msgs")
                    yield item
        if progress is not None:
            progress.update(progress.total, "done", force=True)


def _open_input(name: str, role: str, *, ouster: bool = False) -> _Input:
    """Check what ``name`` is before anything is written (exit 2 with the reason otherwise)."""
    from converters.bags import InputKind, detect_input, open_bag
    from lidarscan.errors import McapFormatError

    path = Path(name)
    if ouster and path.suffix.lower() in (".pcap", ".osf") and path.is_file():
        return _Input(path, InputKind("ouster", "an Ouster recording"))
    kind = detect_input(path)
    if kind.kind == "missing":
        raise FileNotFoundError(f"{role} {path}: no such file or directory")
    if kind.kind == "mcap":
        return _Input(path, kind)
    if kind.is_bag:
        return _Input(path, kind, open_bag(path))
    raise McapFormatError(f"{role} {path}", kind.description,
                          "an MCAP file, a rosbag2 directory or a rosbag2 .db3 file"
                          + (" (or an Ouster .pcap/.osf)" if ouster else ""))


def _describe_bad(item: Any) -> str:
    """One line for a BadMessage: a message, or a damaged part of the input."""
    if item.index < 0:
        return f"damaged input: {item.reason}"
    return (f"bad message #{item.index} topic '{item.topic}' stamp "
            f"{_fmt_stamp(item.log_time_ns)}: {item.reason}")


# ------------------------------------------------------------------------------------ demo

def cmd_demo(args: argparse.Namespace) -> int:
    import importlib.util

    from converters.demo import run_demo
    from lidarscan._install import missing_module_hint

    images = not args.no_images
    if images and importlib.util.find_spec("matplotlib") is None:   # a plain `pip install`
        images = False
        _err(f"note: no PNG views: {missing_module_hint('matplotlib', 'lidarscan demo')}")
    progress = Progress(args.frames, "simulating")
    try:
        result = run_demo(args.out, args.frames, images=images,
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
    from converters.bags import PACKET_TYPES
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
                msg = item.decode()
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

    def good(self, items: Iterable[Any], emit: Callable[[str], None]) -> Iterator[Any]:
        """The readable messages of ``items`` (counted in ``read``); each BadMessage of the
        reader (a message, or a damaged part of the input) is reported."""
        from lidarscan.mcap import BadMessage

        for item in items:
            if not isinstance(item, BadMessage):
                self.read += 1
                yield item
            else:
                self.bad.append((item.index, item.topic, item.log_time_ns, item.reason))
                emit(_describe_bad(item))


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
        options["fields"] = args.fields
    return options


def _option_error(err: Exception, topic: str, args: argparse.Namespace) -> Exception:
    """No scan of a topic could be converted, for a reason its options decide: one usage error
    (the run stops, exit 2, nothing written)."""
    from converters.nodes.tf import TransformLookupError
    from lidarscan.errors import ConfigError

    if isinstance(err, TransformLookupError):
        return err  # it names --frame / --merge-topic and the transform it needs
    given = [f"--preset {args.preset}" if args.preset else "",
             f"--fields {','.join(args.fields)}" if args.fields else "",
             *[f"--slice {s}" for s in args.slice]]
    return ConfigError(" ".join(g for g in given if g) or "options", "",
                       f"options that fit the scans of {topic} ({err})")


def _is_option_error(err: Exception) -> bool:
    from converters.nodes.tf import TransformLookupError
    from lidarscan.errors import ConfigError, UnknownChannelError

    return isinstance(err, (ConfigError, UnknownChannelError, TransformLookupError))


@dataclass
class _Plan:
    """Output topics of one run: where the outputs of each input topic go."""

    prefix: dict[str, str] = field(default_factory=dict)  # input topic -> output namespace
    outputs: dict[str, str] = field(default_factory=dict)  # output topic -> the input it is from
    excluded: set[str] = field(default_factory=set)


def _prefixes(inputs: Sequence[str]) -> dict[str, str]:
    """Each input's output namespace: its own namespace when no other input shares it, else the
    input topic itself (so outputs of different inputs never share a topic)."""
    shared: dict[str, int] = {}
    for topic in inputs:
        shared[_namespace(topic)] = shared.get(_namespace(topic), 0) + 1
    return {t: _namespace(t) if shared[_namespace(t)] == 1 else t for t in inputs}


def _plan(topics: dict[str, str], args: argparse.Namespace, slices: Sequence[Any],
          mode: str) -> _Plan:
    """The output topics; refuses (exit 2) an output topic the input already has unless it is
    excluded (``--exclude TOPIC`` or ``--replace``)."""
    from converters.bags import PACKET_TYPES
    from lidarscan.errors import ConfigError
    from lidarscan.mcap import SCAN_TYPE

    plan = _Plan(excluded=set(args.exclude))
    if mode == "packets":
        sources = [t for t, k in topics.items() if k in PACKET_TYPES]
        plan.prefix = {t: t for t in sources}
        per = ["lidar_info", "lidar_scan"]
    elif mode == "clouds":
        sources = [t for t, k in topics.items() if k == "sensor_msgs/msg/PointCloud2"
                   and (not args.cloud_topic or t in args.cloud_topic)]
        plan.prefix = _prefixes(sources)
        per = ["lidar_info", "lidar_scan"]
    else:
        sources = [t for t, k in topics.items() if k == SCAN_TYPE]
        plan.prefix = _prefixes(sources)
        per = []
    per += (["points"] if args.pointcloud2 and mode != "clouds" else []) + \
        [f"slices/{s.name}" for s in slices]
    for topic in sources:
        for name in per:
            plan.outputs[f"{plan.prefix[topic]}/{name}"] = topic
    if args.merge or args.merge_topic:
        plan.outputs[args.merge_out] = "the merged scan"
    clashes = sorted(t for t in plan.outputs if t in topics and t not in plan.excluded)
    if clashes and args.replace:
        plan.excluded.update(clashes)
        clashes = []
    if clashes:
        raise ConfigError("output topics", clashes, "topics the input does not already have "
                          f"(the input's {clashes[0]} would be mixed with the new messages "
                          f"made from {plan.outputs[clashes[0]]}); drop the input's with "
                          "--exclude TOPIC or --replace, or choose other slice names / "
                          "--merge-out")
    return plan


def cmd_convert(args: argparse.Namespace) -> int:
    from lidarscan.errors import ConfigError, McapFormatError
    from lidarscan.mcap import CODEC_ENCODING, SCAN_TYPE, McapWriter

    source = _open_input(args.input, "IN", ouster=True)
    src, dst = source.path, Path(args.output)
    if dst.is_dir():
        raise ConfigError("OUT", str(dst), "a file name (it is a directory)")
    if src.resolve() == dst.resolve():
        raise ConfigError("OUT", str(dst), "a file other than IN")
    if not dst.parent.is_dir():
        raise FileNotFoundError(f"OUT {dst}: no such directory {dst.parent}")
    from converters.nodes.params import parse_extrinsics

    slices = [parse_slice(s) for s in args.slice]
    if len({s.name for s in slices}) != len(slices):
        raise ConfigError("--slice", [s.name for s in slices], "unique slice names")
    fallback = parse_extrinsics(args.extrinsics) if args.extrinsics is not None else None
    if (args.merge or args.merge_topic) and not (slices or args.merge_topic):
        raise ConfigError("--merge", True, "at least one --slice or --merge-topic to merge")
    if args.merge_topic and not slices and not args.frame:
        raise ConfigError("--frame", "", "the output frame of the merged scan when only "
                          "--merge-topic inputs are merged")
    if args.zstd_level is not None and args.compression != "zstd":
        raise ConfigError("--zstd-level", args.zstd_level, "--chunk-compression zstd (the "
                          f"chunks are {args.compression})")
    for option, value in (("--calibration", args.calibration), ("--metadata", args.metadata)):
        if value is not None and not Path(value).is_file():
            raise FileNotFoundError(f"{option} {value}: no such file")
    topics: dict[str, str] = {}
    mode = "ouster"
    if source.kind.kind != "ouster":
        from converters.bags import PACKET_TYPES

        topics = source.topics()
        kinds = set(topics.values())
        if kinds & set(PACKET_TYPES):
            mode = "packets"
        elif SCAN_TYPE not in kinds and "sensor_msgs/msg/PointCloud2" in kinds:
            mode = "clouds"
        else:
            mode = "scans"
    plan = _plan(topics, args, slices, mode)
    decoders = _packet_decoders(topics) if mode == "packets" else {}
    decoder_options = _decoder_options(args, decoders)
    if decoder_options:
        import functools
        decoders = {t: functools.partial(d, **decoder_options) for t, d in decoders.items()}
    report = ConvertReport()
    emit = _err  # bad messages are always reported, also with --quiet
    tmp = dst.with_name(f".{dst.name}.{os.getpid()}.partial")
    writer = McapWriter(tmp, compression=args.compression, chunk_size=1 << 20,
                        level=args.zstd_level,
                        scan_encoding=CODEC_ENCODING if args.compress else "cdr")
    size = sum(f.stat().st_size for f in source.bag.files) if source.bag else src.stat().st_size
    progress = Progress(size, f"converting {src.name}",
                        enabled=True if args.progress else (None if not args.quiet else False))
    interrupted = finished = False
    try:
        try:
            if mode == "ouster":
                _convert_ouster(src, writer, args, slices, fallback, report, emit)
            elif mode == "packets":
                _convert_packets(source, writer, args, plan, decoders, slices, fallback,
                                 report, emit, progress)
            elif mode == "clouds":
                _convert_clouds(source, writer, args, plan, slices, fallback, report, emit,
                                progress)
            else:
                _convert_scans(source, writer, args, plan, slices, fallback, report, emit,
                               progress)
        except KeyboardInterrupt:
            interrupted = True
        finally:
            progress.close()
            writer.close()
        if not interrupted and report.read == 0 and report.bad:
            raise McapFormatError(f"IN {src}", f"{len(report.bad)} damaged part(s), listed above",
                                  "at least one readable message; nothing written")
        os.replace(tmp, dst)
        finished = True
    finally:
        if not finished:
            tmp.unlink(missing_ok=True)
    if interrupted:
        _err(f"interrupted: {dst} is a valid MCAP file with the {writer.count} messages "
             f"written so far ({report.read} read)")
        return EXIT_INTERRUPTED
    summary = (f"{src} -> {dst}: {report.read} messages read, {report.converted} converted, "
               f"{writer.count} written")
    if report.bad:
        _err(f"{summary}; {len(report.bad)} BAD message(s) or damaged part(s) skipped "
             "(listed above)")
        return EXIT_BAD
    if not args.quiet:
        _err(summary)
    return EXIT_OK


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
        self.done: set[str] = set()  # input topics with one scan converted
        self.held: dict[str, list[tuple[int, int, Exception]]] = {}

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

    def outputs(self, scan: Any, info: Any, topic: str, prefix: str, log_time_ns: int,
                writer: Any, report: ConvertReport, merge: Callable[[str, Any, int], None],
                emit: Callable[[str], None]) -> None:
        """Write the cloud and slices of one scan under ``prefix`` (raises what the conversion
        raises; the caller passes it to :meth:`failed`)."""
        extrinsics = self.extrinsics(scan, info) if self.slices else None
        cloud, out_slices = self.core.convert(scan, info, cloud=bool(self.args.pointcloud2),
                                              extrinsics=extrinsics)
        if cloud is not None:
            writer.write(f"{prefix}/points", cloud, log_time_ns=log_time_ns)
        for name, msg in out_slices.items():
            writer.write(f"{prefix}/slices/{name}", msg, log_time_ns=log_time_ns)
            merge(f"{prefix}/slices/{name}", msg, log_time_ns)
        report.converted += 1
        if topic not in self.done:  # the options fit this topic: earlier failures were the data
            self.done.add(topic)
            for index, stamp_ns, err in self.held.pop(topic, []):
                report.report_bad(index, topic, stamp_ns, f"not converted: {err}", emit)

    def failed(self, err: Exception, index: int, topic: str, stamp_ns: int,
               report: ConvertReport, emit: Callable[[str], None]) -> None:
        """A scan that could not be converted: a bad message, unless no scan of its topic has
        converted yet and the error is one the options decide (``--frame``, ``--fields``, ...):
        then it is held until one does (then reported) or the run ends (see :meth:`finish`)."""
        if topic not in self.done and _is_option_error(err):
            self.held.setdefault(topic, []).append((index, stamp_ns, err))
        else:
            report.report_bad(index, topic, stamp_ns, f"not converted: {err}", emit)

    def finish(self) -> None:
        """Raise the usage error of a topic none of whose scans the options could convert."""
        for topic, failures in self.held.items():
            raise _option_error(failures[0][2], topic, self.args)


def _merger(args: argparse.Namespace, names: Sequence[str], extrinsics: dict[str, Any],
            frame: str) -> Any:
    import math

    from converters.merger import LaserScanMerger, MergerInput

    inputs = {name: MergerInput(extrinsics=extrinsics[name]) for name in names}
    return LaserScanMerger(inputs, frame_id=frame, angle_min=-math.pi,
                           angle_increment=math.radians(args.merge_increment),
                           range_min=0.0, range_max=args.merge_range_max)


def _merge_sink(args: argparse.Namespace, plan: _Plan, tf: Any, writer: Any
                ) -> Callable[[str, Any, int], None]:
    """push(input name, LaserScan, log time) for ``--merge``: inputs are the slice topics of
    every scan topic and the ``--merge-topic`` topics; a no-op without ``--merge``."""
    merge_topics = list(args.merge_topic)
    if not (args.merge or merge_topics):
        return lambda name, msg, log: None
    names = [t for t in plan.outputs if t != args.merge_out and "/slices/" in t] + merge_topics
    state: dict[str, Any] = {"merger": None}

    def push(name: str, msg: Any, log_time_ns: int) -> None:
        if name not in names:
            return
        if state["merger"] is None and not args.frame and name in merge_topics:
            return  # the merged frame is the first slice's: nothing to merge into yet
        if state["merger"] is None:
            state["merger"] = _LazyMerger(args, names, {n: None for n in names},
                                          args.frame or msg.header.frame_id, tf)
        for merged in state["merger"].push(name, msg):
            writer.write(args.merge_out, merged, log_time_ns=log_time_ns)
    return push


def _side_input(item: Any, tf: Any, args: argparse.Namespace,
                merge: Callable[[str, Any, int], None]) -> None:
    """A TF message into the buffer, a ``--merge-topic`` LaserScan into the merger (raises
    LidarScanError for one that does not decode)."""
    if item.msgtype == "tf2_msgs/msg/TFMessage":
        tf.add_message(item.decode(), static=item.topic.endswith("_static"))
    elif item.topic in args.merge_topic and item.msgtype == "sensor_msgs/msg/LaserScan":
        merge(item.topic, item.decode(), item.log_time_ns)


def _copy(writer: Any, item: Any, plan: _Plan, report: ConvertReport) -> None:
    """Copy one input message as it is (payload, times, channel metadata such as QoS)."""
    if item.topic in plan.excluded:
        return
    writer.write(item.topic, item.payload, msgtype=item.msgtype, log_time_ns=item.log_time_ns,
                 publish_time_ns=item.publish_time_ns, metadata=dict(item.metadata) or None,
                 encoding=getattr(item, "encoding", "cdr"))
    report.written += 1


def _convert_scans(source: _Input, writer: Any, args: argparse.Namespace, plan: _Plan,
                   slices: Sequence[Any], fallback: Any, report: ConvertReport,
                   emit: Callable[[str], None], progress: Progress) -> None:
    """LidarScan recording: copy every good message, add the requested outputs."""
    from converters.nodes.tf import TransformBuffer
    from lidarscan.errors import LidarScanError
    from lidarscan.mcap import INFO_TYPE, SCAN_TYPE, McapMessage
    from lidarscan.stamps import to_ns

    tf = TransformBuffer(cache_ns=3600 * 10**9, max_per_edge=100_000)
    pipeline = _ScanPipeline(args, slices, fallback, tf)
    merge = _merge_sink(args, plan, tf, writer)
    origin: dict[int, McapMessage] = {}

    for item in report.good(source.items(progress), emit):
        try:
            ready: list[Any] = []
            if item.msgtype in (INFO_TYPE, SCAN_TYPE):
                msg = item.decode()
                if item.msgtype == INFO_TYPE:
                    ready = pipeline.core.resolver.add_info(msg)
                else:
                    ready = pipeline.core.resolver.add_scan(msg)
                    origin[id(msg)] = item
            else:
                _side_input(item, tf, args, merge)
        except LidarScanError as err:
            report.report_bad(item.index, item.topic, item.log_time_ns, str(err), emit)
            continue
        _copy(writer, item, plan, report)
        _drain_drops(pipeline, origin, report, emit)
        for scan, info in ready:
            src_item = origin.pop(id(scan), item)
            try:
                pipeline.outputs(scan, info, src_item.topic, plan.prefix.get(
                    src_item.topic, _namespace(src_item.topic)), src_item.log_time_ns,
                    writer, report, merge, emit)
            except LidarScanError as err:
                pipeline.failed(err, src_item.index, src_item.topic, to_ns(scan.header.stamp),
                                report, emit)
    pipeline.core.resolver.flush()
    _drain_drops(pipeline, origin, report, emit)
    pipeline.finish()


def _drain_drops(pipeline: _ScanPipeline, origin: dict[int, Any], report: ConvertReport,
                 emit: Callable[[str], None]) -> None:
    for drop in pipeline.core.resolver.take_dropped():
        item = origin.pop(id(drop.scan), None)
        report.report_bad(item.index if item else -1, item.topic if item else "",
                          drop.stamp_ns, f"not converted: {drop.reason}", emit)


class _LazyMerger:
    """The merger of ``convert --merge``: inputs' extrinsics resolved from the file's TF (an
    input already in the merged frame needs none).

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
        import numpy as np

        from converters.nodes.tf import TransformLookupError

        if self.extrinsics.get(name) is None:
            source = scan.header.frame_id
            try:
                self.extrinsics[name] = np.eye(4) if source == self.frame else \
                    self.tf.lookup(self.frame, source)
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


def _convert_clouds(source: _Input, writer: Any, args: argparse.Namespace, plan: _Plan,
                    slices: Sequence[Any], fallback: Any, report: ConvertReport,
                    emit: Callable[[str], None], progress: Progress) -> None:
    """Driver PointCloud2 recording -> LidarScan + LidarInfo (a new info only on change); with
    ``--slice``, every cloud's slices from its points (any cloud, grid or not:
    :class:`converters.nodes.cloud_to_scan_node.CloudSlicer`), and a cloud without a grid
    gives its slices instead of failing (said once per topic)."""
    from converters.nodes.cloud_to_scan_node import CloudSlicer, CloudToScanCore
    from converters.nodes.tf import TransformBuffer
    from lidarscan.errors import ConfigError, LidarScanError

    cores = {t: CloudToScanCore() for t in plan.prefix}
    tf = TransformBuffer(cache_ns=3600 * 10**9, max_per_edge=100_000)
    holes = [s for s in slices if s.extra.get("holes")]
    # holes need rays: the slices then come from each cloud's LidarScan (a cloud with a grid)
    pipeline = _ScanPipeline(argparse.Namespace(**{**vars(args), "pointcloud2": False}),
                             slices, fallback, tf) if holes else None
    slicer = CloudSlicer(slices, target_frame=args.frame) if slices and not holes else None
    merge = _merge_sink(args, plan, tf, writer)
    gridless: set[str] = set()
    for item in report.good(source.items(progress), emit):
        core = cores.get(item.topic)
        if core is None:
            if slices:                                 # TF for --frame, --merge-topic scans
                try:
                    _side_input(item, tf, args, merge)
                except LidarScanError as err:
                    report.report_bad(item.index, item.topic, item.log_time_ns, str(err), emit)
                    continue
            _copy(writer, item, plan, report)
            continue
        ns = plan.prefix[item.topic]
        try:
            cloud = item.decode()
            scan, info, changed = core.convert(cloud) if slicer is None else \
                _grid_or_none(core, cloud)
        except LidarScanError as err:
            if pipeline is None:
                report.report_bad(item.index, item.topic, item.log_time_ns, str(err), emit)
            else:   # an option error unless a cloud of the topic had a grid (then bad data)
                pipeline.failed(ConfigError(
                    f"--slice {holes[0].name}", "holes", "clouds with a grid (holes need the "
                    "rays of a LidarScan; cloud_slices refuses them for clouds without one), "
                    f"or no holes ({err})"), item.index, item.topic, item.log_time_ns,
                    report, emit)
            continue
        if pipeline is not None:
            if changed:
                writer.write(f"{ns}/lidar_info", info, log_time_ns=item.log_time_ns)
            writer.write(f"{ns}/lidar_scan", scan, log_time_ns=item.log_time_ns)
            try:
                pipeline.outputs(scan, info, item.topic, ns, item.log_time_ns, writer, report,
                                 merge, emit)
            except LidarScanError as err:
                pipeline.failed(err, item.index, item.topic, item.log_time_ns, report, emit)
            if args.keep_clouds:
                _copy(writer, item, plan, report)
            continue
        if scan is not None:
            if changed:
                writer.write(f"{ns}/lidar_info", info, log_time_ns=item.log_time_ns)
            writer.write(f"{ns}/lidar_scan", scan, log_time_ns=item.log_time_ns)
        elif item.topic not in gridless:
            gridless.add(item.topic)
            if not args.quiet:
                _err(f"{item.topic}: a cloud gave no LidarScan ({info}); its slices are "
                     "written (said once per topic)")
        if slicer is not None:
            try:
                out = slicer.convert(cloud, _cloud_extrinsics(cloud, args, tf, fallback))
            except LidarScanError as err:
                report.report_bad(item.index, item.topic, item.log_time_ns,
                                  f"no slices: {err}", emit)
                continue
            for name, msg in out.items():
                writer.write(f"{ns}/slices/{name}", msg, log_time_ns=item.log_time_ns)
                merge(f"{ns}/slices/{name}", msg, item.log_time_ns)
        report.converted += 1
        if args.keep_clouds:
            _copy(writer, item, plan, report)
    if pipeline is not None:
        pipeline.finish()


def _grid_or_none(core: Any, cloud: Any) -> tuple[Any, Any, bool]:
    """``core.convert(cloud)``, or (None, the reason, False) for a cloud that has no grid."""
    from lidarscan.errors import LidarScanError

    try:
        return core.convert(cloud)  # type: ignore[no-any-return]
    except LidarScanError as err:
        return None, err, False


def _cloud_extrinsics(cloud: Any, args: argparse.Namespace, tf: Any, fallback: Any) -> Any:
    """``--frame`` <- the cloud's frame from the file's TF at the cloud's stamp, else
    ``--extrinsics``; None without ``--frame`` (raises TransformLookupError naming --frame)."""
    import numpy as np

    from converters.nodes.tf import TransformLookupError
    from lidarscan.stamps import to_ns

    source = str(cloud.header.frame_id)
    if not args.frame or args.frame == source:
        return None
    try:
        return tf.lookup(args.frame, source, to_ns(cloud.header.stamp))
    except TransformLookupError as err:
        if fallback is not None:
            return np.asarray(fallback)
        raise TransformLookupError(
            "--frame", args.frame, f"a transform {args.frame} <- {source} in the file's /tf or "
            f"/tf_static, or --extrinsics ({err})") from err


def _decoder_options(args: argparse.Namespace, decoders: dict[str, Any]) -> dict[str, Any]:
    """Keyword options of the packet decoders from the command line (``--cut-angle``), checked
    against every decoder that will get them (before anything is written)."""
    if args.cut_angle is None:
        return {}
    import inspect
    import math

    from lidarscan.errors import ConfigError

    if not decoders:
        raise ConfigError("--cut-angle", args.cut_angle, "a recording of raw packets")
    for topic, decoder in sorted(decoders.items()):
        if "cut_angle_deg" not in inspect.signature(decoder).parameters:
            raise ConfigError("--cut-angle", args.cut_angle,
                              f"packets whose decoder takes a cut angle (Velodyne); topic "
                              f"{topic} is decoded by {decoder.__module__}, which has none")
    if not math.isfinite(args.cut_angle):
        raise ConfigError("--cut-angle", args.cut_angle, "a finite angle in degrees")
    return {"cut_angle_deg": args.cut_angle}


def _packet_decoders(topics: dict[str, str]) -> dict[str, Any]:
    """topic -> PacketDecoder class for every packet topic; a clear error when this
    installation has no decoder for one of them (before anything is written)."""
    import importlib

    from converters.bags import PACKET_TYPES
    from lidarscan.errors import ConversionError

    out: dict[str, Any] = {}
    for topic, msgtype in sorted(topics.items()):
        if msgtype not in PACKET_TYPES:
            continue
        module_name = PACKET_TYPES[msgtype][0]
        try:
            module: Any = importlib.import_module(module_name)
            why = f"{module_name} has no PacketDecoder"
        except ImportError as err:
            module, why = None, f"{module_name} cannot be imported: {err}"
        decoder = getattr(module, "PacketDecoder", None)
        if decoder is None:
            raise ConversionError(f"topic {topic}", msgtype, "a message type this installation "
                                  "can decode", hint=f"no decoder for {msgtype} in this "
                                  f"installation: {why}")
        out[topic] = decoder
    return out


def _convert_packets(source: _Input, writer: Any, args: argparse.Namespace, plan: _Plan,
                     decoders: dict[str, Any], slices: Sequence[Any], fallback: Any,
                     report: ConvertReport, emit: Callable[[str], None],
                     progress: Progress) -> None:
    """Raw sensor packets (VelodyneScan / PandarScan) -> per packet topic a latched
    ``<topic>/lidar_info`` (each version written once, before its first scan) and
    ``<topic>/lidar_scan`` (+ the requested outputs); other messages are copied, the packets
    only with ``--keep-packets``."""
    from converters.bags import PACKET_TYPES, register_packet_types
    from converters.nodes.tf import TransformBuffer
    from lidarscan.errors import LidarScanError
    from lidarscan.stamps import to_ns

    register_packet_types()
    tf = TransformBuffer(cache_ns=3600 * 10**9, max_per_edge=100_000)
    pipeline = _ScanPipeline(args, slices, fallback, tf)
    merge = _merge_sink(args, plan, tf, writer)
    active: dict[str, Any] = {}
    info_written: dict[str, int] = {}

    def emit_scans(topic: str, pairs: list[Any], log_time_ns: int, index: int) -> None:
        prefix = plan.prefix[topic]
        for scan, info in pairs:
            stamp = to_ns(info.header.stamp)
            if info_written.get(topic) != stamp:
                writer.write(f"{prefix}/lidar_info", info, log_time_ns=log_time_ns)
                info_written[topic] = stamp
            writer.write(f"{prefix}/lidar_scan", scan, log_time_ns=log_time_ns)
            if args.pointcloud2 or slices:
                try:
                    pipeline.outputs(scan, info, topic, prefix, log_time_ns, writer, report,
                                     merge, emit)
                except LidarScanError as err:
                    pipeline.failed(err, index, topic, to_ns(scan.header.stamp), report, emit)
            else:
                report.converted += 1

    last: dict[str, tuple[int, int]] = {}
    for item in report.good(source.items(progress), emit):
        try:
            _side_input(item, tf, args, merge)
        except LidarScanError as err:
            report.report_bad(item.index, item.topic, item.log_time_ns, str(err), emit)
            continue
        if item.topic in decoders:
            try:
                packets = PACKET_TYPES[item.msgtype][1](item.payload)
            except LidarScanError as err:
                report.report_bad(item.index, item.topic, item.log_time_ns, str(err), emit)
                continue
            decoder = active.get(item.topic)
            if decoder is None:  # built on first use: the frame comes from the messages
                decoder = decoders[item.topic](args.calibration,
                                               frame_id=packets.frame_id or "lidar")
                active[item.topic] = decoder
            payloads = packets.payloads
            if payloads is not None and hasattr(decoder, "push_many"):
                # one batch per message (the contract's optional fast path), bad rows skipped
                bad: list[tuple[int, Any]] = []
                done = decoder.push_many(packets.stamps, payloads, errors=bad)
                for k, err in bad:
                    report.report_bad(item.index, item.topic, item.log_time_ns,
                                      f"packet {k} of {len(packets.stamps)}: {err}", emit)
                emit_scans(item.topic, done, item.log_time_ns, item.index)
            else:                               # PandarScan packets of mixed sizes
                for k, (stamp, payload) in enumerate(packets.packets):
                    try:
                        done = decoder.push(stamp, payload)
                    except LidarScanError as err:
                        report.report_bad(item.index, item.topic, item.log_time_ns,
                                          f"packet {k} of {len(packets.stamps)}: {err}", emit)
                        continue
                    emit_scans(item.topic, done, item.log_time_ns, item.index)
            last[item.topic] = (item.log_time_ns, item.index)
            if not args.keep_packets:
                continue
        _copy(writer, item, plan, report)
    for topic, decoder in active.items():
        log_time, index = last.get(topic, (0, -1))
        emit_scans(topic, decoder.flush(), log_time, index)
    pipeline.finish()


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
            pipeline.outputs(scan, info, "/lidar/scan", "/lidar", stamp, writer, report,
                             lambda name, msg, log: None, emit)
        except LidarScanError as err:
            pipeline.failed(err, index, "/lidar/scan", stamp, report, emit)
    pipeline.finish()


# ------------------------------------------------------------------------------------ view

def cmd_view(args: argparse.Namespace) -> int:
    import numpy as np

    from converters import viz
    from converters.nodes.tf import TransformBuffer, TransformLookupError
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
    for item in source.items():
        if isinstance(item, BadMessage):
            note_damage(item)
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
    for item in damage.values():
        _err(_describe_bad(item))
    if not written:
        _err(f"{path} ({source.kind.description}): nothing to draw (no LidarScan with its "
             f"LidarInfo, LaserScan or PointCloud2 at index {args.index}"
             + (", and the input is damaged" if damage else "") + ")")
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


# ---------------------------------------------------------------------------------- parser

def build_parser() -> argparse.ArgumentParser:
    """The argparse parser of ``lidarscan``."""
    parser = argparse.ArgumentParser(
        prog="lidarscan",
        description="Structured lidar scans (LidarScan + LidarInfo) for ROS 2: demo, inspect, "
                    "convert and draw MCAP recordings.")
    parser.add_argument("--version", action="version", version=f"lidarscan {_version()}")
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
                       description="Summarise a recording (MCAP, rosbag2 directory or .db3); "
                                   "exit status 1 if it has problems (bad messages, damaged "
                                   "parts, unlinked scans, conflicting infos, a topic whose "
                                   "frame, shape or type changes).")
    p.add_argument("file", help="an MCAP file, a rosbag2 directory or a .db3 file")
    p.set_defaults(func=cmd_info)

    p = sub.add_parser(
        "convert", help="offline conversion of a recording",
        description="IN is an MCAP file, a rosbag2 directory or .db3 file, or an Ouster "
                    ".pcap/.osf. LidarScan recording: copy every message and add PointCloud2 "
                    "(<ns>/points), slices (<ns>/slices/NAME) and a merged scan. Driver "
                    "PointCloud2 (no LidarScan in it): convert the organized clouds to "
                    "<ns>/lidar_scan + <ns>/lidar_info; with --slice, every cloud (any "
                    "layout, grid or not, e.g. Livox) also gives <ns>/slices/NAME from its "
                    "points, and a cloud without a grid gives only those. Raw packets "
                    "(velodyne_msgs/VelodyneScan, pandar_msgs/PandarScan): <topic>/lidar_info + "
                    "<topic>/lidar_scan (+ outputs). An Ouster .pcap/.osf (needs ouster-sdk): "
                    "/lidar/info + /lidar/scan (+ outputs). Copied topics keep their channel "
                    "metadata (QoS). Bad messages and damaged parts of IN are reported on "
                    "stderr; every good message is written. OUT is written under a temporary "
                    "name and renamed at the end. Exit status 0 all good, 1 some bad, 2 fatal "
                    "(nothing written), 130 Ctrl-C (OUT stays readable).")
    p.add_argument("input", help="input recording (.mcap, rosbag2 directory or .db3, "
                                 ".pcap/.osf with --metadata)")
    p.add_argument("output", help="output MCAP file")
    p.add_argument("--pointcloud2", action="store_true", help="add PointCloud2 per scan")
    p.add_argument("--preset", default="", type=_preset, help="PointCloud2 field preset")
    p.add_argument("--fields", default=(), type=_fields,
                   help="PointCloud2 fields, e.g. x,y,z,intensity")
    p.add_argument("--slice", action="append", default=[], metavar="NAME:ZMIN:ZMAX[:KEY=V]",
                   help="add a LaserScan height slice (repeatable), heights in --frame; "
                        "negative obstacles (holes) with the keys holes, floor_height=M, "
                        "hole_depth=M, hole_range_max=M, hole_no_return=false, e.g. "
                        "floor:0.05:0.5:holes:floor_height=0 (LidarScans and clouds with a "
                        "grid; a cloud without one has no rays to see a hole along)")
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
    p.add_argument("--replace", action="store_true",
                   help="drop the input topics an output is written to (default: refuse)")
    p.add_argument("--calibration", default=None, metavar="FILE",
                   help="sensor calibration for raw packets (Velodyne YAML, Hesai CSV); "
                        "default: the model's nominal one where it exists")
    p.add_argument("--cut-angle", type=float, default=None, metavar="DEG",
                   help="raw Velodyne packets: packet azimuth (degrees, clockwise, the packets' "
                        "own convention) where a rotation starts; default 0. Put it in the "
                        "blind part of a restricted field of view (e.g. 180 for a front "
                        "sensor seeing 270..90) so no scan is split")
    p.add_argument("--keep-packets", action="store_true",
                   help="also copy the input packet messages")
    p.add_argument("--progress", action="store_true",
                   help="report progress also when stderr is not a terminal")
    p.add_argument("--metadata", default=None, help="Ouster metadata JSON for a .pcap")
    p.add_argument("--max-pending", type=_positive_int, default=64,
                   help="scans held while waiting for their LidarInfo (64)")
    p.add_argument("--compress", action="store_true",
                   help="write every LidarScan compressed by lidarscan.codec (MCAP message "
                        "encoding 'lidarscan.codec', lossless; readable by lidarscan, not by "
                        "ros2 bag play: convert again without --compress to get CDR back)")
    p.add_argument("--chunk-compression", "--compression", dest="compression",
                   choices=("zstd", "lz4", "none"), default="zstd",
                   help="compression of the output MCAP's chunks (zstd; lz4 is faster to "
                        "write and larger, see bench/README.md)")
    p.add_argument("--zstd-level", type=_zstd_level, default=None, metavar="N",
                   help="zstd level of the chunks: 1 (default, fast), up to 22 for smaller "
                        "files, negative for faster and larger")
    p.add_argument("-q", "--quiet", action="store_true",
                   help="no progress bar, notes or summary (bad messages are still listed)")
    p.set_defaults(func=cmd_convert)

    p = sub.add_parser("view", help="PNG views of a recording (MCAP or rosbag2)",
                       description="Range images of a LidarScan, a top view of the LaserScans "
                                   "(in --frame via the file's TF) and of each PointCloud2.")
    p.add_argument("file", help="an MCAP file, a rosbag2 directory or a .db3 file")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--index", type=_non_negative_int, default=0,
                   help="which scan of each topic (0 = first)")
    p.add_argument("--frame", default="", help="frame of the LaserScan top view")
    p.set_defaults(func=cmd_view)
    return parser


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("lidarscan")
    except Exception:  # noqa: BLE001 - not installed as a distribution (source tree)
        return "unknown (not installed)"


def _preset(text: str) -> str:
    from converters.pointcloud2 import PRESETS

    if text and text not in PRESETS:
        raise argparse.ArgumentTypeError(f"{text!r}: expected one of {', '.join(sorted(PRESETS))}")
    return text


def _fields(text: str) -> tuple[str, ...]:
    names = tuple(f.strip() for f in text.split(",") if f.strip())
    if len(set(names)) != len(names):
        raise argparse.ArgumentTypeError(f"{text!r}: expected unique field names")
    if not {"x", "y", "z"} <= set(names):
        raise argparse.ArgumentTypeError(f"{text!r}: expected x, y and z among the fields")
    return names


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: expected an integer >= 1")
    return value


def _zstd_level(text: str) -> int:
    value = int(text)
    if not -131072 <= value <= 22:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a zstd level from -131072 to 22")
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
    if getattr(args, "preset", "") and getattr(args, "fields", ()):
        parser.error("--preset and --fields: give one of them (a preset fixes the fields)")
    try:
        return int(args.func(args))
    except KeyboardInterrupt:
        _err("interrupted")
        return EXIT_INTERRUPTED
    except LidarScanError as err:
        _err(f"lidarscan {args.command}: error: {err}")
        return EXIT_FATAL
    except ModuleNotFoundError as err:    # an extra or a message package not installed
        from lidarscan._install import missing_module_hint
        _err(f"lidarscan {args.command}: error: "
             f"{missing_module_hint(err, f'lidarscan {args.command}')}")
        return EXIT_FATAL
    except (OSError, ImportError) as err:
        _err(f"lidarscan {args.command}: error: {err}")
        return EXIT_FATAL


if __name__ == "__main__":
    sys.exit(main())
