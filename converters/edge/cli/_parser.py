"""The argparse parser of ``lidarscan`` and its value checks."""

from __future__ import annotations

import argparse
from typing import Any

from converters.edge.cli._argtypes import _non_negative_int, _positive_int
from converters.edge.cli._examples import EXAMPLES, HelpFormatter
from converters.edge.cli.demo import cmd_demo
from converters.edge.cli.fleet import add_options as add_fleet_options
from converters.edge.cli.fleet import cmd_convert_many
from converters.edge.cli.info import cmd_info
from converters.edge.cli.view import cmd_view


def build_parser() -> argparse.ArgumentParser:
    """The argparse parser of ``lidarscan``."""
    parser = argparse.ArgumentParser(
        prog="lidarscan",
        description="Structured lidar scans (LidarScan + LidarInfo) for ROS 2: demo, inspect, "
                    "convert and draw MCAP recordings.")
    parser.add_argument("--version", action="version", version=f"lidarscan {_version()}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser(
        "demo", formatter_class=HelpFormatter, epilog=EXAMPLES["demo"],
        help="simulate a robot in a room (3D + 2D lidar, depth camera), convert, "
             "record and draw",
        description="Simulated robot with a 3D lidar (real Ouster OS-1-128 geometry), a 2D "
                    "lidar and a depth camera (424x240 16UC1) in a room with a table, an "
                    "overhanging shelf and a stairwell going down. Converts every frame "
                    "(PointCloud2, height slices, the camera's slice with hole detection: the "
                    "stairwell's edge is an obstacle no lidar band sees, the merged scan) and "
                    "writes DIR/demo.mcap and PNG views (range_image, birdseye_slices, "
                    "merged_scan, depth_camera, pointcloud_topview).")
    p.add_argument("--out", default="demo_out", help="output folder (default: ./demo_out)")
    p.add_argument("--frames", type=_positive_int, default=10, help="frames at 10 Hz (10)")
    p.add_argument("--no-images", action="store_true", help="skip the PNG views")
    p.add_argument("--noise", type=float, default=0.0, metavar="M",
                   help="range noise of the 3D lidar, metres (0: exact)")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("info", formatter_class=HelpFormatter, epilog=EXAMPLES["info"],
                       help="topics, types, counts, LidarInfo versions, linkage",
                       description="Summarise a recording (MCAP, rosbag2 directory or .db3); "
                                   "exit status 1 if it has problems (bad messages, damaged "
                                   "parts, unlinked scans, conflicting infos, a topic whose "
                                   "frame, shape or type changes).")
    p.add_argument("file", metavar="REC", help="an MCAP file, a rosbag2 directory or a .db3 "
                                               "file, or an Ouster .pcap/.osf")
    p.add_argument("--metadata", default=None, metavar="FILE",
                   help="Ouster metadata JSON for a .pcap (as for convert)")
    p.set_defaults(func=cmd_info)

    p = sub.add_parser(
        "convert", formatter_class=HelpFormatter, epilog=EXAMPLES["convert"],
        help="offline conversion of a recording",
        usage="lidarscan convert [-h] [options] IN OUT",  # a usage error: two lines, not 15
        description="IN is an MCAP file, a rosbag2 directory or .db3 file, or an Ouster "
                    ".pcap/.osf. LidarScan recording: copy every message and add PointCloud2 "
                    "(<ns>/points), slices (<ns>/slices/NAME) and a merged scan. Driver "
                    "PointCloud2 (no LidarScan in it): convert the organized clouds to "
                    "<ns>/lidar_scan + <ns>/lidar_info; with --slice, every cloud (any "
                    "layout, grid or not, e.g. Livox) also gives <ns>/slices/NAME from its "
                    "points, and a cloud without a grid gives only those. Raw packets "
                    "(velodyne_msgs/VelodyneScan, pandar_msgs/PandarScan, ouster-ros PacketMsg with "
                    "its /ouster/metadata or --metadata): <topic>/lidar_info + "
                    "<topic>/lidar_scan (+ outputs). An Ouster .pcap/.pcapng (with --metadata "
                    "or the .json next to it) or .osf (needs ouster-sdk): "
                    "/lidar/info + /lidar/scan (+ outputs). Copied topics keep their channel "
                    "metadata (QoS). Bad messages and damaged parts of IN are reported on "
                    "stderr; every good message is written. OUT is written under a temporary "
                    "name and renamed at the end. Exit status 0 all good, 1 some bad, 2 fatal "
                    "(nothing written), 130 Ctrl-C (OUT stays readable).")
    p.add_argument("input", metavar="IN", nargs="+",
                   help="input recording (.mcap, rosbag2 directory or .db3, .pcap/.pcapng/.osf "
                        "with --metadata); several, a folder of recordings or a quoted glob: "
                        "each converted into the folder OUT (README, 'Converting many "
                        "recordings')")
    p.add_argument("output", metavar="OUT", help="output: an MCAP file (a new name, not IN), "
                   "or a folder (OUT/ or an existing empty one) for a rosbag2 bag with MCAP "
                   "storage and metadata.yaml (.db3 is refused: not written); the folder of "
                   "the outputs for several recordings")
    p.add_argument("--pointcloud2", action="store_true", help="add PointCloud2 per scan")
    p.add_argument("--preset", default="", type=_preset,
                   help="PointCloud2 field preset: a driver's layout, e.g. ouster, velodyne, "
                        "hesai (a wrong name lists them all)")
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
    p.add_argument("--merge-out", default="/scan_merged", metavar="TOPIC",
                   help="topic of the merged scan (/scan_merged)")
    p.add_argument("--merge-increment", type=float, default=0.25, metavar="DEG",
                   help="merged scan angle increment, degrees (0.25)")
    p.add_argument("--merge-range-max", type=float, default=100.0, metavar="M",
                   help="merged scan range_max, metres (100)")
    p.add_argument("--cloud-topic", action="append", default=[], metavar="TOPIC",
                   help="PointCloud2 input topic to convert (repeatable; default: all)")
    p.add_argument("--topics", action="append", default=[], metavar="T1,T2",
                   help="read only these input topics (comma-separated, repeatable; default: "
                        "all); what is not read is neither copied nor converted (add /tf and "
                        "/tf_static when --frame needs them)")
    p.add_argument("--start", type=_time, default=None, metavar="TIME",
                   help="skip the messages logged before TIME (LidarInfo and /tf_static are "
                        "kept): seconds since the epoch (1713492677.46, as `info` prints), "
                        "nanoseconds (1713492677464078412ns, or 16+ digits), an ISO date "
                        "(2024-04-19T02:11:17.5Z; UTC without an offset) or +SECONDS after the "
                        "first message")
    p.add_argument("--end", type=_time, default=None, metavar="TIME",
                   help="skip the messages logged at or after TIME (same forms as --start)")
    p.add_argument("--rename-topic", action="append", default=[], metavar="OLD=NEW",
                   help="write the output topic OLD (copied or new) as NEW (repeatable)")
    p.add_argument("--keep-clouds", action="store_true",
                   help="also copy the input PointCloud2 messages")
    p.add_argument("--exclude", action="append", default=[], metavar="TOPIC",
                   help="do not copy this input topic (repeatable), e.g. to replace it")
    p.add_argument("--replace", action="store_true",
                   help="drop the input topics an output is written to (default: refuse)")
    p.add_argument("--calibration", default=None, metavar="FILE",
                   help="sensor calibration for raw packets (Velodyne YAML, Hesai CSV); "
                        "default: the model's nominal one where it exists")
    p.add_argument("--firetimes", default=None, metavar="FILE",
                   help="Hesai raw packets: the sensor model's firetime correction CSV "
                        "(per-pixel times on the 128 series); default: built-in tables")
    p.add_argument("--cut-angle", type=float, default=None, metavar="DEG",
                   help="raw Velodyne packets: packet azimuth (degrees, clockwise, the packets' "
                        "own convention) where a rotation starts; default 0. Put it in the "
                        "blind part of a restricted field of view (e.g. 180 for a front "
                        "sensor seeing 270..90) so no scan is split")
    p.add_argument("--keep-packets", action="store_true",
                   help="also copy the input packet messages")
    p.add_argument("--progress", action="store_true",
                   help="report progress also when stderr is not a terminal")
    p.add_argument("--metadata", default=None, metavar="FILE",
                   help="Ouster metadata JSON for a .pcap, or for ouster-ros packets "
                        "recorded without their /ouster/metadata")
    p.add_argument("--max-pending", type=_positive_int, default=64, metavar="N",
                   help="scans held while waiting for their LidarInfo (64)")
    p.add_argument("--compress", action="store_true",
                   help="(no value) write every LidarScan compressed by lidarscan.codec "
                        "(MCAP message encoding 'lidarscan.codec', lossless; readable by "
                        "lidarscan, not by ros2 bag play: convert again without --compress to "
                        "get CDR back)")
    p.add_argument("--chunk-compression", "--compression", dest="compression",
                   choices=("zstd", "lz4", "none"), default="zstd",
                   help="compression of the output MCAP's chunks (zstd; lz4 is faster to "
                        "write and larger, see bench/README.md)")
    p.add_argument("--zstd-level", type=_zstd_level, default=None, metavar="N",
                   help="zstd level of the chunks: 2 (default, fast; chunks of single-return "
                        "scans with a smaller hash table), up to 22 for smaller files, "
                        "negative for faster and larger")
    p.add_argument("--threads", type=int, choices=range(1, 17), default=3, metavar="N",
                   help="threads of the run (same output bytes for every N): 3 (default): "
                        "decoding in one, the output's chunks compressed by a second "
                        "(a third takes the backlog; written in order); 2: one thread compresses "
                        "and writes; with 2 or more, one more reads the input a few messages "
                        "ahead; 1: everything in one thread (reproducible CPU measurements)")
    p.add_argument("-q", "--quiet", action="store_true",
                   help="no progress bar, notes or summary (bad messages are still listed)")
    add_fleet_options(p)
    p.set_defaults(func=cmd_convert_many)

    p = sub.add_parser("view", formatter_class=HelpFormatter, epilog=EXAMPLES["view"],
                       help="PNG views of a recording (MCAP or rosbag2)",
                       description="Range images of a LidarScan, a top view of the LaserScans "
                                   "(in --frame via the file's TF) and of each PointCloud2.")
    p.add_argument("file", metavar="REC", help="an MCAP file, a rosbag2 directory or a .db3 file "
                                               "(raw packets: convert them first)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--index", type=_non_negative_int, default=None, metavar="K",
                   help="which scan of each topic (0 = first; default: the first complete "
                        "rotation, a scan covering as many columns as the next ones); a "
                        "partial rotation is marked in the image title")
    p.add_argument("--frame", default="",
                   help="frame of the LaserScan top view (default: base_link if known, else "
                        "the first LaserScan's)")
    p.set_defaults(func=cmd_view)
    return parser


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("lidarscan")
    except Exception:  # noqa: BLE001 - not installed as a distribution (source tree)
        return "unknown (not installed)"


def _preset(text: str) -> str:
    from converters.pointcloud2.converter import PRESETS

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


def _zstd_level(text: str) -> int:
    value = int(text)
    if not -131072 <= value <= 22:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a zstd level from -131072 to 22")
    return value


def _floats(text: str) -> list[float]:
    try:
        return [float(v) for v in text.replace(" ", ",").split(",") if v]
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"{text!r}: expected comma-separated numbers") from err


def _time(text: str) -> Any:
    """``--start``/``--end``: :func:`converters.edge.cli.convert_filters.parse_time`."""
    from converters.edge.cli.convert_filters import parse_time

    try:
        return parse_time(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
