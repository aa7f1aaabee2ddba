"""``lidarscan convert``: checks of the options and the input (before anything is written),
the output topics, the output file (temporary name, renamed at the end) and the summary; the
per-input conversions are in :mod:`converters.edge.cli.convert_inputs`."""

from __future__ import annotations

import argparse
import contextlib
import sys
from collections.abc import Iterator, Sequence
from typing import Any

from converters.edge.cli._common import (
    EXIT_BAD,
    EXIT_INTERRUPTED,
    EXIT_OK,
    Progress,
    _err,
    _namespace,
    _open_input,
    codec_coder,
)
from converters.edge.cli.convert_inputs import (
    _convert_clouds,
    _convert_ouster,
    _convert_packets,
    _convert_scans,
    _takes,
)
from converters.edge.cli._interrupt import StopRequest, is_interrupt
from converters.edge.cli.convert_checks import (check_option_files, output_of,
                                                refuse_unfit_options)
from converters.edge.cli.convert_filters import (
    RenamingWriter,
    check_renames,
    parse_renames,
    selection_of,
)
from converters.edge.cli.convert_pipeline import ConvertReport, _Plan


_TRUE, _FALSE = ("1", "true", "yes", "on"), ("0", "false", "no", "off")
#: the interpreter's GIL switch interval (s) while ``convert`` runs with threads (Python's
#: default is 5 ms): the reading and output threads take the GIL for short moments between
#: their sqlite reads, zstd and file writes, and the converting thread gives it up in every
#: ctypes call and numpy loop; a thread that asks for it back waits up to one interval
#: (bench/README.md, bench_convert: the converting thread's waits)
GIL_SWITCH_S = 0.001


def parse_slice(text: str) -> Any:
    """``NAME:ZMIN:ZMAX[:KEY[=VALUE]]...`` -> :class:`converters.edge.nodes.params.SliceConfig`.

    KEYs are the hole options of a slice (:data:`converters.shared.options.HOLE_KEYS`): ``holes``
    (alone: on), ``floor_height`` (metres, in --frame), ``hole_depth`` (metres, > 0),
    ``hole_range_max`` (metres, > 0, ``inf``), ``hole_no_return`` (true/false), e.g.
    ``floor:0.05:0.5:holes:floor_height=0:hole_depth=0.08``.

    Raises:
        ConfigError: naming the bad part of ``text`` and what was expected.
    """
    from converters.edge.nodes.params import SliceConfig, parse_slice_arg
    from converters.shared.options import HOLE_KEYS, number
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


def _prefixes(inputs: Sequence[str]) -> dict[str, str]:
    """Each input's output namespace: its own namespace when no other input shares it, else the
    input topic itself (so outputs of different inputs never share a topic)."""
    shared: dict[str, int] = {}
    for topic in inputs:
        shared[_namespace(topic)] = shared.get(_namespace(topic), 0) + 1
    return {t: _namespace(t) if shared[_namespace(t)] == 1 else t for t in inputs}


def _listing(topics: dict[str, str]) -> str:
    return ", ".join(f"{t} ({k})" for t, k in sorted(topics.items())) or "no topics"


def _check_input_topics(topics: dict[str, str], args: argparse.Namespace) -> None:
    """Refuses (exit 2) an input-topic option naming a topic IN does not have with that type."""
    from lidarscan.errors import ConfigError

    for option, wanted, names in (("--cloud-topic", "sensor_msgs/msg/PointCloud2",
                                   args.cloud_topic),
                                  ("--merge-topic", "sensor_msgs/msg/LaserScan",
                                   args.merge_topic)):
        for name in names or ():
            if topics.get(name) != wanted:
                have = sorted(t for t, k in topics.items() if k == wanted)
                raise ConfigError(option, name, f"a {wanted} topic of IN (it has "
                                  f"{', '.join(have) or 'none'})")


def _plan(topics: dict[str, str], args: argparse.Namespace, slices: Sequence[Any],
          mode: str) -> _Plan:
    """The output topics; refuses (exit 2) an output topic the input already has unless it is
    excluded (``--exclude TOPIC`` or ``--replace``)."""
    from converters.sources.bags import is_packet_topic
    from lidarscan.errors import ConfigError
    from lidarscan.mcap import SCAN_TYPE

    plan = _Plan(excluded=set(args.exclude))
    if mode != "ouster":
        _check_input_topics(topics, args)
    if mode == "packets":
        sources = [t for t, k in topics.items() if is_packet_topic(t, k)]
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
    if mode == "scans" and not sources and per:
        asked = "--pointcloud2" if args.pointcloud2 else "--slice"
        raise ConfigError(asked, True, "a recording with LidarScan, lidar packet or "
                          f"PointCloud2 topics to make it from (IN has {_listing(topics)})")
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
    """``lidarscan convert``; Ctrl-C stops it between messages (:mod:`._interrupt`)."""
    with StopRequest() as stop:
        return _convert(args, stop)


def _convert(args: argparse.Namespace, stop: StopRequest) -> int:
    from lidarscan.errors import ConfigError, McapFormatError
    from lidarscan.mcap import CODEC_ENCODING, SCAN_TYPE

    source = _open_input(args.input, "IN", ouster=True)
    source.ahead = args.threads > 1     # --threads 1: everything in one thread
    source.stop = stop
    src = source.path
    output = output_of(args.output, src)
    dst = output.path
    from converters.edge.nodes.params import parse_extrinsics

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
    check_option_files(args)
    selection = selection_of(args)
    renames = parse_renames(args.rename_topic)
    topics: dict[str, str] = {}
    mode = "ouster"
    if source.kind.kind == "ouster" and selection.topics:
        raise ConfigError("--topics", ",".join(selection.topics), "a recording with topics "
                          "(IN is an Ouster .pcap/.osf: its scans go to /lidar/info and "
                          "/lidar/scan)")
    if source.kind.kind != "ouster":
        from converters.sources.bags import is_packet_topic

        topics = selection.select_topics(source.topics())
        source.keep = selection.keep if selection.active else None
        kinds = set(topics.values())
        if any(is_packet_topic(t, k) for t, k in topics.items()):
            mode = "packets"
        elif SCAN_TYPE not in kinds and "sensor_msgs/msg/PointCloud2" in kinds:
            mode = "clouds"
        else:
            mode = "scans"
    refuse_unfit_options(args, mode, slices, topics)
    plan = _plan(topics, args, slices, mode)
    if renames:
        check_renames(renames, _written_topics(topics, plan, args, slices, mode))
    decoders = _packet_decoders(topics) if mode == "packets" else {}
    for topic, msgtype in topics.items():
        if topic in decoders and msgtype in _ouster_packet_types():
            from converters.edge.cli.convert_inputs import ouster_decoder, ouster_metadata

            decoders[topic] = ouster_decoder(ouster_metadata(source, topic, args.metadata))
    decoder_options = _decoder_options(args, decoders)
    if decoder_options:
        import functools
        decoders = {t: functools.partial(d, **decoder_options) for t, d in decoders.items()}
    report = ConvertReport()
    emit = _err  # bad messages are always reported, also with --quiet
    writer = output.writer(compression=args.compression, chunk_size=1 << 20,
                           level=args.zstd_level, threads=args.threads,
                           scan_encoding=CODEC_ENCODING if args.compress else "cdr",
                           # the compiled coder (numba: ~0.4 s to import) only where a scan may
                           # be coded: --compress, or LidarScans that may come codec-compressed
                           codec_coder=codec_coder() if args.compress
                           or SCAN_TYPE in topics.values() else None)
    if renames:
        writer = RenamingWriter(writer, renames)
    size = sum(f.stat().st_size for f in source.bag.files) if source.bag else src.stat().st_size
    # a fleet run (converters.edge.cli.fleet) passes its own progress and takes the counters
    progress = getattr(args, "make_progress", Progress)(
        size, f"converting {src.name}",
        enabled=True if args.progress else (None if not args.quiet else False))
    interrupted = finished = False
    switch = sys.getswitchinterval()
    if args.threads > 1:    # see GIL_SWITCH_S
        sys.setswitchinterval(min(switch, GIL_SWITCH_S))
    try:
        try:
            if mode == "ouster":
                _convert_ouster(src, writer, args, slices, fallback, report, emit, stop,
                                selection.keep_time)
            elif mode == "packets":
                with _calibration_flag(args, decoders):
                    _convert_packets(source, writer, args, plan, decoders, slices, fallback,
                                     report, emit, progress)
            elif mode == "clouds":
                _convert_clouds(source, writer, args, plan, slices, fallback, report, emit,
                                progress)
            else:
                _convert_scans(source, writer, args, plan, slices, fallback, report, emit,
                               progress)
        except (KeyboardInterrupt, SystemError) as err:   # a second Ctrl-C
            if not is_interrupt(err):
                raise
            interrupted = True
        finally:
            progress.close()
            try:
                writer.close()
            finally:
                sys.setswitchinterval(switch)
        interrupted = interrupted or stop()
        if not interrupted and report.read == 0 and report.bad:
            raise McapFormatError(f"IN {src}", f"{len(report.bad)} damaged part(s), listed above",
                                  "at least one readable message; nothing written")
        output.finish()
        finished = True
    finally:
        if not finished:
            output.discard()
    stats = getattr(args, "stats", None)
    if stats is not None:
        stats.update(read=report.read, written=writer.count, bad=len(report.bad))
    if interrupted:
        _err(f"interrupted: {dst} is a valid {'rosbag2 folder' if output.bag else 'MCAP file'}"
             f" with the {writer.count} messages written so far ({report.read} read)")
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


def _ouster_packet_types() -> tuple[str, ...]:
    from converters.sources.bags import OUSTER_PACKET_TYPES

    return OUSTER_PACKET_TYPES


def _written_topics(topics: dict[str, str], plan: _Plan, args: argparse.Namespace,
                    slices: Sequence[Any], mode: str) -> set[str]:
    """The topics the output will have (before ``--rename-topic``): the copied input topics
    and the new ones."""
    from converters.sources.bags import is_packet_topic

    copied = {t for t, k in topics.items() if t not in plan.excluded
              and not (is_packet_topic(t, k) and not args.keep_packets)
              and not (mode == "clouds" and t in plan.prefix and not args.keep_clouds)}
    if mode == "ouster":
        copied = {"/lidar/info", "/lidar/scan"} | ({"/lidar/points"} if args.pointcloud2
                                                  else set())
        copied |= {f"/lidar/slices/{s.name}" for s in slices}
    return copied | set(plan.outputs)


@contextlib.contextmanager
def _calibration_flag(args: argparse.Namespace, decoders: dict[str, Any]) -> Iterator[None]:
    """A decoder's calibration error restated with the option and the file: "no calibration"
    (a model without a nominal one) names ``--calibration FILE`` and the file it expects; an
    error of the given file names it and the format expected (a Velodyne YAML, a Hesai CSV),
    on one line."""
    from lidarscan.errors import ConfigError, LidarScanError

    try:
        yield
    except LidarScanError as err:
        if not err.field.startswith("calibration"):
            raise
        if args.calibration is None:
            if not isinstance(err, ConfigError) or err.field != "calibration":
                raise
            raise ConfigError("--calibration", "not given", err.expected,
                              hint="give the file with --calibration FILE") from err
        modules = " ".join(getattr(d, "__module__", "") for d in decoders.values())
        formats = (("velodyne", "a Velodyne calibration YAML (ros-drivers format)"),
                   ("hesai", "a Hesai angle-correction CSV"))
        kinds = [kind for word, kind in formats if word in modules]
        raise ConfigError("--calibration", args.calibration,
                          f"{' or '.join(kinds) or 'a calibration'} of the sensor that sent "
                          "these packets", hint=" ".join(str(err).split())) from err


def _decoder_options(args: argparse.Namespace, decoders: dict[str, Any]) -> dict[str, Any]:
    """Keyword options of the packet decoders from the command line (``--cut-angle``), checked
    against every decoder that will get them (before anything is written)."""
    if args.cut_angle is None:
        return {}
    import math

    from lidarscan.errors import ConfigError

    if not decoders:
        raise ConfigError("--cut-angle", args.cut_angle, "a recording of raw packets")
    for topic, decoder in sorted(decoders.items()):
        if not _takes(decoder, "cut_angle_deg"):
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

    from converters.sources.bags import PACKET_TYPES, is_packet_topic
    from lidarscan.errors import ConversionError

    out: dict[str, Any] = {}
    for topic, msgtype in sorted(topics.items()):
        if not is_packet_topic(topic, msgtype):
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
