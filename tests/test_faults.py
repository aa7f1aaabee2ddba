"""Faults end to end: info linkage through recordings (read_scans) and the converters, merger.

Linkage cases, each with two geometries that differ (so a scan converted with the wrong info
would give other points): scans before their info, an info change mid-stream, the same stamp
republished (same and different content), an info that never arrives, an info that arrives late
after some of its scans were dropped. Invariants checked every time:

* a scan is only ever paired with the info whose stamp it names, carrying the geometry first
  published under that stamp (never a newer/other geometry);
* every scan is accounted for: yielded once, or reported once (with index, topic, stamp and a
  reason) -- nothing is silently lost;
* buffers stay bounded (``max_pending``).
"""

from __future__ import annotations

import io
from collections.abc import Iterable
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import lidarscan as ls
from lidarscan.geometry import exact_xyz
from lidarscan.linkage import InfoResolver
from lidarscan.mcap import BadMessage, McapWriter, read_scans

from helpers import Clock

H, W = 4, 16
STAMP_A, STAMP_B, STAMP_C = 1_000_000_000, 2_000_000_000, 3_000_000_000


def _info(stamp_ns: int, tilt: float = 0.0) -> Any:
    """Geometry differing by ``tilt`` (radians added to every elevation) and a z offset."""
    return ls.make_info(stamp_ns=stamp_ns, frame_id="lidar",
                        vertical_angles=np.linspace(0.3, -0.3, H) + tilt,
                        horizontal_angles=2 * np.pi * (1 - np.arange(W) / W),
                        beam_origins=np.tile([0.01 + tilt, 0.0, tilt], H),
                        as_dataclass=True)


GEOMETRY = {STAMP_A: _info(STAMP_A, 0.0), STAMP_B: _info(STAMP_B, 0.2),
            STAMP_C: _info(STAMP_C, -0.1)}


def _scan(info_stamp: int, stamp_ns: int) -> Any:
    info = GEOMETRY.get(info_stamp) or _info(info_stamp)
    ranges = np.full((H, W), 1.0 + (stamp_ns % 1000) / 100.0, np.float32)
    return ls.make_scan(info, {"range": ranges}, stamp_ns, as_dataclass=True)


def _recording(events: Iterable[tuple[str, Any]]) -> bytes:
    buf = io.BytesIO()
    with McapWriter(buf, chunk_size=2048) as writer:
        for kind, msg in events:
            writer.write("/lidar/info" if kind == "info" else "/lidar/scan", msg,
                         log_time_ns=ls.to_ns(msg.header.stamp))
    return buf.getvalue()


def _run(events: list[tuple[str, Any]], max_pending: int = 64
         ) -> tuple[list[tuple[Any, Any]], list[BadMessage]]:
    errors: list[BadMessage] = []
    pairs = list(read_scans(_recording(events), on_error=errors.append, max_pending=max_pending))
    return pairs, errors


def _assert_right_geometry(scan: Any, info: Any) -> None:
    """The pair is the scan's own version, and projecting it equals the original geometry."""
    key = ls.to_ns(scan.lidar_info_time)
    assert ls.to_ns(info.header.stamp) == key
    original = GEOMETRY[key]
    np.testing.assert_array_equal(np.asarray(info.vertical_angles), original.vertical_angles)
    points = ls.make_projector(info).project(scan, info)
    expected = exact_xyz(original, ls.range_m(scan))
    np.testing.assert_allclose(points, expected, atol=1e-4)


def _stamps(items: Iterable[Any]) -> list[int]:
    return [ls.to_ns(s.header.stamp) for s in items]


# -------------------------------------------------------------------------- linkage, files

def test_scans_recorded_before_their_info_are_all_converted() -> None:
    scans = [_scan(STAMP_A, 10 + i) for i in range(5)]
    pairs, errors = _run([("scan", s) for s in scans] + [("info", GEOMETRY[STAMP_A])])
    assert errors == []
    assert _stamps(s for s, _ in pairs) == _stamps(scans)
    for scan, info in pairs:
        _assert_right_geometry(scan, info)


def test_info_change_mid_stream_pairs_each_scan_with_its_own_geometry() -> None:
    events: list[tuple[str, Any]] = [("info", GEOMETRY[STAMP_A])]
    events += [("scan", _scan(STAMP_A, 100 + i)) for i in range(3)]
    events += [("info", GEOMETRY[STAMP_B])]
    events += [("scan", _scan(STAMP_B, 200 + i)) for i in range(3)]
    events += [("scan", _scan(STAMP_A, 300))]  # a straggler of the old geometry, after the change
    pairs, errors = _run(events)
    assert errors == []
    assert len(pairs) == 7
    for scan, info in pairs:
        _assert_right_geometry(scan, info)
    assert [ls.to_ns(i.header.stamp) for _, i in pairs] == [STAMP_A] * 3 + [STAMP_B] * 3 + [STAMP_A]


def test_same_stamp_republished_identically_changes_nothing() -> None:
    info = GEOMETRY[STAMP_A]
    events = [("info", info), ("scan", _scan(STAMP_A, 1)), ("info", info),
              ("scan", _scan(STAMP_A, 2))]
    pairs, errors = _run(events)
    assert errors == [] and len(pairs) == 2
    for scan, got in pairs:
        _assert_right_geometry(scan, got)


def test_same_stamp_with_other_geometry_drops_its_scans_with_a_reason() -> None:
    impostor = _info(STAMP_A, 0.2)  # same stamp, other geometry
    events = [("info", GEOMETRY[STAMP_A]), ("scan", _scan(STAMP_A, 1)), ("info", impostor),
              ("scan", _scan(STAMP_A, 2)), ("scan", _scan(STAMP_A, 3)),
              ("info", GEOMETRY[STAMP_B]), ("scan", _scan(STAMP_B, 4))]
    pairs, errors = _run(events)
    # The scan before the conflict used the geometry published then; none after it.
    assert _stamps(s for s, _ in pairs) == [1, 4]
    for scan, info in pairs:
        _assert_right_geometry(scan, info)
    assert [e.log_time_ns for e in errors] == [2, 3]
    assert all("ambiguous" in e.reason and e.topic == "/lidar/scan" for e in errors)
    assert [e.index for e in errors] == [3, 4]


def _sensors_recording(infos: list[Any], info_topic: str, scan_topic: str) -> bytes:
    """Each info latched at the start (as rosbag2 records them), then three scans per sensor
    interleaved; sensor i's ranges are all 1 + i."""
    buf = io.BytesIO()
    with McapWriter(buf, chunk_size=2048) as writer:
        for i, info in enumerate(infos):
            writer.write(info_topic.format(i=i), info, log_time_ns=STAMP_A)
        for k in range(3):
            for i, info in enumerate(infos):
                scan = ls.make_scan(info, {"range": np.full((H, W), 1.0 + i, np.float32)},
                                    STAMP_B + k, as_dataclass=True)
                writer.write(scan_topic.format(i=i), scan, log_time_ns=STAMP_B + k)
    return buf.getvalue()


def _sensor_of(scan: Any) -> int:
    return int(ls.channel(scan, "range")[0, 0]) - 1


def test_a_recording_of_more_sensors_than_the_live_default_pairs_every_scan() -> None:
    """Twelve sensors (more than a live resolver's eight held versions): every scan is paired
    with its own sensor's geometry and nothing is dropped, also with max_infos=8 when each
    sensor has its own namespace. (Before: the first four sensors' scans were all dropped as
    "evicted".) Topics outside the namespace convention are paired by stamp alone, bounded by
    max_infos: with 8, the four oldest sensors are lost, each scan reported."""
    infos = [_info(STAMP_A + i, tilt=0.01 * i) for i in range(12)]
    for max_infos in (256, 8):
        errors: list[BadMessage] = []
        pairs = list(read_scans(_sensors_recording(infos, "/lidar{i}/lidar_info",
                                                   "/lidar{i}/lidar_scan"),
                                on_error=errors.append, max_infos=max_infos))
        assert errors == [] and len(pairs) == 36
        for scan, info in pairs:
            assert ls.to_ns(info.header.stamp) == STAMP_A + _sensor_of(scan)
    other_names = _sensors_recording(infos, "/infos/lidar{i}", "/scans/lidar{i}")
    errors = []
    assert len(list(read_scans(other_names, on_error=errors.append))) == 36 and errors == []
    assert len(list(read_scans(other_names, on_error=errors.append, max_infos=8))) == 24
    assert len(errors) == 12 and all("evicted" in e.reason for e in errors)


def test_two_sensors_whose_infos_share_a_stamp_each_keep_their_own_geometry() -> None:
    """Simulation time or one launch can stamp two sensors' infos alike. In their own
    namespaces, each sensor's scans are paired with its own info; by stamp alone (no
    namespace convention) the stamp is ambiguous and every scan is dropped with that reason,
    never paired with the other sensor's geometry."""
    infos = [_info(STAMP_A, tilt=0.0), _info(STAMP_A, tilt=0.2)]
    errors: list[BadMessage] = []
    pairs = list(read_scans(_sensors_recording(infos, "/robot/lidar{i}/lidar_info",
                                               "/robot/lidar{i}/lidar_scan"),
                            on_error=errors.append))
    assert errors == [] and len(pairs) == 6
    for scan, info in pairs:
        assert info is infos[_sensor_of(scan)] or np.array_equal(
            info.vertical_angles, infos[_sensor_of(scan)].vertical_angles)
    pairs = list(read_scans(_sensors_recording(infos, "/infos/lidar{i}", "/scans/lidar{i}"),
                            on_error=errors.append))
    assert pairs == [] and len(errors) == 6 and all("ambiguous" in e.reason for e in errors)


def test_info_that_never_arrives_reports_every_scan() -> None:
    events = [("info", GEOMETRY[STAMP_A])] + [("scan", _scan(STAMP_B, 10 + i)) for i in range(4)]
    pairs, errors = _run(events)
    assert pairs == []  # never converted with STAMP_A's geometry
    assert [(e.index, e.topic, e.log_time_ns) for e in errors] == [
        (1 + i, "/lidar/scan", 10 + i) for i in range(4)]
    assert all("never arrived" in e.reason for e in errors)


def test_info_late_after_drops_releases_the_rest_bounded() -> None:
    scans = [_scan(STAMP_A, 10 + i) for i in range(6)]
    pairs, errors = _run([("scan", s) for s in scans] + [("info", GEOMETRY[STAMP_A])],
                         max_pending=2)
    assert [e.log_time_ns for e in errors] == [10, 11, 12, 13]  # oldest dropped first
    assert all("pending buffer full" in e.reason for e in errors)
    assert _stamps(s for s, _ in pairs) == [14, 15]
    for scan, info in pairs:
        _assert_right_geometry(scan, info)


def test_corrupt_info_is_reported_and_never_used() -> None:
    good = ls.encode(GEOMETRY[STAMP_A])
    buf = io.BytesIO()
    with McapWriter(buf) as writer:
        writer.write("/lidar/info", good[:40], msgtype="lidarscan_msgs/msg/LidarInfo",
                     log_time_ns=1)
        writer.write("/lidar/scan", _scan(STAMP_A, 2))
        writer.write("/lidar/info", GEOMETRY[STAMP_A])
        writer.write("/lidar/scan", _scan(STAMP_A, 3))
    errors: list[BadMessage] = []
    pairs = list(read_scans(buf.getvalue(), on_error=errors.append))
    assert [(e.index, e.topic, e.log_time_ns) for e in errors] == [(0, "/lidar/info", 1)]
    assert _stamps(s for s, _ in pairs) == [2, 3]  # the early scan waited for the good info


# Random streams: every scan is paired with its own geometry or reported, exactly once.
_EVENT = st.one_of(
    st.tuples(st.just("info"), st.sampled_from([STAMP_A, STAMP_B, STAMP_C]),
              st.sampled_from([0.0, 0.0, 0.3])),
    st.tuples(st.just("scan"), st.sampled_from([STAMP_A, STAMP_B, STAMP_C, 4_000_000_000]),
              st.just(0.0)))


@settings(max_examples=40)
@given(st.lists(_EVENT, min_size=1, max_size=25), st.integers(0, 6))
def test_random_streams_never_pair_a_scan_with_wrong_geometry(events: list[Any],
                                                             max_pending: int) -> None:
    msgs: list[tuple[str, Any]] = []
    first_geometry: dict[int, Any] = {}
    scan_count = 0
    for kind, stamp, tilt in events:
        if kind == "info":
            # tilt != 0 republishes the stamp with another geometry
            info = GEOMETRY[stamp] if tilt == 0.0 else _info(stamp, tilt)
            first_geometry.setdefault(stamp, info)
            msgs.append(("info", info))
        else:
            scan_count += 1
            msgs.append(("scan", _scan(stamp, 1000 + scan_count)))
    errors: list[BadMessage] = []
    pairs = list(read_scans(_recording(msgs), on_error=errors.append, max_pending=max_pending))
    yielded = _stamps(s for s, _ in pairs)
    reported = [e.log_time_ns for e in errors]
    assert sorted(yielded + reported) == list(range(1001, 1001 + scan_count)), \
        "a scan was lost or counted twice"
    for scan, info in pairs:
        key = ls.to_ns(scan.lidar_info_time)
        assert ls.to_ns(info.header.stamp) == key
        assert info is not None and key in first_geometry
        np.testing.assert_array_equal(np.asarray(info.vertical_angles),
                                      np.asarray(first_geometry[key].vertical_angles))
    for err in errors:
        assert err.topic == "/lidar/scan" and err.index >= 0 and err.reason


# ----------------------------------------------------------------- linkage, live (resolver)

def test_live_resolver_is_bounded_when_info_never_comes() -> None:
    clock = Clock()
    events: list[str] = []
    resolver = InfoResolver(max_pending=8, max_wait_ns=500_000_000, clock=clock,
                            on_event=events.append)
    dropped = 0
    for i in range(1000):
        clock.now = i * 25_000_000  # 40 Hz
        assert resolver.add_scan(_scan(STAMP_B, i)) == []
        assert resolver.pending <= 8
        dropped += len(resolver.take_dropped())
    assert dropped == 1000 - resolver.pending
    assert len(events) == dropped  # one log line per dropped scan
    resolver.add_info(GEOMETRY[STAMP_A])  # the wrong version changes nothing
    assert resolver.take_dropped() == [] and resolver.pending <= 8


def test_live_resolver_many_info_versions_keeps_a_bounded_history() -> None:
    resolver = InfoResolver(max_infos=3, max_wait_ns=None)
    for k in range(50):
        resolver.add_info(_info(10_000 + k, 0.001 * k))
    assert sum(resolver.info(10_000 + k) is not None for k in range(50)) == 3
    # a scan of a forgotten version waits (bounded), is never paired with a newer one
    assert resolver.add_scan(_scan(10_000, 5)) == []
    resolver.flush()
    assert len(resolver.take_dropped()) == 1


def test_live_resolver_logs_one_clear_line_per_case() -> None:
    clock = Clock()
    events: list[str] = []
    resolver = InfoResolver(max_pending=2, max_wait_ns=1_000, clock=clock, on_event=events.append)
    resolver.add_info(GEOMETRY[STAMP_A])
    resolver.add_info(GEOMETRY[STAMP_B])                      # change
    resolver.add_info(_info(STAMP_B, 0.3))                    # same stamp, other geometry
    resolver.add_scan(_scan(STAMP_B, 1))                      # ambiguous: dropped
    for i in range(3):                                        # overflow: one dropped
        resolver.add_scan(_scan(STAMP_C, 10 + i))
    clock.now = 5_000
    resolver.expire()                                         # two expire
    assert len(events) == 1 + 1 + 1 + 1 + 2
    assert f"LidarInfo changed: stamp {STAMP_A} -> {STAMP_B}" in events[0]
    assert "DIFFERENT geometry" in events[1]
    assert "dropped scan stamp=1" in events[2] and "ambiguous" in events[2]
    assert "pending buffer full" in events[3] and "stamp=10" in events[3]
    assert all("did not arrive within" in line for line in events[4:])


# ------------------------------------------------------------------ converters (when present)

def _converter_module(name: str) -> Any:
    return pytest.importorskip(f"converters.{name}")


def _laser_scan_cls() -> Any:
    from lidarscan import types as lt
    return lt.message_class("sensor_msgs/msg/LaserScan"), lt


def test_converter_core_never_converts_with_the_wrong_geometry() -> None:
    """ConverterCore (the node's logic) fed CDR bytes: early scans, an info change, a conflicting
    republish, an orphan; every cloud equals the exact projection with the scan's own info."""
    nodes = _converter_module("nodes.converter_node")
    pointcloud2 = _converter_module("pointcloud2")
    core = nodes.ConverterCore(cloud_options={"fields": ("x", "y", "z")}, max_pending=4,
                               max_wait_ns=None)
    converted: list[tuple[Any, Any]] = []

    def feed(kind: str, msg: Any) -> None:
        payload = ls.encode(msg)
        ready = core.add_info(payload) if kind == "info" else core.add_scan(payload)
        for scan, info in ready:
            cloud, _ = core.convert(scan, info)
            converted.append((scan, cloud))

    feed("scan", _scan(STAMP_A, 1))            # before its info
    feed("info", GEOMETRY[STAMP_A])
    feed("scan", _scan(STAMP_A, 2))
    feed("info", GEOMETRY[STAMP_B])            # geometry change
    feed("scan", _scan(STAMP_B, 3))
    feed("scan", _scan(STAMP_A, 4))            # straggler of the old version
    feed("info", _info(STAMP_B, -0.25))        # same stamp, other geometry: ambiguous
    feed("scan", _scan(STAMP_B, 5))
    feed("scan", _scan(STAMP_C, 6))            # its info never comes
    with pytest.raises(ls.errors.LidarScanError):
        core.add_scan(ls.encode(_scan(STAMP_A, 7))[:50])  # corrupt bytes: raised and counted
    assert _stamps(s for s, _ in converted) == [1, 2, 3, 4]
    for scan, cloud in converted:
        pts = pointcloud2.read_points(cloud)
        xyz = np.stack([pts["x"], pts["y"], pts["z"]], -1).reshape(H, W, 3)
        expected = exact_xyz(GEOMETRY[ls.to_ns(scan.lidar_info_time)], ls.range_m(scan))
        np.testing.assert_allclose(xyz, expected, atol=1e-4)
    assert core.stats.scans_dropped == 1 and core.stats.bad_messages == 1
    assert core.resolver.pending == 1  # STAMP_C's scan, bounded by max_pending


# ----------------------------------------------------------------------------------- merger

N_RAYS = 180
T0 = 100 * 10**9
PERIOD = 100_000_000  # 10 Hz


def _half_scan(name: str, index: int, stamp_ns: int) -> Any:
    """Input "a" covers [-pi, 0), "b" [0, pi) (base_link); every range encodes ``index``."""
    cls, lt = _laser_scan_cls()
    sec, nanosec = divmod(stamp_ns, 10**9)
    start = -np.pi if name == "a" else 0.0
    return cls(header=lt.Header(lt.Time(sec, nanosec), "base_link"), angle_min=start,
               angle_max=start + np.pi * (N_RAYS - 1) / N_RAYS,
               angle_increment=np.pi / N_RAYS, time_increment=0.0, scan_time=0.1,
               range_min=0.05, range_max=30.0,
               ranges=np.full(N_RAYS, (5.0 if name == "a" else 3.0) + index * 1e-3, np.float32),
               intensities=np.zeros(0, np.float32))


def _decoded(out: Any) -> dict[str, int | None]:
    """Which scan index of each input a merged output holds (None: that half is empty)."""
    r = np.asarray(out.ranges, np.float64)
    n = r.size
    result: dict[str, int | None] = {}
    for name, half, base in (("a", r[: n // 2], 5.0), ("b", r[n // 2:], 3.0)):
        finite = half[np.isfinite(half)]
        if finite.size == 0:
            result[name] = None
            continue
        codes = np.unique(np.round((finite - base) / 1e-3).astype(int))
        assert codes.size == 1, f"input {name}: several scans mixed in one output {codes}"
        result[name] = int(codes[0])
    return result


#: Merger options of the fault tests (library and node alike), overridden per test.
_MERGER_OPTIONS: dict[str, Any] = {"frame_id": "base_link", "angle_increment": np.radians(1.0),
                                   "slop_ns": 20_000_000, "policy": "timeout",
                                   "timeout_ns": 500_000_000, "queue_size": 10,
                                   "motion_compensation": False}


def _merger(**options: Any) -> Any:
    merger = _converter_module("merger")
    defaults = {**_MERGER_OPTIONS, **options}
    return merger.LaserScanMerger({"a": merger.MergerInput(), "b": merger.MergerInput()},
                                  **defaults)


def _stamp(out: Any) -> int:
    return int(out.header.stamp.sec) * 10**9 + int(out.header.stamp.nanosec)


def _check_fresh(out: Any, stamps: dict[str, dict[int, int]], slop_ns: int) -> dict[str, Any]:
    """Every fused scan is within the slop of the output stamp (nothing stale fused)."""
    used = _decoded(out)
    for name, index in used.items():
        if index is not None:
            assert abs(stamps[name][index] - _stamp(out)) <= slop_ns, \
                f"stale {name} scan #{index} fused into output at {_stamp(out)}"
    return used


def test_merger_dead_input_timeout_policy_keeps_publishing_without_stale_data() -> None:
    m = _merger()
    stamps: dict[str, dict[int, int]] = {"a": {}, "b": {}}
    outs = []
    for i in range(80):
        t = T0 + i * PERIOD
        for name in ("a", "b"):
            if name == "b" and 20 <= i < 50:  # b dies for 3 s, then its publisher restarts
                continue
            stamps[name][i] = t + (3_000_000 if name == "b" else 0)
            out = m.push(name, _half_scan(name, i, stamps[name][i]))
            if out is not None:
                outs.append(_check_fresh(out, stamps, 20_000_000) | {"t": _stamp(out)})
    a_only = [o for o in outs if o["b"] is None]
    assert a_only, "no output while b was dead"
    # a alone from (b's death + timeout) until b's first scan back (a's scan 50 may go out
    # alone: it is pushed before b's scan 50, while b is still dead)
    assert all(20 <= o["a"] <= 50 for o in a_only)
    first_alone = min(o["a"] for o in a_only)
    assert first_alone <= 20 + 500_000_000 // PERIOD + 1
    assert {o["a"] for o in a_only} >= set(range(first_alone, 50))
    # b rejoins as soon as it publishes again
    both_after = [o for o in outs if o["a"] is not None and o["a"] >= 50 and o["b"] is not None]
    assert [o["a"] for o in both_after] == list(range(51, 80))
    assert all(o["a"] == o["b"] for o in outs if o["b"] is not None)
    assert [o["t"] for o in outs] == sorted(o["t"] for o in outs)


def test_merger_wait_policy_stops_on_a_dead_input_with_bounded_memory() -> None:
    import tracemalloc
    m = _merger(policy="wait", queue_size=10)
    for i in range(5):
        for name in ("a", "b"):
            m.push(name, _half_scan(name, i, T0 + i * PERIOD))
    tracemalloc.start()
    try:
        sizes = []
        for i in range(5, 2005):
            assert m.push("a", _half_scan("a", i % 500, T0 + i * PERIOD)) is None
            if i in (505, 2004):
                sizes.append(tracemalloc.get_traced_memory()[0])
    finally:
        tracemalloc.stop()
    assert m.stats["dropped_overflow"] == 2000 - 10
    assert sizes[1] - sizes[0] < 200_000, f"memory grew by {sizes[1] - sizes[0]} bytes"


def test_merger_late_and_out_of_order_inputs_pair_only_matching_stamps() -> None:
    rng = np.random.default_rng(5)
    m = _merger(queue_size=10)
    stamps: dict[str, dict[int, int]] = {"a": {}, "b": {}}
    events = []
    for i in range(60):
        stamps["a"][i] = T0 + i * PERIOD
        stamps["b"][i] = T0 + i * PERIOD + 5_000_000
        events.append((i, "a", i))
        # b delivered 2-3 periods late: its data age stays under the 500 ms timeout
        events.append((i + 2 + int(rng.integers(0, 2)), "b", i))
    events.sort(key=lambda e: (e[0], e[1]))
    outs = []
    for _, name, i in events:
        out = m.push(name, _half_scan(name, i, stamps[name][i]))
        if out is not None:
            outs.append(_check_fresh(out, stamps, 20_000_000))
    paired = [o for o in outs if o["a"] is not None and o["b"] is not None]
    assert all(o["a"] == o["b"] for o in paired)
    assert len(paired) >= 58  # late by < queue_size periods: (almost) every scan still paired


def test_merger_duplicate_late_and_zero_stamps_are_dropped_not_fused() -> None:
    m = _merger()
    stamps: dict[str, dict[int, int]] = {"a": {}, "b": {}}
    outs = []

    def push(name: str, i: int, stamp: int) -> None:
        stamps[name][i] = stamp
        out = m.push(name, _half_scan(name, i, stamp))
        if out is not None:
            outs.append(_check_fresh(out, stamps, 20_000_000) | {"t": _stamp(out)})

    for i in range(30):
        t = T0 + i * PERIOD
        push("a", i, t)
        push("b", i, t)
        if i % 5 == 0:
            push("b", 400 + i, t)                  # duplicate stamp, other content
        if i % 7 == 3:
            push("a", 300 + i, t - 10 * PERIOD)    # out of order, far in the past
        if i % 4 == 1:
            push("b", 200 + i, 0)                  # zero stamp
    bad_pushes = len([i for i in stamps["a"] if i >= 100]) + len(
        [i for i in stamps["b"] if i >= 100])
    dropped = sum(m.stats[k] for k in ("dropped_duplicate", "dropped_late",
                                       "dropped_unmatched"))
    assert dropped >= bad_pushes, m.stats
    assert all(o["a"] is not None and o["a"] < 100 for o in outs)
    assert all(o["b"] is None or o["b"] < 100 for o in outs)
    assert [o["t"] for o in outs] == sorted({o["t"] for o in outs})
    assert len(outs) >= 28


def test_merger_odometry_history_is_bounded() -> None:
    import tracemalloc
    _, lt = _laser_scan_cls()
    odom_cls = lt.message_class("nav_msgs/msg/Odometry")
    pose_cls = lt.message_class("geometry_msgs/msg/PoseWithCovariance")
    p_cls = lt.message_class("geometry_msgs/msg/Pose")
    point_cls = lt.message_class("geometry_msgs/msg/Point")
    quat_cls = lt.message_class("geometry_msgs/msg/Quaternion")
    m = _merger(motion_compensation=True, odom_queue_size=50)

    def odom(i: int) -> Any:
        sec, nanosec = divmod(T0 + i * 10_000_000, 10**9)
        return odom_cls(header=lt.Header(lt.Time(sec, nanosec), "odom"),
                        child_frame_id="base_link",
                        pose=pose_cls(pose=p_cls(position=point_cls(x=i * 0.01, y=0.0, z=0.0),
                                                 orientation=quat_cls(x=0.0, y=0.0, z=0.0,
                                                                      w=1.0)),
                                      covariance=np.zeros(36)))
    tracemalloc.start()
    try:
        for i in range(1000):  # warm-up (numpy's first-call caches are traced too)
            m.push_odometry(odom(i))
        before = tracemalloc.get_traced_memory()[0]
        for i in range(1000, 3200):
            m.push_odometry(odom(i))
        grown = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    assert grown < 100_000
    assert m.pose_at(T0 + 3199 * 10_000_000) is not None
    assert m.pose_at(T0) is None or m.pose_at(T0).stamp_ns != T0  # old samples forgotten


# DEFECT FOUND (D7, fixed in converters/merger.py; this is its regression test). A clock jump
# backwards (a recording played in a loop, a sensor clock reset, sim time restarting) used to
# silence LaserScanMerger for good: every later scan was dropped as "late". Expected per issue 6:
# keep publishing per the documented policy (the merger's per-input jump_back_ns).
def test_merger_recovers_from_a_clock_jump_backwards() -> None:
    m = _merger()
    outs: list[tuple[int, Any]] = []
    for loop in range(2):
        for i in range(30):
            t = T0 + i * PERIOD
            for name in ("a", "b"):
                out = m.push(name, _half_scan(name, i, t))
                if out is not None:
                    outs.append((loop, out))
    after_jump = [o for loop, o in outs if loop == 1]
    assert len(after_jump) >= 30 - 500_000_000 // PERIOD - 2, \
        f"{len(after_jump)} outputs after the jump; stats {m.stats}"


def _merger_core(**options: Any) -> Any:
    node = _converter_module("nodes.merger_node")
    defaults = {**_MERGER_OPTIONS, **options}
    return node.MergerCore({"a": {}, "b": {}}, **defaults)


def test_merger_node_core_restarts_after_a_clock_jump_backwards() -> None:
    """MergerCore (the merger node's logic) treats a jump back as a restart (its jump_back)."""
    core = _merger_core()
    outs: list[tuple[int, Any]] = []
    for loop in range(2):
        for i in range(30):
            t = T0 + i * PERIOD
            for name in ("a", "b"):
                outs += [(loop, o) for o in core.push(name, _half_scan(name, i, t))]
    after = [_decoded(o) for loop, o in outs if loop == 1]
    assert len(after) >= 30 - 2
    assert all(o["a"] == o["b"] for o in after)


# DEFECT FOUND (D11, fixed in converters/edge/nodes/merger_node.py; this is its regression test), by
# bench/soak.py (2 % malformed LaserScans with a zero stamp): MergerCore.push used to take ONE
# scan older than the newest stamp by more than jump_back (1 s) as a clock jump and restart the
# merger, dropping every input's queue. Expected: such a scan is dropped as late, nothing resets.
def test_merger_node_core_one_zero_stamped_scan_does_not_reset_the_fusion() -> None:
    core = _merger_core()
    outs = []
    for i in range(60):
        t = T0 + i * PERIOD
        outs += core.push("a", _half_scan("a", i, t))
        if i % 3 == 1:
            try:
                core.push("b", _half_scan("b", 500 + i, 0))  # a zero-stamped scan
            except ls.errors.LidarScanError:
                pass
        outs += core.push("b", _half_scan("b", i, t + 1_000_000))
    fused = [o for o in map(_decoded, outs) if o["a"] is not None and o["a"] == o["b"]]
    # today: 20 resets, and 20 of the 60 outputs lack input a (its queued scan was dropped)
    assert len(fused) >= 57 and core.resets == 0, \
        f"{core.resets} resets; {len(fused)} of {len(outs)} outputs fused both inputs"


# Same defect, the way bench/soak.py met it without any malformed message: under load the
# converter's slice output lagged 2.3 s behind the 2D laser for a moment; each lagging slice was
# taken as a clock jump and reset the merger (9+ resets, 31 % of the merged scans lost, an 8.5 s
# outage). A jump back should be judged per input (its own stamps going backwards).
def test_merger_node_core_a_lagging_input_does_not_reset_the_fusion() -> None:
    core = _merger_core()
    outs = []
    held: list[tuple[int, int]] = []
    for i in range(60):
        t = T0 + i * PERIOD
        outs += core.push("a", _half_scan("a", i, t))
        if 20 <= i < 35:        # b stalls for 1.5 s, then delivers its backlog late
            held.append((i, t + 1_000_000))
            continue
        for j, tb in held:
            outs += core.push("b", _half_scan("b", j, tb))
        held.clear()
        outs += core.push("b", _half_scan("b", i, t + 1_000_000))
    decoded = [_decoded(o) for o in outs]
    after = [o for o in decoded if o["a"] is not None and o["a"] >= 36 and o["a"] == o["b"]]
    assert core.resets == 0 and len(after) >= 23, \
        f"{core.resets} resets; {len(after)} fused outputs after b caught up (of 24)"
