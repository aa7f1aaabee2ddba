"""``lidarscan demo``: the simulated scene is exact, the recording complete, the views drawn, and
the demo shows what it claims (the table top that the plain 2D lidar misses, the staircase down
that only the depth camera's slice with hole detection reports)."""

from __future__ import annotations

import hashlib
import math
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import lidarscan
from converters.edge.demo import run as demo

from helpers import messages_by_topic

ROOT = Path(__file__).resolve().parent.parent
PNG = b"\x89PNG\r\n\x1a\n"
FRAMES = 2


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    """The console script, as a new user runs it (a fresh process, default settings)."""
    out = tmp_path_factory.mktemp("demo_out")
    exe = Path(sys.executable).parent / "lidarscan"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "converters.edge.cli"]
    env = {k: v for k, v in os.environ.items() if k != "_ROS_WHEELS_BOOTSTRAP_COMPLETE"}
    done = subprocess.run(cmd + ["demo", "--out", str(out), "--frames", str(FRAMES)],
                          check=False, capture_output=True, text=True, timeout=120, env=env, cwd=out)
    assert done.returncode == 0, done.stderr
    return out, done.stdout


def test_demo_writes_recording_views_and_summary(demo_run: tuple[Path, str]) -> None:
    out, stdout = demo_run
    topics = messages_by_topic(out / "demo.mcap")
    for topic in ("/lidar/scan", "/lidar/points", "/lidar/slices/floor_to_knee",
                  "/lidar/slices/table", "/lidar/slices/full", "/laser/scan", "/scan_merged",
                  "/tf", "/odom", "/camera/depth/image_rect_raw", "/camera/depth/camera_info",
                  "/camera/slice"):
        assert len(topics[topic]) == FRAMES, topic
    assert len(topics["/lidar/info"]) == 1 and len(topics["/tf_static"]) == 1
    for name in ("range_image.png", "birdseye_slices.png", "merged_scan.png",
                 "depth_camera.png", "pointcloud_topview.png"):
        assert (out / name).read_bytes()[:8] == PNG, name
    scan_bytes = len(topics["/lidar/scan"][0].payload)
    cloud_bytes = len(topics["/lidar/points"][0].payload)
    assert re.search(rf"LidarScan\s+{scan_bytes:,d}", stdout)
    assert re.search(rf"PointCloud2\s+{cloud_bytes:,d}", stdout)
    assert "timings per frame" in stdout and "x LidarScan)" in stdout
    assert cloud_bytes > scan_bytes  # the compact message is the point of the project


def recording(demo_run: tuple[Path, str]) -> tuple[dict[str, list[Any]], Any]:
    """(messages by topic, a TransformBuffer filled from /tf_static and /tf) of the demo run."""
    from converters.edge.nodes.tf import TransformBuffer

    out, _ = demo_run
    topics = messages_by_topic(out / "demo.mcap")
    tf = TransformBuffer()
    tf.add_message(topics["/tf_static"][0].decode(), static=True)
    for item in topics["/tf"]:
        tf.add_message(item.decode())
    return topics, tf


def _box_distance(points: np.ndarray[Any, Any], box: demo.Box) -> np.ndarray[Any, Any]:
    """|signed distance| of points to an axis-aligned box surface."""
    lo, hi = np.asarray(box.lo), np.asarray(box.hi)
    q = np.abs(points - (lo + hi) / 2) - (hi - lo) / 2
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
    inside = np.minimum(q.max(axis=1), 0.0)
    return np.abs(outside + inside)


def test_simulated_scan_lands_exactly_on_the_scene(demo_run: tuple[Path, str]) -> None:
    topics, tf = recording(demo_run)
    info = topics["/lidar/info"][0].decode()
    scan = topics["/lidar/scan"][-1].decode()
    points = lidarscan.make_projector(info).project(scan, info).reshape(-1, 3)
    points = points[np.isfinite(points[:, 0])][::5].astype(np.float64)
    world = tf.lookup("odom", "os_sensor", lidarscan.to_ns(scan.header.stamp))
    points = points @ world[:3, :3].T + world[:3, 3]
    scene = demo.room_scene()
    nearest = np.min([_box_distance(points, b) for b in scene.boxes], axis=0)
    assert len(points) > 40_000
    assert nearest.max() < 2e-4  # float32 ranges and tables, metres


def _reference_cast(scene: demo.Scene, o: np.ndarray[Any, Any], d: np.ndarray[Any, Any]
                    ) -> tuple[float, int]:
    """Slow per-ray slab test written from the formula (the oracle)."""
    best, which = math.inf, -1
    for index, box in enumerate(scene.boxes):
        t_near, t_far = -math.inf, math.inf
        for k in range(3):
            if d[k] == 0.0:
                if not box.lo[k] <= o[k] <= box.hi[k]:
                    t_near, t_far = math.inf, -math.inf
                continue
            t0, t1 = (box.lo[k] - o[k]) / d[k], (box.hi[k] - o[k]) / d[k]
            t_near, t_far = max(t_near, min(t0, t1)), min(t_far, max(t0, t1))
        if t_near <= t_far and 1e-9 < t_near < best:
            best, which = t_near, index
    return best, which


def test_ray_casting_matches_a_loop_reference() -> None:
    scene = demo.room_scene()
    rng = np.random.default_rng(7)
    d = rng.normal(size=(300, 3))
    d[:20, 2] = 0.0  # horizontal rays, as the 2D lidar casts
    d /= np.linalg.norm(d, axis=1)[:, None]
    o = np.column_stack([rng.uniform(-3.5, 3.5, 300), rng.uniform(-2.5, 2.5, 300),
                         rng.uniform(0.1, 2.0, 300)])
    hits = scene.cast(o, d)
    for i in range(len(o)):
        t, which = _reference_cast(scene, o[i], d[i])
        assert hits.box[i] == which
        assert (hits.t[i] == t == math.inf) or abs(hits.t[i] - t) < 1e-12


def test_the_table_top_is_missed_by_the_2d_lidar_and_seen_by_the_slices(
        demo_run: tuple[Path, str]) -> None:
    from converters.edge.demo import viz
    topics, tf = recording(demo_run)
    scene = demo.room_scene()
    top = next(b for b in scene.boxes if b.name == "table" and b.lo[2] > 0.5)
    legs = [b for b in scene.boxes if b.name == "table" and b.lo[2] == 0.0]

    def in_odom(msg: Any) -> np.ndarray[Any, Any]:
        m = tf.lookup("odom", msg.header.frame_id, lidarscan.to_ns(msg.header.stamp))
        return viz.laserscan_xy(msg, m)

    def on_top(xy: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
        return (xy[:, 0] >= top.lo[0] - 0.01) & (xy[:, 0] <= top.hi[0] + 0.01) & \
            (xy[:, 1] >= top.lo[1] - 0.01) & (xy[:, 1] <= top.hi[1] + 0.01)

    def near_leg(xy: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
        return np.any([(np.abs(xy[:, 0] - (b.lo[0] + b.hi[0]) / 2) < 0.04) &
                       (np.abs(xy[:, 1] - (b.lo[1] + b.hi[1]) / 2) < 0.04) for b in legs], axis=0)

    laser = in_odom(topics["/laser/scan"][-1].decode())
    table = in_odom(topics["/lidar/slices/table"][-1].decode())
    low = in_odom(topics["/lidar/slices/floor_to_knee"][-1].decode())
    merged = in_odom(topics["/scan_merged"][-1].decode())
    assert on_top(laser).sum() >= 2 and np.all(near_leg(laser[on_top(laser)]))
    assert (on_top(table) & ~near_leg(table)).sum() > 20      # the table top's edge
    assert np.all(near_leg(low[on_top(low)]))                  # below 0.5 m: legs only
    assert (on_top(merged) & ~near_leg(merged)).sum() > 20


def test_the_depth_camera_reports_the_stair_edge_that_no_band_sees(
        demo_run: tuple[Path, str]) -> None:
    """The recorded depth image (with its CameraInfo) converts to the LidarScan the camera slice
    was cut from; the slice's hole edges lie on the stairwell's rim (at most a few cm beyond it,
    never in front of it), the same slice without holes sees only farther things there, and the
    merged scan carries the edge too."""
    from converters.edge.demo import viz
    from converters.sources.depth import from_depth_image
    topics, tf = recording(demo_run)
    image = topics["/camera/depth/image_rect_raw"][-1].decode()
    scan, info = from_depth_image(image, topics["/camera/depth/camera_info"][-1].decode())
    stamp = lidarscan.to_ns(scan.header.stamp)
    optical = tf.lookup("base_link", info.header.frame_id, stamp)
    config = demo.DemoConfig()
    with_holes = topics["/camera/slice"][-1].decode()
    again = demo._camera_slicer(info, optical, config, holes=True).convert(scan)["camera"]
    np.testing.assert_array_equal(np.asarray(again.ranges), np.asarray(with_holes.ranges))
    plain = demo._camera_slicer(info, optical, config, holes=False).convert(scan)["camera"]
    edge = demo.hole_bins(with_holes, plain)
    assert edge.sum() > 40
    ranges = np.asarray(with_holes.ranges, np.float64)
    angles = with_holes.angle_min + with_holes.angle_increment * np.arange(ranges.size)
    xy = np.stack([ranges * np.cos(angles), ranges * np.sin(angles), np.zeros_like(ranges),
                   np.ones_like(ranges)], 1)[edge]
    odom = (xy @ tf.lookup("odom", "base_link", stamp).T)[:, :2]
    x0, y0, x1, y1 = demo.STAIRWELL
    tol = 0.01              # drawn at the bin's centre angle: up to half a bin (4 mm at 2 m) off
    inside = (odom[:, 0] >= x0 - tol) & (odom[:, 0] <= x1) & (odom[:, 1] >= y0) & \
        (odom[:, 1] <= y1 + tol)
    assert np.all(inside), odom[~inside]                     # on or beyond the rim, never before
    rim = np.minimum(odom[:, 0] - x0, y1 - odom[:, 1])       # the two rims the camera faces
    assert np.all(rim < 0.05), rim.max()
    behind = np.asarray(plain.ranges, np.float64)[edge]      # what the band alone sees there
    assert np.all(behind > ranges[edge] + 0.2)                # walls and table, well behind
    merged = viz.laserscan_xy(topics["/scan_merged"][-1].decode(),
                              tf.lookup("odom", "base_link", stamp))
    on_rim = (np.abs(merged[:, 0] - x0) < 0.05) & (merged[:, 1] > y0) & (merged[:, 1] < y1)
    assert on_rim.sum() > 10


def test_the_views_slice_the_camera_scan_once(tmp_path: Path,
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """The merged-scan view and the depth-camera view share one slice of the last camera scan
    without hole detection (it was cut once per view)."""
    pytest.importorskip("matplotlib")
    from converters.edge.demo import config as demo_config

    made: list[bool] = []
    slicer = demo_config.camera_slicer

    def counting(*args: Any, holes: bool, **kwargs: Any) -> Any:
        made.append(holes)
        return slicer(*args, holes=holes, **kwargs)

    monkeypatch.setattr(demo_config, "camera_slicer", counting)    # what the views call
    result = demo.run_demo(tmp_path, frames=1)
    assert {p.name for p in result.images} >= {"merged_scan.png", "depth_camera.png"}
    assert made == [False]


def test_demo_ships_its_metadata_with_provenance() -> None:
    path = demo.METADATA_PATH
    assert path.is_file() and path.parent == ROOT / "converters" / "data"
    notice = (path.parent / "NOTICE.md").read_text()
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    assert digest in notice and "BSD 3-Clause License" in notice and "Ouster, Inc." in notice
    info = demo._info(0)
    assert (info.height, info.width, info.model) == (128, 2048, "OS-1-128")


def test_nothing_reads_the_shared_folder_at_run_time() -> None:
    sources = list((ROOT / "converters").rglob("*.py")) + list((ROOT / "lidarscan").rglob("*.py"))
    sources += list((ROOT / "examples").glob("*.py"))
    assert ROOT / "converters" / "edge" / "demo" / "run.py" in sources
    for source in sources:
        assert "/work/shared" not in source.read_text(), source
        assert "../shared" not in source.read_text(), source


def test_trajectory_is_an_exact_unicycle() -> None:
    poses = demo.trajectory(11, rate_hz=10.0, speed=0.2, yaw_rate=0.1)
    assert poses[0].stamp_ns == demo.START_NS and poses[-1].stamp_ns == demo.START_NS + 10**9
    radius = 0.2 / 0.1
    centre = np.array([-2.2, 0.2 + radius])
    for p in poses:
        assert math.isclose(np.hypot(p.x - centre[0], p.y - centre[1]), radius, rel_tol=1e-12)
        assert math.isclose(p.yaw, 0.1 * (p.stamp_ns - demo.START_NS) / 1e9, rel_tol=1e-12)
    with pytest.raises(lidarscan.errors.ConfigError):
        demo.run_demo(Path("unused"), frames=0)
