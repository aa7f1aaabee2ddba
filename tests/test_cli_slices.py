"""``lidarscan convert --slice NAME:ZMIN:ZMAX[:KEY=VALUE]...``: hole options per slice (LidarScans
and clouds with a grid; refused for clouds without one), and the spec's errors."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from converters.edge import cli
from converters.slices.converter import SliceConverter
from converters.edge.nodes.tf import TransformBuffer
from lidarscan.errors import ConfigError
from lidarscan.mcap import McapWriter, read_messages, read_scans
from lidarscan.stamps import to_ns
from test_cli import copy_topics as _copy_topics
from helpers import messages_by_topic as _topics

SPEC = "floor:-0.3:0.3:holes:floor_height=0:hole_depth=0.05"
HOLES = {"min_height": -0.3, "max_height": 0.3, "holes": True, "floor_height": 0.0,
         "hole_depth": 0.05}


@pytest.fixture(scope="module")
def demo_mcap(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from converters.edge.demo.run import run_demo

    return run_demo(tmp_path_factory.mktemp("demo"), frames=2, images=False).mcap_path


def _holed_scans(src: Path) -> list[tuple[Any, Any]]:
    """The demo's scans with a pit cut into the floor: every return of the lower beams (the
    ones that hit the floor) pushed 0.5 m further along its ray, i.e. seen below the floor."""
    import lidarscan

    out = []
    for scan, info in read_scans(src):
        rng = lidarscan.range_m(scan, info).copy()
        lower = np.asarray(info.vertical_angles) < np.radians(-10)
        rng[lower] = np.where(np.isfinite(rng[lower]), rng[lower] + 0.5, rng[lower])
        names = [c.name for c in scan.channels]
        channels = {n: lidarscan.channel(scan, n) for n in names}
        channels["range"] = rng.astype(np.float32)
        out.append((lidarscan.make_scan(info, channels, to_ns(scan.header.stamp)), info))
    return out


def _oracle(scan: Any, info: Any, tf: TransformBuffer, spec: dict[str, Any]) -> Any:
    return SliceConverter(info, {"floor": spec}, extrinsics=tf.lookup("base_link", "os_sensor"),
                          frame_id="base_link").convert(scan)["floor"]


def test_holes_of_a_lidarscan_recording_match_the_library(tmp_path: Path,
                                                           demo_mcap: Path) -> None:
    src, dst = tmp_path / "in.mcap", tmp_path / "out.mcap"
    _copy_topics(demo_mcap, src, {"/tf_static", "/tf", "/lidar/info", "/lidar/scan"})
    assert cli.main(["convert", str(src), str(dst), "--slice", SPEC, "--frame", "base_link",
                     "-q"]) == 0
    out = _topics(dst)
    tf = TransformBuffer()
    tf.add_message(out["/tf_static"][0].decode(), static=True)
    pairs = list(read_scans(src))
    assert len(out["/lidar/slices/floor"]) == len(pairs) == 2
    for (scan, info), item in zip(pairs, out["/lidar/slices/floor"]):
        got = np.asarray(item.decode().ranges)
        want = np.asarray(_oracle(scan, info, tf, HOLES).ranges)
        assert np.array_equal(got, want, equal_nan=True)


def test_a_pit_is_reported_with_holes_and_not_without(tmp_path: Path, demo_mcap: Path) -> None:
    """The test above cannot tell holes on from off on a flat floor: here the floor has a pit,
    so the holes change the slice (-inf/near ranges where the floor is missing)."""
    src = tmp_path / "pit.mcap"
    with McapWriter(src) as writer:
        for item in read_messages(demo_mcap):
            if item.topic == "/tf_static":
                writer.write(item.topic, item.payload, msgtype=item.msgtype,
                             log_time_ns=item.log_time_ns)
        for scan, info in _holed_scans(demo_mcap):
            writer.write("/lidar/info", info)
            writer.write("/lidar/scan", scan)
    slices = {}
    for name, spec in (("on", SPEC), ("off", "floor:-0.3:0.3")):
        dst = tmp_path / f"{name}.mcap"
        assert cli.main(["convert", str(src), str(dst), "--slice", spec, "--frame",
                         "base_link", "-q"]) == 0
        slices[name] = [np.asarray(m.decode().ranges)
                        for m in _topics(dst)["/lidar/slices/floor"]]
    tf = TransformBuffer()
    tf.add_message(next(m for m in read_messages(src) if m.topic == "/tf_static").decode(),
                   static=True)
    (scan, info), = _holed_scans(demo_mcap)[:1]
    assert np.array_equal(slices["on"][0], np.asarray(_oracle(scan, info, tf, HOLES).ranges),
                          equal_nan=True)
    assert not np.array_equal(slices["on"][0], slices["off"][0], equal_nan=True)


def test_clouds_with_a_grid_get_holes_through_their_lidarscan(tmp_path: Path,
                                                               demo_mcap: Path) -> None:
    src, dst = tmp_path / "clouds.mcap", tmp_path / "out.mcap"
    _copy_topics(demo_mcap, src, {"/lidar/points", "/tf_static"})
    assert cli.main(["convert", str(src), str(dst), "--slice", SPEC, "--frame", "base_link",
                     "-q"]) == 0
    out = _topics(dst)
    assert len(out["/lidar/lidar_scan"]) == len(out["/lidar/slices/floor"]) == 2
    tf = TransformBuffer()
    tf.add_message(out["/tf_static"][0].decode(), static=True)
    for (scan, info), item in zip(read_scans(dst), out["/lidar/slices/floor"]):
        want = _oracle(scan, info, tf, HOLES)
        assert np.array_equal(np.asarray(item.decode().ranges), np.asarray(want.ranges),
                              equal_nan=True)


def test_clouds_without_a_grid_refuse_holes(tmp_path: Path, demo_mcap: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    from test_cloud_slices import LIVOX, make_cloud, random_points

    src, dst = tmp_path / "livox.mcap", tmp_path / "out.mcap"
    rng = np.random.default_rng(3)
    with McapWriter(src) as writer:
        for k in range(2):
            writer.write("/livox/points", make_cloud(random_points(rng, 500), layout=LIVOX,
                                                     frame="livox", stamp=(10**9 + k, 0)),
                         log_time_ns=(10**9 + k) * 10**9)
    status = cli.main(["convert", str(src), str(dst), "--slice", SPEC])
    err = capsys.readouterr().err
    assert status == 2, err
    assert "holes" in err and "grid" in err
    assert not dst.exists() and list(tmp_path.iterdir()) == [src]


@pytest.mark.parametrize("spec,words", [
    ("f:0:1:holes:depth=3", "KEY among holes, floor_height"),
    ("f:0:1:holes=maybe", "true or false"),
    ("f:0:1:holes:hole_depth=-1", "hole_depth"),
    ("f:0:1:holes:hole_depth=x", "a number of metres"),
    ("f:0:1:floor_height=0.2", "'holes' among the keys"),
    ("f:0:1:holes:holes", "each key once"),
])
def test_bad_slice_keys_are_usage_errors(spec: str, words: str, tmp_path: Path,
                                         demo_mcap: Path,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["convert", str(demo_mcap), str(tmp_path / "o.mcap"), "--slice",
                     spec]) == 2
    err = capsys.readouterr().err
    assert words in err and spec in err
    assert not list(tmp_path.iterdir())


def test_slice_spec_values() -> None:
    s = cli.parse_slice("f:0:1:holes:floor_height=-0.2:hole_range_max=inf:hole_no_return=no")
    assert (s.name, s.min_height, s.max_height) == ("f", 0.0, 1.0)
    assert s.extra == {"holes": True, "floor_height": -0.2, "hole_range_max": float("inf"),
                       "hole_no_return": False}
    assert cli.parse_slice("f:0:1").extra == {}
    with pytest.raises(ConfigError):
        cli.parse_slice("f:0")
