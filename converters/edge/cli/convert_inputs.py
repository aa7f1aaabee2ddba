"""``lidarscan convert`` per kind of input: LidarScan recordings, driver PointCloud2, raw packets
(Velodyne, Hesai) and Ouster .pcap/.osf."""

from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from converters.edge.cli._common import Progress, _Input, _err, _namespace, decode_item
from converters.edge.cli.convert_pipeline import (
    ConvertReport,
    _Plan,
    _ScanPipeline,
    _copy,
    _drain_drops,
    _merge_sink,
    _side_input,
)


def _convert_scans(source: _Input, writer: Any, args: argparse.Namespace, plan: _Plan,
                   slices: Sequence[Any], fallback: Any, report: ConvertReport,
                   emit: Callable[[str], None], progress: Progress) -> None:
    """LidarScan recording: copy every good message, add the requested outputs."""
    from converters.edge.nodes.tf import TransformBuffer
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
                msg = decode_item(item)
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


def _convert_clouds(source: _Input, writer: Any, args: argparse.Namespace, plan: _Plan,
                    slices: Sequence[Any], fallback: Any, report: ConvertReport,
                    emit: Callable[[str], None], progress: Progress) -> None:
    """Driver PointCloud2 recording -> LidarScan + LidarInfo (a new info only on change); with
    ``--slice``, every cloud's slices from its points (any cloud, grid or not:
    :class:`converters.edge.nodes.cloud_to_scan_node.CloudSlicer`), and a cloud without a grid
    gives its slices instead of failing (said once per topic). A slice with holes needs rays:
    then every slice comes from the cloud's LidarScan (as for a LidarScan recording), and a
    topic none of whose clouds has a grid is a usage error (exit 2)."""
    from converters.edge.nodes.cloud_to_scan_node import CloudSlicer, CloudToScanCore
    from converters.edge.nodes.tf import TransformBuffer
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

    from converters.edge.nodes.tf import TransformLookupError
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


def _convert_packets(source: _Input, writer: Any, args: argparse.Namespace, plan: _Plan,
                     decoders: dict[str, Any], slices: Sequence[Any], fallback: Any,
                     report: ConvertReport, emit: Callable[[str], None],
                     progress: Progress) -> None:
    """Raw sensor packets (VelodyneScan / PandarScan) -> per packet topic a latched
    ``<topic>/lidar_info`` (each version written once, before its first scan) and
    ``<topic>/lidar_scan`` (+ the requested outputs); other messages are copied, the packets
    only with ``--keep-packets``. A ConfigError of a decoder (a calibration of another
    model: no packet can be decoded with it) stops the run (exit 2, nothing written)."""
    from converters.sources.bags import PACKET_TYPES, register_packet_types
    from converters.edge.nodes.tf import TransformBuffer
    from lidarscan.errors import ConfigError, LidarScanError
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

    def parse(item: Any) -> Any:    # in the reading thread
        if item.topic not in decoders:
            return None
        packets = PACKET_TYPES[item.msgtype][1](item.payload)
        packets.payloads  # noqa: B018 - computed (and kept) here, not in the converting thread
        return packets

    last: dict[str, tuple[int, int]] = {}
    for item, packets in report.good(source.items(progress, prepare=parse), emit):
        try:
            _side_input(item, tf, args, merge)
        except LidarScanError as err:
            report.report_bad(item.index, item.topic, item.log_time_ns, str(err), emit)
            continue
        if item.topic in decoders:
            if isinstance(packets, LidarScanError):
                report.report_bad(item.index, item.topic, item.log_time_ns, str(packets), emit)
                continue
            decoder = active.get(item.topic)
            if decoder is None:  # built on first use: the frame comes from the messages
                decoder = decoders[item.topic](args.calibration,
                                               frame_id=packets.frame_id or "lidar",
                                               **_dataclass_option(decoders[item.topic]),
                                               **_firetimes_option(decoders[item.topic], args))
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
                    except ConfigError:
                        raise
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


def _takes(decoder: Any, keyword: str) -> bool:
    """Whether the decoder class (or partial) ``decoder`` takes the keyword argument."""
    import inspect

    try:
        return keyword in inspect.signature(decoder).parameters
    except (TypeError, ValueError):
        return False


def _dataclass_option(decoder: Any) -> dict[str, Any]:
    """``as_dataclass=True`` for a decoder that takes it: its scans are then
    :mod:`lidarscan.types` dataclasses over the decoder's read-only data block, which the
    writer serialises without building an rclpy message or copying the block."""
    return {"as_dataclass": True} if _takes(decoder, "as_dataclass") else {}


def _firetimes_option(decoder: Any, args: argparse.Namespace) -> dict[str, Any]:
    """``firetimes=`` (``--firetimes``) for a decoder that takes it (Hesai); a ConfigError for
    one that does not."""
    firetimes = getattr(args, "firetimes", None)
    if firetimes is None:
        return {}
    from lidarscan.errors import ConfigError

    if not _takes(decoder, "firetimes"):
        raise ConfigError("--firetimes", firetimes, "packets whose decoder takes a firetime "
                          "correction file (Hesai)")
    return {"firetimes": firetimes}


def _convert_ouster(src: Path, writer: Any, args: argparse.Namespace, slices: Sequence[Any],
                    fallback: Any, report: ConvertReport, emit: Callable[[str], None]) -> None:
    """Ouster pcap/OSF (via ouster-sdk) -> LidarInfo + LidarScan (+ the requested outputs)."""
    from converters.edge.nodes.tf import TransformBuffer
    from converters.sources.ouster.metadata import scans_from_recording
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
