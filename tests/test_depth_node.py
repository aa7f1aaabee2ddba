"""The converter node's depth-image input: Image + CameraInfo paired by exact stamps
(:class:`converters.edge.nodes.common.ExactSync`), converted by :mod:`converters.sources.depth` and sliced
like a lidar, over real rclpy publishers and subscribers."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from converters.edge.nodes.common import ExactSync
from lidarscan.errors import ConfigError

from test_nodes import Graph, graph, overrides, same_floats  # noqa: F401 - graph is a fixture

# base_link <- camera optical frame: optical z forward = base x, x right = -y, y down = -z;
# the camera 0.5 m above base_link's origin
BASE_FROM_OPTICAL = np.array([[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0],
                              [0.0, -1.0, 0.0, 0.5], [0.0, 0.0, 0.0, 1.0]])


# ---------------------------------------------------------------------------- synchroniser

def test_exact_sync_pairs_equal_stamps_in_input_order() -> None:
    sync = ExactSync(("image", "info"), queue_size=3)
    assert sync.add("image", 10, "i10") is None
    assert sync.add("info", 10, "c10") == ("i10", "c10")
    assert sync.add("info", 20, "c20") is None          # info first works too
    assert sync.add("image", 20, "i20") == ("i20", "c20")
    assert sync.released == 2 and sync.drops() == 0 and sync.waiting() == {"image": 0, "info": 0}


def test_exact_sync_bounds_queues_and_counts_every_drop() -> None:
    sync = ExactSync(("image", "info"), queue_size=2)
    for t in (1, 2, 3):                                  # no partner: the oldest falls out
        assert sync.add("image", t, f"i{t}") is None
    assert sync.dropped["image"]["overflow"] == 1 and sync.waiting()["image"] == 2
    assert sync.add("image", 3, "i3b") is None           # same stamp again: replaced, counted
    assert sync.dropped["image"]["duplicate"] == 1
    assert sync.add("info", 5, "c5") is None
    assert sync.add("info", 3, "c3") == ("i3b", "c3")    # a pair at 3: image 2 can never pair
    assert sync.dropped["image"]["stale"] == 1
    assert sync.waiting() == {"image": 0, "info": 1}     # info 5 is newer: it waits
    assert sync.drops() == 3
    with pytest.raises(ConfigError):
        sync.add("depth", 1, None)
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ConfigError):
            ExactSync(("a", "b"), queue_size=bad)
    with pytest.raises(ConfigError):
        ExactSync(("a", "a"))


# ----------------------------------------------------------------------------------- node

def _camera_info(stamp_ns: int, *, height: int = 48, width: int = 64) -> Any:
    from sensor_msgs.msg import CameraInfo

    msg = CameraInfo(height=height, width=width, distortion_model="plumb_bob")
    msg.header.frame_id = "cam_optical"
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 10**9)
    fx = fy = 0.6 * width                                # about 80 degrees across
    msg.k = [fx, 0.0, width / 2 - 0.5, 0.0, fy, height / 2 - 0.5, 0.0, 0.0, 1.0]
    msg.d = [0.0] * 5
    msg.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    msg.p = [fx, 0.0, width / 2 - 0.5, 0.0, 0.0, fy, height / 2 - 0.5, 0.0, 0.0, 0.0, 1.0, 0.0]
    return msg


def _image(stamp_ns: int, depth_mm: np.ndarray[Any, Any]) -> Any:
    from sensor_msgs.msg import Image

    h, w = depth_mm.shape
    msg = Image(height=h, width=w, encoding="16UC1", is_bigendian=0, step=2 * w,
                data=depth_mm.astype("<u2").tobytes())
    msg.header.frame_id = "cam_optical"
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 10**9)
    return msg


@pytest.mark.ros
def test_converter_node_slices_a_depth_camera(graph: Graph) -> None:  # noqa: F811
    from sensor_msgs.msg import CameraInfo, Image, LaserScan

    from converters.sources.depth import DepthImageConverter
    from converters.slices.converter import SliceConverter
    from converters.edge.nodes.converter_node import ConverterNode

    from lidarscan_msgs.msg import LidarInfo, LidarScan

    slices = graph.collect(LaserScan, "depth/slices/knee")
    scans = graph.collect(LidarScan, "depth/lidar_scan")
    infos = graph.collect(LidarInfo, "depth/lidar_info", "latched")
    lidar_slices = graph.collect(LaserScan, "slices/knee")
    image_pub = graph.publisher(Image, "depth/image_rect", "sensor_data")
    info_pub = graph.publisher(CameraInfo, "depth/camera_info", "sensor_data")
    node = graph.add(ConverterNode(context=graph.context, parameter_overrides=overrides(
        **{"depth.enabled": True, "depth.extrinsics": BASE_FROM_OPTICAL.reshape(-1).tolist(),
           "depth.sync_queue": 4, "depth.publish_scan": True},
        target_frame="base_link", slice_names=["knee"], slices__knee__min_height=0.3,
        slices__knee__max_height=0.7, slices__knee__angle_increment=math.radians(0.25))))
    assert node.startup.ready and not node.startup.failed
    # a wall 2 m in front of the camera (fronto-parallel: z = 2000 mm everywhere), with a hole
    depth = np.full((48, 64), 2000, np.uint16)
    depth[20:28, 40:44] = 0                              # no measurement

    # an image whose CameraInfo never comes: waits, then dropped (counted) by the next pair
    image_pub.publish(_image(5 * 10**8, depth))
    assert graph.wait(lambda: node.depth_stats.scans_received >= 1)
    k = [0]

    def tick() -> None:
        k[0] += 1
        stamp = 10**9 + k[0] * 10**8
        info_pub.publish(_camera_info(stamp))
        image_pub.publish(_image(stamp, depth))

    assert graph.wait(lambda: len(slices) >= 1 and scans and infos, timeout=20, tick=tick)
    got = slices[0]
    assert got.header.frame_id == "base_link"
    stamp_ns = got.header.stamp.sec * 10**9 + got.header.stamp.nanosec
    # the library, step by step, on the same pair
    camera = _camera_info(stamp_ns)
    version = infos[-1].header.stamp      # the first CameraInfo's stamp (the version key)
    scan, info = DepthImageConverter(camera, info_stamp_ns=version.sec * 10**9 +
                                     version.nanosec).convert(_image(stamp_ns, depth))
    expected = SliceConverter(info, {"knee": {"min_height": 0.3, "max_height": 0.7,
                                              "angle_increment": math.radians(0.25)}},
                              extrinsics=BASE_FROM_OPTICAL, frame_id="base_link",
                              intensity_channel=None).convert(scan)["knee"]
    assert same_floats(got.ranges, expected.ranges) and len(got.intensities) == 0
    # the LidarScan and its latched LidarInfo, as the library makes them
    import lidarscan

    assert lidarscan.encode(infos[-1]) == lidarscan.encode(info)
    pub = next(m for m in scans if m.header.stamp == got.header.stamp)
    assert np.array_equal(lidarscan.channel(pub, "range"), lidarscan.channel(scan, "range"),
                          equal_nan=True)
    # and the geometry itself: straight ahead the wall is 2 m away, planar
    ranges = np.asarray(got.ranges)
    seen = np.isfinite(ranges)
    bearings = got.angle_min + np.flatnonzero(seen) * got.angle_increment
    ahead = np.argmin(np.abs(bearings))
    assert abs(bearings[ahead]) < math.radians(1.3)        # one column apart at most
    assert ranges[seen][ahead] == pytest.approx(2.0, abs=2e-3)
    assert np.all(np.abs(bearings) < math.radians(45))      # only inside the camera's view
    assert np.allclose(ranges[seen] * np.cos(bearings), 2.0, atol=0.01)   # a straight wall
    # the unpaired image was dropped and counted; the lidar's own slices stayed silent
    assert node.depth_sync.dropped["image"]["stale"] + \
        node.depth_sync.dropped["image"]["overflow"] >= 1
    assert not lidar_slices
    status = node._diagnose_depth()
    assert status.values["pairs"] >= 1 and status.values["sync_dropped"] >= 1
    assert status.values["camera"].startswith("48x64")


@pytest.mark.ros
def test_depth_input_needs_a_target_frame_and_refuses_bad_parameters(
        graph: Graph) -> None:  # noqa: F811
    from converters.edge.nodes.converter_node import ConverterNode

    with pytest.raises(ConfigError, match="target_frame"):
        ConverterNode(context=graph.context, parameter_overrides=overrides(
            **{"depth.enabled": True}))
    for name, value in (("depth.rectified", "maybe"), ("depth.sync_queue", 0),
                        ("depth.range_max", -1.0), ("depth.no_measurement", "zero")):
        with pytest.raises(ConfigError, match=name.replace(".", r"\.")):
            ConverterNode(context=graph.context, parameter_overrides=overrides(
                **{"depth.enabled": True, name: value}, target_frame="base_link"))
