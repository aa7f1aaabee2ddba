"""The simulated scene of ``lidarscan demo``: a robot with a 3D lidar, a 2D lidar and a depth
camera in a small room with a staircase down.

Everything here is deterministic and offline (no network, nothing read outside the package):

* the room (``room_scene``): floor, four walls 2.5 m high with a doorway, a table (top at
  0.68..0.72 m on four thin legs), a shelf overhanging from a wall at 1.18..1.22 m, a crate, a
  pillar and a staircase down (a stairwell in the floor, four 0.18 m steps); every object is an
  axis-aligned box in the ``odom`` frame (metres, REP 103, z up);
* the 3D lidar (:class:`SimulatedLidar3D`): the geometry of a real Ouster OS-1-128 (2048 x 10,
  metadata shipped in ``converters/data``, see its NOTICE.md) turned into a LidarInfo by
  :func:`converters.sources.ouster.metadata.info_from_metadata`; every pixel's ray (``P = rho * D + O`` from the
  projector) is intersected exactly with the boxes, so projecting the produced ranges lands on the
  surfaces to float32 precision; intensity, reflectivity and ambient follow a simple model
  (albedo, incidence angle, 1/r^2, light from the doorway);
* the 2D lidar (:class:`SimulatedLaser2D`): a 270 degree scanner 0.2 m above the floor, which sees
  the table legs but not the table top or the shelf;
* the depth camera (:class:`SimulatedDepthCamera`): a pinhole camera (424 x 240, 87 degrees wide,
  no distortion) 0.6 m up, pitched down and turned to the right, publishing 16UC1 depth images
  (REP 118, millimetres) and their CameraInfo, which
  :class:`converters.sources.depth.DepthImageConverter` turns into LidarScans;
* :func:`run_demo`: moves the robot slowly through the room, converts every frame (PointCloud2,
  three height slices in ``base_link``, the depth camera's slice with hole detection, the merged
  scan of the full slice, the 2D lidar and the camera slice), writes ``demo.mcap`` and PNG
  views, and returns sizes and timings. Neither lidar's height band sees the staircase (it is
  below the floor); the camera slice reports its edge as an obstacle (holes, see
  :mod:`converters.slices.converter`).

The scene, sensors and trajectory live in :mod:`converters.edge.demo.scene`, the PNG views in
:mod:`converters.edge.demo.views`; their public names are importable from here too.

The robot pose is constant during one frame (no motion inside a scan; at 0.2 m/s it would move
2 cm in 0.1 s). Ranges are exact (no noise) unless ``noise_m`` is given.
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from converters.edge.demo.scene import (
    LINK_FROM_OPTICAL,
    STAIRWELL,
    START_NS,  # noqa: F401 - re-exported (its old home)
    Box,
    Hits,
    Pose2D,
    Scene,
    SimulatedDepthCamera,
    SimulatedLaser2D,
    SimulatedLidar3D,
    pose_matrix,
    room_scene,
    trajectory,
)
from converters.edge.demo.config import DEFAULT_SLICES, DemoConfig, camera_slicer
from converters.edge.demo.views import hole_bins  # noqa: F401 - re-exported (its old home)

_camera_slicer = camera_slicer  # its old name

__all__ = [
    "DEFAULT_SLICES",
    "METADATA_PATH",
    "Box",
    "DemoConfig",
    "DemoResult",
    "Hits",
    "Pose2D",
    "Scene",
    "STAIRWELL",
    "SimulatedDepthCamera",
    "SimulatedLaser2D",
    "SimulatedLidar3D",
    "pose_matrix",
    "room_scene",
    "run_demo",
    "trajectory",
]

#: The Ouster metadata the simulated 3D lidar is built from (shipped with the package).
METADATA_PATH = Path(__file__).resolve().parents[2] / "data" / \
    "2_0_0_os1-992008000494-128_col_win_legacy.json"

# ----------------------------------------------------------------------------- ROS messages

def _transform_msg(parent: str, child: str, matrix: np.ndarray[Any, Any], stamp_ns: int) -> Any:
    from geometry_msgs.msg import Quaternion, Transform, TransformStamped, Vector3
    from std_msgs.msg import Header

    from converters.edge.nodes.tf import quaternion_from_matrix
    from lidarscan.stamps import time_msg

    qx, qy, qz, qw = quaternion_from_matrix(matrix)
    return TransformStamped(
        header=Header(stamp=time_msg(stamp_ns), frame_id=parent), child_frame_id=child,
        transform=Transform(translation=Vector3(x=float(matrix[0, 3]), y=float(matrix[1, 3]),
                                                z=float(matrix[2, 3])),
                            rotation=Quaternion(x=qx, y=qy, z=qz, w=qw)))


def tf_message(transforms: Sequence[Any]) -> Any:
    """A ``tf2_msgs/msg/TFMessage`` (rclpy class if built, else a lidarscan dataclass)."""
    try:
        from tf2_msgs.msg import TFMessage
        return TFMessage(transforms=list(transforms))
    except ImportError:
        from lidarscan.errors import SchemaError
        from lidarscan.msgdef import find_msg_text, register_msg_text
        from lidarscan.types import message_class
        try:
            find_msg_text("tf2_msgs/msg/TFMessage")
        except SchemaError:
            register_msg_text("tf2_msgs/msg/TFMessage",
                              "geometry_msgs/TransformStamped[] transforms\n")
        return message_class("tf2_msgs/msg/TFMessage")(transforms=tuple(transforms))


def _odometry_msg(pose: Pose2D) -> Any:
    from geometry_msgs.msg import (
        Point,
        Pose,
        PoseWithCovariance,
        Quaternion,
        Twist,
        TwistWithCovariance,
        Vector3,
    )
    from nav_msgs.msg import Odometry
    from std_msgs.msg import Header

    from lidarscan.stamps import time_msg

    return Odometry(
        header=Header(stamp=time_msg(pose.stamp_ns), frame_id="odom"), child_frame_id="base_link",
        pose=PoseWithCovariance(pose=Pose(
            position=Point(x=pose.x, y=pose.y, z=0.0),
            orientation=Quaternion(x=0.0, y=0.0, z=math.sin(pose.yaw / 2),
                                   w=math.cos(pose.yaw / 2)))),
        twist=TwistWithCovariance(twist=Twist(linear=Vector3(x=pose.vx),
                                              angular=Vector3(z=pose.wz))))


# ---------------------------------------------------------------------------------- the demo

@dataclass
class DemoResult:
    """What :func:`run_demo` produced.

    Attributes:
        out_dir: output folder.
        mcap_path: the recording.
        images: PNG files written.
        frames: frames simulated.
        topics: topic -> (type, message count).
        sizes: name -> CDR bytes of one message (first frame): "LidarScan", "PointCloud2", ...
        timings: stage -> list of seconds per frame.
        total_s: wall time of the whole run.
    """

    out_dir: Path
    mcap_path: Path
    images: list[Path] = field(default_factory=list)
    frames: int = 0
    topics: dict[str, tuple[str, int]] = field(default_factory=dict)
    sizes: dict[str, int] = field(default_factory=dict)
    timings: dict[str, list[float]] = field(default_factory=dict)
    total_s: float = 0.0

    def summary(self) -> str:
        """A human-readable report (the CLI prints it)."""
        lines = [f"lidarscan demo: {self.frames} frames -> {self.mcap_path}"]
        lines.append("  topics:")
        for topic, (msgtype, count) in self.topics.items():
            lines.append(f"    {topic:<28} {msgtype:<32} {count:>4} msgs")
        scan = self.sizes.get("LidarScan")
        lines.append("  message sizes (CDR bytes, one frame):")
        lines.append("    (LidarScan: range f32 + intensity u16 + reflectivity u8 + ambient u16;"
                     " PointCloud2: x y z intensity f32, 16 B/point; ouster-ros: 48 B/point)")
        for name, size in self.sizes.items():
            ratio = f"  ({size / scan:.2f}x LidarScan)" if scan and name.startswith(
                "PointCloud2") else ""
            lines.append(f"    {name:<30} {size:>12,d}{ratio}")
        lines.append("  timings per frame (median, ms; the first frame also builds tables"
                     " and compiles kernels):")
        for stage, values in self.timings.items():
            if values:
                lines.append(f"    {stage:<28} {1e3 * statistics.median(values):>9.1f}"
                             f"   (first frame {1e3 * values[0]:.1f})")
        if self.images:
            lines.append("  images:")
            lines.extend(f"    {p}" for p in self.images)
        lines.append(f"  total {self.total_s:.1f} s. Open {self.mcap_path.name} in Foxglove, or "
                     f"run: {_lidarscan_command()} info {self.mcap_path}")
        return "\n".join(lines)


def _lidarscan_command() -> str:
    """``lidarscan`` as the user can run it: the script beside this interpreter (a venv's
    ``.venv/bin/lidarscan``, not on PATH unless the venv is active), else the bare name."""
    import shutil
    import sys

    beside = Path(sys.executable).parent / "lidarscan"
    if beside.is_file() and shutil.which("lidarscan") != str(beside):
        try:
            return str(beside.relative_to(Path.cwd()))
        except ValueError:
            return str(beside)
    return "lidarscan"


def _info(stamp_ns: int) -> Any:
    from converters.sources.ouster.metadata import info_from_metadata

    return info_from_metadata(METADATA_PATH, stamp_ns=stamp_ns, frame_id="os_sensor")


def run_demo(out_dir: str | Path = "demo_out", frames: int = 10, *, images: bool = True,
             config: DemoConfig | None = None, noise_m: float = 0.0,
             progress: Callable[[int, int], None] | None = None) -> DemoResult:
    """Simulate, convert, record and draw: the whole pipeline in one call.

    Args:
        out_dir: folder for ``demo.mcap`` and the PNG views (created).
        frames: number of 3D/2D frames (>= 1), at ``config.rate_hz``.
        images: write the PNG views (needs matplotlib).
        config: robot set-up (default :class:`DemoConfig`).
        noise_m: range noise of the 3D lidar (standard deviation, m).
        progress: called as ``progress(done, total)`` after each frame.

    Returns:
        :class:`DemoResult` with paths, message sizes and per-stage timings.

    Raises:
        ConfigError: ``frames`` < 1.
    """
    import lidarscan
    from converters.sources.depth import DepthImageConverter
    from converters.slices.converter import SliceConverter
    from converters.merger import LaserScanMerger, MergerInput
    from converters.pointcloud2.converter import PointCloud2Converter
    from lidarscan.errors import ConfigError
    from lidarscan.mcap import McapWriter

    if int(frames) < 1:
        raise ConfigError("frames", frames, ">= 1")
    started = time.perf_counter()
    config = config or DemoConfig()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    result = DemoResult(out, out / "demo.mcap", frames=int(frames))
    timings: dict[str, list[float]] = {k: [] for k in (
        "ray casting (3D + 2D + depth)", "LidarScan build", "PointCloud2", "slices (3)",
        "depth image -> scan + slice", "merge", "encode + write")}
    result.timings = timings

    scene = room_scene()
    poses = trajectory(int(frames), rate_hz=config.rate_hz)
    info = _info(poses[0].stamp_ns - 1_000_000_000)
    lidar = SimulatedLidar3D(info, scene, noise_m=noise_m)
    laser = SimulatedLaser2D(scene)
    camera = SimulatedDepthCamera(scene)
    optical_mount = config.camera_mount @ LINK_FROM_OPTICAL      # base_link <- optical frame
    # the camera's LidarInfo is derived from the CameraInfo and not recorded (the recording holds
    # the Image + CameraInfo a robot would); its version key is the first image's stamp
    depth_converter = DepthImageConverter(camera.camera_info(poses[0].stamp_ns))
    camera_slices = camera_slicer(depth_converter.info, optical_mount, config, holes=True)
    cloud_converter = PointCloud2Converter(info)
    slicer = SliceConverter(info, {name: {"min_height": lo, "max_height": hi}
                                   for name, (lo, hi) in config.slices.items()},
                            extrinsics=config.lidar_mount, frame_id="base_link",
                            angle_min=-math.pi, angle_increment=math.radians(0.25),
                            range_min=0.1, range_max=20.0)
    merger = LaserScanMerger(
        {"full": MergerInput(extrinsics=None),
         "laser": MergerInput(extrinsics=config.laser_mount),
         "camera": MergerInput(extrinsics=None)},
        frame_id="base_link", angle_min=-math.pi, angle_increment=math.radians(0.25),
        range_min=0.1, range_max=20.0)

    counts: dict[str, list[Any]] = {}

    def write(writer: McapWriter, topic: str, msg: Any, stamp_ns: int | None = None) -> None:
        writer.write(topic, msg, log_time_ns=stamp_ns)
        entry = counts.setdefault(topic, [lidarscan.types.msgtype_of(msg), 0])
        entry[1] += 1

    last: dict[str, Any] = {}
    with McapWriter(result.mcap_path, chunk_size=1 << 20) as writer:
        static = [_transform_msg("base_link", "os_sensor", config.lidar_mount, info_stamp(info)),
                  _transform_msg("base_link", "laser", config.laser_mount, info_stamp(info)),
                  _transform_msg("base_link", "camera_link", config.camera_mount,
                                 info_stamp(info)),
                  _transform_msg("camera_link", camera.frame_id, LINK_FROM_OPTICAL,
                                 info_stamp(info))]
        write(writer, "/tf_static", tf_message(static), info_stamp(info))
        write(writer, "/lidar/info", info)
        for k, pose in enumerate(poses):
            base = pose.matrix()
            laser_stamp = pose.stamp_ns + config.laser_delay_ns
            t0 = time.perf_counter()
            channels = lidar.channels(base @ config.lidar_mount)
            laser_scan = laser.scan(base @ config.laser_mount, laser_stamp)
            image = camera.image(base @ optical_mount, pose.stamp_ns)
            camera_info = camera.camera_info(pose.stamp_ns)
            t1 = time.perf_counter()
            scan = lidarscan.make_scan(info, channels, pose.stamp_ns)
            t2 = time.perf_counter()
            cloud = cloud_converter.convert(scan)
            t3 = time.perf_counter()
            slices = slicer.convert(scan)
            t4 = time.perf_counter()
            camera_scan, _ = depth_converter.convert(image, camera_info=camera_info)
            camera_slice = camera_slices.convert(camera_scan)["camera"]
            t4b = time.perf_counter()
            merged = merger.merge({"full": slices["full"], "laser": laser_scan,
                                   "camera": camera_slice})
            t5 = time.perf_counter()
            write(writer, "/tf", tf_message([_transform_msg("odom", "base_link", base,
                                                            pose.stamp_ns)]), pose.stamp_ns)
            write(writer, "/odom", _odometry_msg(pose))
            write(writer, "/lidar/scan", scan)
            write(writer, "/lidar/points", cloud)
            for name, slice_scan in slices.items():
                write(writer, f"/lidar/slices/{name}", slice_scan)
            write(writer, "/laser/scan", laser_scan)
            write(writer, "/camera/depth/image_rect_raw", image)
            write(writer, "/camera/depth/camera_info", camera_info)
            write(writer, "/camera/slice", camera_slice)
            if merged is not None:
                write(writer, "/scan_merged", merged)
            t6 = time.perf_counter()
            for stage, seconds in zip(timings, (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t4b - t4,
                                                t5 - t4b, t6 - t5)):
                timings[stage].append(seconds)
            if k == 0:
                from converters.pointcloud2.converter import to_pointcloud2

                result.sizes = {
                    "LidarScan": len(lidarscan.encode(scan)),
                    "PointCloud2": len(lidarscan.encode(cloud)),
                    "PointCloud2 ouster-ros layout": len(lidarscan.encode(
                        to_pointcloud2(scan, info, preset="ouster"))),
                    "LidarInfo (once, latched)": len(lidarscan.encode(info)),
                    "LaserScan slice 'full'": len(lidarscan.encode(slices["full"])),
                    "LaserScan 2D lidar": len(lidarscan.encode(laser_scan)),
                    "Image 16UC1 depth": len(lidarscan.encode(image)),
                    "LidarScan depth camera": len(lidarscan.encode(camera_scan)),
                }
            last = {"scan": scan, "cloud": cloud, "slices": slices, "laser": laser_scan,
                    "merged": merged, "pose": pose, "image": image, "camera_scan": camera_scan,
                    "camera_slice": camera_slice, "camera_info": depth_converter.info}
            if progress is not None:
                progress(k + 1, len(poses))
    result.topics = {topic: (msgtype, n) for topic, (msgtype, n) in counts.items()}
    if images:
        from converters.edge.demo.views import draw

        result.images = draw(out, scene, info, last, config)
    result.total_s = time.perf_counter() - started
    return result


def info_stamp(info: Any) -> int:
    """The info's version key in int ns."""
    from lidarscan.stamps import to_ns

    return to_ns(info.header.stamp)
