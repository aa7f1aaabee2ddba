"""``lidarscan-converter`` with ``moving: true``: the slices' extrinsics come from /tf at every
pixel's time (a TransformTrack filled from the node's TransformBuffer), a scan is held until /tf
covers its sweep, and dropped (counted, logged) when it cannot be.

Oracles: :class:`converters.slices.converter.SliceConverter` with an independently built
TransformTrack (the composed chain looked up at the same /tf stamps: bit-identical slices); the
mount's analytic pose (the track's poses match it); the fixed-mount slices (the motion must
change them).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import pytest

from converters.slices.converter import SliceConverter
from converters.edge.nodes.converter_node import ConverterCore
from converters.edge.nodes.params import SliceConfig
from converters.edge.nodes.tf import TransformBuffer
from converters.shared.transforms import TransformTrack
from grid_reference import pose
from lidarscan.errors import ConfigError
from test_laserscan import make_sensor
from test_moving_slices import STAMP, moving_room_scan
from test_moving_mounts import _tf_message
from test_nodes import graph  # noqa: F401 - the rclpy graph fixture

MS = 1_000_000
SCAN_NS = 100 * MS                 # make_sensor: 10 Hz sweep
STEP = 5 * MS                      # /tf rate of the pan joint
ARM = pose(z=0.05, roll=0.02)      # pan_link <- os_sensor (static)
SLICES = [SliceConfig("band", 0.9, 1.5), SliceConfig("low", 0.3, 0.8, angle_increment=0.05)]


def pan(t: int) -> np.ndarray:
    """base_link <- pan_link at t ns: yawing at 1 turn/s, nodding 0.2 rad at 5 Hz."""
    s = (t - STAMP) * 1e-9
    return pose(0.1, 0.0, 0.6, yaw=2.0 * math.pi * s, pitch=0.2 * math.sin(2 * math.pi * 5 * s))


def mount(t: int) -> np.ndarray:
    return pan(t) @ ARM


def scan_at(info: Any, stamp: int) -> Any:
    """The room seen from the moving mount during the sweep that starts at ``stamp``."""
    scan = moving_room_scan(info, lambda t: mount(t - STAMP + stamp),
                            rng=np.random.default_rng(stamp % 1000))
    when = type(scan.header.stamp)(sec=stamp // 10**9, nanosec=stamp % 10**9)
    return dataclasses.replace(scan, header=dataclasses.replace(scan.header, stamp=when))


def feed(buf: TransformBuffer, start: int, stop: int) -> None:
    """/tf samples of the pan joint every STEP in [start, stop]."""
    for t in range(start, stop + 1, STEP):
        buf.set_transform("base_link", "pan_link", pan(t), t)


def make_core(buf: TransformBuffer, events: list[str] | None = None, **kwargs: Any
              ) -> ConverterCore:
    buf.set_transform("pan_link", "os_sensor", ARM, static=True)
    log = events if events is not None else []
    return ConverterCore(slices=SLICES, target_frame="base_link", moving=True,
                         tf_samples=buf.samples, on_event=log.append, **kwargs)


def same_slices(a: dict[str, Any], b: dict[str, Any]) -> None:
    assert list(a) == list(b)
    for name in a:
        assert a[name].header.frame_id == b[name].header.frame_id == "base_link"
        assert a[name].header.stamp == b[name].header.stamp
        assert np.asarray(a[name].ranges).tobytes() == np.asarray(b[name].ranges).tobytes()
        assert np.asarray(a[name].intensities).tobytes() == \
            np.asarray(b[name].intensities).tobytes()


# ----------------------------------------------------------------------------- core

def test_moving_core_equals_slice_converter_with_the_equivalent_track() -> None:
    info = make_sensor(16, 128)
    buf = TransformBuffer()
    core = make_core(buf, tf_wait_ns=10**9)
    assert core.add_info(info) == []
    stamps = [STAMP + k * SCAN_NS for k in range(3)]
    feed(buf, STAMP - 20 * MS, STAMP + 20 * MS)          # only the first sweep's start
    out = []
    for stamp in stamps:
        pairs = core.add_scan(scan_at(info, stamp))
        assert len(pairs) == 1
        out += core.hold(pairs)                          # /tf does not cover it yet: held
    assert out == [] and len(core.held) == 3
    feed(buf, STAMP - 20 * MS, stamps[-1] + SCAN_NS + 10 * MS)
    out = core.update_tracks()
    assert [p[0].header.stamp.nanosec for p in out] == [0, SCAN_NS, 2 * SCAN_NS]
    assert len(out) == 3 and not core.held and core.stats.dropped_no_pose == 0
    # the equivalent track, built independently from the same /tf stamps
    ref = TransformTrack(name="base_link <- os_sensor")
    for t in range(STAMP - 20 * MS, stamps[-1] + SCAN_NS + 10 * MS + 1, STEP):
        ref.add(t, buf.lookup("base_link", "os_sensor", t))
        np.testing.assert_allclose(buf.lookup("base_link", "os_sensor", t), mount(t),
                                   atol=1e-12)
    slicer = SliceConverter(info, {s.name: s.spec() for s in SLICES}, extrinsics=ref,
                            frame_id="base_link", intensity_channel="intensity")
    for scan, paired in out:
        _, got = core.convert(scan, paired, cloud=False, extrinsics=core.track("os_sensor"))
        same_slices(got, dict(slicer.convert(scan)))
        # the motion matters: a fixed mount at the scan stamp gives other slices
        _, fixed = core.convert(scan, paired, cloud=False,
                                extrinsics=mount(int(scan.header.stamp.sec) * 10**9 +
                                                 int(scan.header.stamp.nanosec)))
        assert np.asarray(fixed["band"].ranges).tobytes() != \
            np.asarray(got["band"].ranges).tobytes()
    assert core.stats.scans_converted == 6


def test_a_scan_never_covered_is_dropped_after_tf_wait_and_counted() -> None:
    info = make_sensor(16, 128)
    buf = TransformBuffer()
    events: list[str] = []
    core = make_core(buf, events, tf_wait_ns=50 * MS)
    core.add_info(info)
    feed(buf, STAMP - 20 * MS, STAMP + 60 * MS)          # /tf stops in the middle of sweep 0
    assert core.hold(core.add_scan(scan_at(info, STAMP))) == []
    assert core.update_tracks() == [] and len(core.held) == 1
    # data time moves on (the next scan), but not yet tf_wait past sweep 0's last pixel
    hi = core.held[0][3]
    assert core.hold(core.add_scan(scan_at(info, STAMP + SCAN_NS))) == []
    assert core.stats.dropped_no_pose == 0 and len(core.held) == 2
    assert hi <= STAMP + SCAN_NS + 50 * MS
    # the scan after: data time past tf_wait for sweep 0 (and sweep 1): both dropped
    assert core.hold(core.add_scan(scan_at(info, STAMP + 3 * SCAN_NS))) == []
    assert core.stats.dropped_no_pose == 2 and len(core.held) == 1
    assert core.stats.reasons["no pose"] == 2
    assert core.stats.scans_converted == 0
    assert len(events) == 2 and "does not cover its sweep" in events[0] and \
        "held too long" in events[0] and f"[{STAMP}," in events[0]


def test_a_sweep_older_than_the_poses_is_dropped_at_once_and_held_ones_are_bounded() -> None:
    info = make_sensor(16, 128)
    buf = TransformBuffer()
    events: list[str] = []
    core = make_core(buf, events, tf_wait_ns=10 * SCAN_NS, max_pending=2)
    core.add_info(info)
    feed(buf, STAMP + 50 * MS, STAMP + 3 * SCAN_NS)      # /tf starts mid-sweep 0
    assert core.hold(core.add_scan(scan_at(info, STAMP))) == []
    assert core.stats.dropped_no_pose == 1 and "before the oldest pose" in events[-1]
    assert not core.held
    # covered scans are released at once
    assert len(core.hold(core.add_scan(scan_at(info, STAMP + SCAN_NS)))) == 1
    # three scans beyond /tf with max_pending 2: the oldest is dropped (too many held)
    for k in (4, 5, 6):
        assert core.hold(core.add_scan(scan_at(info, STAMP + k * SCAN_NS))) == []
    assert core.stats.dropped_no_pose == 2 and len(core.held) == 2
    assert "too many scans held" in events[-1]


def test_a_time_jump_back_clears_the_track_and_waits_afresh() -> None:
    info = make_sensor(16, 128)
    buf = TransformBuffer()
    core = make_core(buf, tf_wait_ns=50 * MS)
    core.add_info(info)
    feed(buf, STAMP + 10 * SCAN_NS, STAMP + 11 * SCAN_NS)
    assert core.track("os_sensor").span == (STAMP + 10 * SCAN_NS, STAMP + 11 * SCAN_NS)
    buf.clear()                                          # as TfListener does on a jump back
    assert core.update_tracks(cleared=True) == []
    assert core.track("os_sensor").span is None
    assert core.hold(core.add_scan(scan_at(info, STAMP))) == []   # no pose yet: waits
    assert core.stats.dropped_no_pose == 0
    feed(buf, STAMP - 10 * MS, STAMP + SCAN_NS)
    assert len(core.update_tracks()) == 1


def test_moving_needs_a_target_frame_and_hold_is_transparent_when_fixed() -> None:
    with pytest.raises(ConfigError, match="moving"):
        ConverterCore(slices=SLICES, moving=True)
    pairs = [(object(), object())]
    for core in (ConverterCore(slices=SLICES, target_frame="base_link"),
                 ConverterCore(target_frame="base_link", moving=True)):   # cloud only
        assert core.hold(pairs) == pairs and not core.held


def test_node_parameters_document_moving_and_tf_wait() -> None:
    from converters.edge.nodes import converter_node

    text = converter_node.usage()
    assert "moving" in text and "tf_wait" in text and "tf_tolerance" in text
    node, _ = converter_node._specs()
    by_name = {s.name: s for s in node}
    assert by_name["moving"].default is False and by_name["tf_wait"].default == 0.1
    assert by_name["tf_tolerance"].default == 0.0 and by_name["tf_tolerance"].read_only
    with pytest.raises(ConfigError):
        by_name["tf_tolerance"].check(-0.1)
    with pytest.raises(ConfigError, match="tf_tolerance"):
        make_core(TransformBuffer(), tf_tolerance_ns=-1)


def test_tf_tolerance_holds_the_newest_pose_and_drops_beyond_it() -> None:
    """A sweep that ends at most ``tf_tolerance`` after the newest pose is released at once
    and sliced with the newest pose held (a track with the same tolerance: bit-identical
    slices); without the tolerance it waits; a sweep that ends later than the tolerance waits
    ``tf_wait`` and is then dropped and counted."""
    info = make_sensor(16, 128)
    last = STAMP + 90 * MS                           # the sweep's last pixel: ~99.2 ms
    strict, lenient = TransformBuffer(), TransformBuffer()
    for buf in (strict, lenient):
        feed(buf, STAMP - 20 * MS, last)
    events: list[str] = []
    cores = {"strict": make_core(strict, tf_wait_ns=50 * MS),
             "lenient": make_core(lenient, events, tf_wait_ns=50 * MS,
                                  tf_tolerance_ns=20 * MS)}
    scan = scan_at(info, STAMP)
    released = {}
    for name, core in cores.items():
        core.add_info(info)
        released[name] = core.hold(core.add_scan(scan))
    assert released["strict"] == [] and len(cores["strict"].held) == 1
    assert len(released["lenient"]) == 1 and not cores["lenient"].held
    core = cores["lenient"]
    assert core.track("os_sensor").tolerance_ns == 20 * MS
    ref = TransformTrack(tolerance_ns=20 * MS)
    for t in range(STAMP - 20 * MS, last + 1, STEP):
        ref.add(t, lenient.lookup("base_link", "os_sensor", t))
    _, got = core.convert(scan, info, cloud=False, extrinsics=core.track("os_sensor"))
    want = SliceConverter(info, {s.name: s.spec() for s in SLICES}, extrinsics=ref,
                          frame_id="base_link", intensity_channel="intensity").convert(scan)
    same_slices(got, dict(want))
    # the next sweep ends 100 ms after the newest pose: beyond the tolerance, held, then
    # dropped once data time is tf_wait past it
    assert core.hold(core.add_scan(scan_at(info, STAMP + SCAN_NS))) == []
    assert len(core.held) == 1 and core.stats.dropped_no_pose == 0
    assert core.hold(core.add_scan(scan_at(info, STAMP + 3 * SCAN_NS))) == []
    assert core.stats.dropped_no_pose == 1 and core.stats.reasons["no pose"] == 1
    assert "slices of scan" in events[0] and "held too long" in events[0]


# --------------------------------------------------------------------- real DDS graph

@pytest.mark.ros
def test_converter_node_slices_a_moving_mount_from_tf(graph: Any) -> None:  # noqa: F811
    """The real node: /tf_static (arm) + /tf (pan joint, 200 Hz) published after each sweep;
    every slice equals SliceConverter's with the track of the same /tf messages."""
    from diagnostic_msgs.msg import DiagnosticArray
    from lidarscan_msgs.msg import LidarInfo, LidarScan
    from sensor_msgs.msg import LaserScan, PointCloud2

    from converters.edge.nodes.converter_node import ConverterNode
    from test_nodes import overrides, same_floats, small_info, small_scan

    tf2_msgs = pytest.importorskip("tf2_msgs.msg")
    info = small_info(frame="os_sensor")                  # 128 columns x 781.25 us = 100 ms
    ref_buf = TransformBuffer()
    static = tf2_msgs.TFMessage(transforms=[_tf_message("pan_link", "os_sensor", ARM, 0)])
    ref_buf.add_message(static, static=True)
    graph.publisher(tf2_msgs.TFMessage, "/tf_static", "latched").publish(static)
    graph.publisher(LidarInfo, "lidar_info", "latched").publish(info)
    tf_pub = graph.publisher(tf2_msgs.TFMessage, "/tf", "reliable")
    scan_pub = graph.publisher(LidarScan, "lidar_scan", "reliable")
    out = graph.collect(LaserScan, "slices/band")
    clouds = graph.collect(PointCloud2, "points")
    node = graph.add(ConverterNode(context=graph.context, parameter_overrides=overrides(
        target_frame="base_link", slice_names=["band"], slices__band__min_height=0.7,
        slices__band__max_height=1.5, scan_qos="reliable", moving=True, tf_wait=1.0,
        extrinsics=[9.0, 9.0, 9.0, 0.0, 0.0, 0.0])))
    assert graph.wait(lambda: node.tf_buffer.is_static("pan_link", "os_sensor") and
                      node.core.resolver.latest_stamp_ns is not None and
                      tf_pub.get_subscription_count() > 0 and
                      scan_pub.get_subscription_count() > 0 and
                      node.slice_pubs["band"].get_subscription_count() > 0 and
                      node.cloud_pub.get_subscription_count() > 0)
    scans = {}
    for k in range(3):
        stamp = STAMP + k * SCAN_NS
        scans[stamp] = small_scan(info, stamp, seed=k)
        scan_pub.publish(scans[stamp])                     # the sweep before its /tf
        for t in range(stamp - 10 * MS if k == 0 else stamp + 5 * MS,
                       stamp + SCAN_NS + 5 * MS, STEP):
            msg = tf2_msgs.TFMessage(transforms=[_tf_message("base_link", "pan_link", pan(t), t)])
            ref_buf.add_message(msg)
            tf_pub.publish(msg)
    assert graph.wait(lambda: len(out) >= 3, timeout=15.0)
    track = TransformTrack()
    for t, matrix in ref_buf.samples("base_link", "os_sensor"):
        track.add(t, matrix)
    slicer = SliceConverter(info, {"band": SliceConfig("band", 0.7, 1.5).spec()},
                            extrinsics=track, frame_id="base_link")
    for msg in out:
        stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
        want = slicer.convert(scans[stamp])["band"]
        assert msg.header.frame_id == "base_link"
        assert same_floats(msg.ranges, want.ranges)
        assert same_floats(msg.intensities, want.intensities)
    assert node.stats.dropped_no_pose == 0 and not node.core.held
    status = {s.name: s for s in node._diagnose()}["moving mount"]
    assert status.message == "ok" and status.values["held"] == 0
    # the node's own 1 Hz timer also takes each period's counts: read what it publishes
    arrays = graph.collect(DiagnosticArray, "/diagnostics", "reliable")

    def moving_statuses() -> list[dict[str, str]]:
        return [{"message": st.message, **{kv.key: kv.value for kv in st.values}}
                for array in list(arrays) for st in array.status
                if st.name.endswith("lidarscan_converter: moving mount")]

    assert graph.wait(lambda: moving_statuses() != [], timeout=5.0)   # subscribed before the drop
    # a sweep /tf never covers: held, then dropped once data time is tf_wait past it
    late = STAMP + 3 * SCAN_NS
    scan_pub.publish(small_scan(info, late))
    assert graph.wait(lambda: len(node.core.held) == 1)
    scan_pub.publish(small_scan(info, late + 12 * SCAN_NS))      # 1.2 s later > tf_wait
    assert graph.wait(lambda: node.stats.dropped_no_pose == 1)
    assert graph.wait(lambda: any(st["dropped_no_pose"] == "1" for st in moving_statuses()),
                      timeout=5.0)
    after = [st for st in moving_statuses() if st["dropped_no_pose"] == "1"]
    assert after[0]["dropped_last_period"] == "1" and "did not cover" in after[0]["message"]
    assert all(st["dropped_last_period"] == "0" for st in after[1:])
    assert node.stats.reasons["no pose"] == 1 and len(out) == 3
    # the clouds never wait for /tf: one per scan at its arrival, the dropped one's included
    assert graph.wait(lambda: len(clouds) == 5)
    stamps = sorted(c.header.stamp.sec * 10**9 + c.header.stamp.nanosec for c in clouds)
    assert stamps == [*sorted(scans), late, late + 12 * SCAN_NS]
    assert node.stats.clouds_published == 5 and node.stats.scans_converted == 3
