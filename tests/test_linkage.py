"""The info-linkage resolver: every case of lidarscan/linkage.py's rules, with two geometries."""

from __future__ import annotations

import numpy as np
import pytest

import lidarscan as ls
from lidarscan.errors import ConfigError, InfoMismatchError
from lidarscan.linkage import InfoResolver

H, W = 4, 16


def _info(stamp_ns: int, tilt: float = 0.0, width: int = W) -> object:
    return ls.make_info(stamp_ns=stamp_ns, frame_id="lidar",
                        vertical_angles=np.linspace(0.3, -0.3, H) + tilt,
                        horizontal_angles=2 * np.pi * (1 - np.arange(width) / width),
                        as_dataclass=True)


def _scan(info: object, stamp_ns: int, value: float = 1.0) -> object:
    return ls.make_scan(info, {"range": np.full((H, int(info.width)), value, np.float32)},
                        stamp_ns, as_dataclass=True)


class Clock:
    def __init__(self) -> None:
        self.now = 0

    def __call__(self) -> int:
        return self.now


def test_scan_after_its_info_is_released_at_once() -> None:
    resolver = InfoResolver()
    info = _info(100)
    assert resolver.add_info(info) == []
    scan = _scan(info, 1_000)
    assert resolver.add_scan(scan) == [(scan, info)]
    assert resolver.take_dropped() == []


def test_scans_before_info_are_held_then_released_in_order() -> None:
    resolver = InfoResolver(max_pending=4)
    info = _info(100)
    scans = [_scan(info, 1_000 + i) for i in range(3)]
    for scan in scans:
        assert resolver.add_scan(scan) == []
    assert resolver.pending == 3
    released = resolver.add_info(info)
    assert [s for s, _ in released] == scans
    assert all(i is info for _, i in released)
    assert resolver.pending == 0


def test_info_that_never_arrives_drops_after_max_wait_with_reason() -> None:
    clock = Clock()
    events: list[str] = []
    resolver = InfoResolver(max_wait_ns=1_000, clock=clock, on_event=events.append)
    scan = _scan(_info(100), 5)
    resolver.add_scan(scan)
    clock.now = 1_000
    resolver.expire()
    assert resolver.pending == 1  # exactly max_wait is still allowed
    clock.now = 1_001
    resolver.expire()
    dropped = resolver.take_dropped()
    assert [d.scan for d in dropped] == [scan]
    assert dropped[0].info_stamp_ns == 100
    assert "did not arrive within" in dropped[0].reason
    assert any("dropped scan stamp=5" in line for line in events)


def test_pending_buffer_is_bounded_oldest_dropped_first() -> None:
    resolver = InfoResolver(max_pending=2, max_wait_ns=None)
    info = _info(100)
    scans = [_scan(info, i) for i in range(3)]
    for scan in scans:
        resolver.add_scan(scan)
    dropped = resolver.take_dropped()
    assert [d.scan for d in dropped] == [scans[0]]
    assert "pending buffer full" in dropped[0].reason
    assert [s for s, _ in resolver.add_info(info)] == scans[1:]


def test_info_change_mid_stream_never_pairs_wrong_geometry() -> None:
    resolver = InfoResolver(max_pending=8)
    info_a, info_b = _info(100), _info(200, tilt=0.1)
    scan_a1, scan_b1 = _scan(info_a, 1), _scan(info_b, 2)
    scan_a2 = _scan(info_a, 3)  # a late scan of the old geometry
    resolver.add_info(info_a)
    assert resolver.add_scan(scan_a1) == [(scan_a1, info_a)]
    assert resolver.add_scan(scan_b1) == []  # B not known yet: held, not paired with A
    assert resolver.add_info(info_b) == [(scan_b1, info_b)]
    assert resolver.add_scan(scan_a2) == [(scan_a2, info_a)]
    # the pairing is by stamp, and the geometries really differ
    p_a, p_b = ls.make_projector(info_a), ls.make_projector(info_b)
    assert not np.allclose(p_a.directions, p_b.directions)


def test_same_stamp_same_content_is_a_no_op() -> None:
    resolver = InfoResolver()
    info = _info(100)
    resolver.add_info(info)
    resolver.add_info(_info(100))  # re-published, equal content
    scan = _scan(info, 1)
    assert len(resolver.add_scan(scan)) == 1
    assert resolver.take_dropped() == []


def test_same_stamp_different_geometry_makes_the_stamp_ambiguous() -> None:
    events: list[str] = []
    resolver = InfoResolver(on_event=events.append)
    resolver.add_info(_info(100))
    held = _scan(_info(300), 1)
    resolver.add_scan(held)
    resolver.add_info(_info(100, tilt=0.2))
    assert any("DIFFERENT geometry" in line for line in events)
    assert resolver.add_scan(_scan(_info(100), 2)) == []
    dropped = resolver.take_dropped()
    assert len(dropped) == 1 and "ambiguous" in dropped[0].reason
    assert resolver.pending == 1  # a scan of another stamp is unaffected


def test_late_info_after_drops_pairs_only_later_scans() -> None:
    clock = Clock()
    resolver = InfoResolver(max_wait_ns=10, clock=clock)
    info = _info(100)
    early = _scan(info, 1)
    resolver.add_scan(early)
    clock.now = 50
    late = _scan(info, 2)
    resolver.add_scan(late)  # expires `early` first
    assert [d.scan for d in resolver.take_dropped()] == [early]
    assert resolver.add_info(info) == [(late, info)]


def test_scan_that_does_not_fit_its_info_is_dropped_with_reason() -> None:
    resolver = InfoResolver()
    info = _info(100)
    resolver.add_info(info)
    wide = _scan(_info(100, width=2 * W), 1)  # names stamp 100 but is 2W wide
    assert resolver.add_scan(wide) == []
    (dropped,) = resolver.take_dropped()
    assert "does not fit its LidarInfo" in dropped.reason and "width" in dropped.reason


def test_old_versions_are_forgotten_beyond_max_infos() -> None:
    resolver = InfoResolver(max_infos=2, max_wait_ns=None)
    infos = [_info(100 * (i + 1), tilt=0.01 * i) for i in range(3)]
    for info in infos:
        resolver.add_info(info)
    assert resolver.info(100) is None and resolver.info(300) is infos[2]
    assert resolver.add_scan(_scan(infos[0], 1)) == []  # held: its version was evicted
    resolver.flush()
    (dropped,) = resolver.take_dropped()
    assert "never arrived" in dropped.reason


def test_holding_disabled_drops_immediately() -> None:
    resolver = InfoResolver(max_pending=0)
    resolver.add_scan(_scan(_info(100), 1))
    assert "holding is disabled" in resolver.take_dropped()[0].reason


def test_malformed_info_is_rejected_and_not_stored() -> None:
    resolver = InfoResolver()
    bad = ls.types.LidarInfo(header=ls.types.Header(ls.types.Time(0, 100), "x"), height=2,
                             width=2, vertical_angles=np.array([0.0, np.nan]),
                             horizontal_angles=np.zeros(2))
    with pytest.raises(InfoMismatchError, match="vertical_angles"):
        resolver.add_info(bad)
    assert resolver.info(100) is None


def test_bad_configuration_is_rejected() -> None:
    with pytest.raises(ConfigError):
        InfoResolver(max_infos=0)
