"""``lidarscan convert``: options that do not fit the input (refused, exit 2, before anything is
written) and the kinds of output (an MCAP file or a rosbag2 folder with MCAP storage), each
written under a temporary name and renamed into place when the run ends."""

from __future__ import annotations

import argparse
import os
import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

#: what IN is, per conversion mode (for the refusals)
_WHAT_IN_IS = {"packets": "a recording of raw lidar packets",
               "clouds": "a recording of driver PointCloud2 (no raw packets)",
               "scans": "a recording of LidarScans (no raw packets)",
               "ouster": "an Ouster .pcap/.osf"}

#: output suffixes that name another storage format: never MCAP bytes under such a name
_OTHER_FORMATS = {".db3": "a rosbag2 sqlite3 file", ".bag": "a ROS 1 bag",
                  ".pcap": "a packet capture", ".osf": "an Ouster OSF file"}


def check_option_files(args: argparse.Namespace) -> None:
    """``--calibration`` and ``--metadata``, when given, name existing files (checked before
    anything is read or written).

    Raises:
        FileNotFoundError: naming the option and the path.
    """
    for option, value in (("--calibration", args.calibration), ("--metadata", args.metadata)):
        if value is not None and not Path(value).is_file():
            raise FileNotFoundError(f"{option} {value}: no such file")


def refuse_unfit_options(args: argparse.Namespace, mode: str, slices: Sequence[Any],
                         topics: dict[str, str]) -> None:
    """Raise ConfigError (exit 2) for an option that would be ignored: one for another kind of
    input (``mode``: "packets", "clouds", "scans" or "ouster"), one naming a topic IN does not
    have (``topics``: what is read of IN), or one that needs another option it was given
    without (or contradicts one)."""
    from lidarscan.errors import ConfigError

    what = _WHAT_IN_IS[mode]
    if args.progress and args.quiet:
        raise ConfigError("--progress", True, "one of --progress and -q (no progress)")
    for topic in args.exclude:
        if topic not in topics:
            raise ConfigError("--exclude", topic, "a topic read from IN (it has "
                              f"{', '.join(sorted(topics)) or 'none'})")
    if args.extrinsics is not None and not args.frame:
        raise ConfigError("--extrinsics", ",".join(f"{v:g}" for v in args.extrinsics),
                          "--frame FRAME too (the extrinsics are FRAME <- sensor, used where "
                          "the file's TF has no such transform)")
    if args.frame and not (slices or args.merge_topic):
        raise ConfigError("--frame", args.frame, "--slice or --merge-topic too (--frame is the "
                          "frame of the slices and of the merged scan; nothing else uses it)")
    by_mode = [("--calibration", args.calibration, ("packets",),
                "raw lidar packets (it is their Velodyne YAML or Hesai CSV)"),
               ("--firetimes", args.firetimes, ("packets",), "raw Hesai packets"),
               ("--keep-packets", args.keep_packets or None, ("packets",), "raw lidar packets"),
               ("--metadata", args.metadata, ("ouster", "ouster packets"),
                "an Ouster .pcap/.pcapng/.osf or Ouster packets (it is their metadata JSON)"),
               ("--keep-clouds", args.keep_clouds or None, ("clouds",),
                "driver PointCloud2 without LidarScans"),
               ("--cloud-topic", ",".join(args.cloud_topic) or None, ("clouds",),
                "driver PointCloud2 without LidarScans"),
               ("--pointcloud2", args.pointcloud2 or None, ("packets", "scans", "ouster"),
                ("LidarScans or raw packets (IN's clouds are PointCloud2 already: "
                 "--keep-clouds copies them)"))]
    from converters.sources.bags import OUSTER_PACKET_TYPES, is_packet_topic

    ouster = any(k in OUSTER_PACKET_TYPES and is_packet_topic(t, k) for t, k in topics.items())
    here = {mode} | ({"ouster packets"} if ouster else set())
    for option, value, modes, purpose in by_mode:
        if value is not None and not here & set(modes):
            raise ConfigError(option, value, f"{purpose}; IN is {what}")
    if (args.preset or args.fields) and not args.pointcloud2:
        option = "--preset" if args.preset else "--fields"
        raise ConfigError(option, args.preset or ",".join(args.fields), "--pointcloud2 too "
                          "(it sets the fields of the PointCloud2 output)")
    merging = args.merge or args.merge_topic
    for option, value, default in (("--merge-out", args.merge_out, "/scan_merged"),
                                   ("--merge-increment", args.merge_increment, 0.25),
                                   ("--merge-range-max", args.merge_range_max, 100.0)):
        if value != default and not merging:
            raise ConfigError(option, value, "--merge or --merge-topic too (it sets the "
                              "merged scan)")


@dataclass
class Output:
    """Where ``convert`` writes: ``path`` (final) is an MCAP file, or with ``bag`` a rosbag2
    folder (``OUT/OUT_0.mcap`` + ``OUT/metadata.yaml``, what ``ros2 bag`` reads); both are
    written under ``tmp`` (a hidden name next to ``path``) and renamed by :meth:`finish`."""

    path: Path
    bag: bool
    tmp: Path

    @property
    def storage_name(self) -> str:
        """The name of the MCAP file (in the folder, for a bag)."""
        return f"{self.path.name}_0.mcap" if self.bag else self.path.name

    def writer(self, **options: Any) -> Any:
        """The :class:`lidarscan.mcap.McapWriter` (or :class:`lidarscan.rosbag2.BagWriter`)
        of the temporary output; ``options`` are the writer's."""
        if self.bag:
            from lidarscan.rosbag2 import BagWriter

            self.tmp.mkdir()
            return BagWriter(self.tmp / self.path.name, **options)
        from lidarscan.mcap import McapWriter

        return McapWriter(self.tmp, file_name=self.storage_name, **options)

    def finish(self) -> None:
        """Rename the (closed) temporary output into place (an empty OUT folder is replaced)."""
        if self.bag:
            os.replace(self.tmp / self.path.name, self.path)
            self.tmp.rmdir()
        else:
            os.replace(self.tmp, self.path)

    def discard(self) -> None:
        """Remove the temporary output (a failed run leaves nothing)."""
        if self.bag:
            shutil.rmtree(self.tmp, ignore_errors=True)
        else:
            self.tmp.unlink(missing_ok=True)


def output_of(name: str, src: Path) -> Output:
    """The :class:`Output` that ``OUT`` names: a folder (``OUT/`` or an existing empty folder)
    is a rosbag2 bag with MCAP storage, anything else an MCAP file; checked before anything is
    written (ConfigError / FileNotFoundError)."""
    from lidarscan.errors import ConfigError

    dst = Path(name)
    bag = name.endswith(("/", os.sep)) or dst.is_dir()
    if dst.exists() and src.resolve() == dst.resolve():
        raise ConfigError("OUT", str(dst), "a file other than IN")
    if bag and dst.is_dir() and any(dst.iterdir()):
        raise ConfigError("OUT", str(dst), "a new or empty folder for the rosbag2 bag (this "
                          "one has files; nothing is overwritten)")
    if bag and dst.exists() and not dst.is_dir():
        raise ConfigError("OUT", name, "a folder for the rosbag2 bag (a file of that name "
                          "exists)")
    if not bag and dst.suffix.lower() in _OTHER_FORMATS:
        raise ConfigError("OUT", str(dst), "an .mcap file, or a folder (OUT/) for a rosbag2 "
                          f"bag with MCAP storage: {dst.suffix} names "
                          f"{_OTHER_FORMATS[dst.suffix.lower()]}, which convert does not write "
                          "(`ros2 bag convert` makes a sqlite3 bag from the output)")
    if not dst.parent.is_dir():
        raise FileNotFoundError(f"OUT {dst}: no such directory {dst.parent}")
    return Output(dst, bag, dst.with_name(f".{dst.name}.{os.getpid()}.partial"))
