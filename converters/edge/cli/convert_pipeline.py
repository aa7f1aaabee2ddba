"""What every ``convert`` input shares: the run's counters and bad-message reports, the output
topics, the per-scan outputs (PointCloud2, slices), ``--merge`` and copying messages."""

from __future__ import annotations

import argparse
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

from converters.edge.cli._common import _describe_bad, _fmt_stamp


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
        reader (a message, or a damaged part of the input) is reported. An item may come as
        an ``(item, value)`` tuple (``_Input.items(prepare=...)``): yielded as it is."""
        from lidarscan.mcap import BadMessage

        for entry in items:
            item = entry[0] if type(entry) is tuple else entry
            if not isinstance(item, BadMessage):
                self.read += 1
                yield entry
            else:
                self.bad.append((item.index, item.topic, item.log_time_ns, item.reason))
                emit(_describe_bad(item))


@dataclass
class _Plan:
    """Output topics of one run: where the outputs of each input topic go."""

    prefix: dict[str, str] = field(default_factory=dict)  # input topic -> output namespace
    outputs: dict[str, str] = field(default_factory=dict)  # output topic -> the input it is from
    excluded: set[str] = field(default_factory=set)


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
    from converters.edge.nodes.tf import TransformLookupError
    from lidarscan.errors import ConfigError

    if isinstance(err, TransformLookupError):
        return err  # it names --frame / --merge-topic and the transform it needs
    given = [f"--preset {args.preset}" if args.preset else "",
             f"--fields {','.join(args.fields)}" if args.fields else "",
             *[f"--slice {s}" for s in args.slice]]
    return ConfigError(" ".join(g for g in given if g) or "options", "",
                       f"options that fit the scans of {topic} ({err})")


def _is_option_error(err: Exception) -> bool:
    from converters.edge.nodes.tf import TransformLookupError
    from lidarscan.errors import ConfigError, UnknownChannelError

    return isinstance(err, (ConfigError, UnknownChannelError, TransformLookupError))


class _ScanPipeline:
    """Per linked (scan, info): PointCloud2, slices, merged scan; built lazily per info."""

    def __init__(self, args: argparse.Namespace, slices: Sequence[Any],
                 fallback: Any, tf_buffer: Any) -> None:
        from converters.edge.nodes.converter_node import ConverterCore

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

        from converters.edge.nodes.tf import TransformLookupError
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

        from converters.edge.nodes.tf import TransformLookupError

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
