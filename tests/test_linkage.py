"""The info-linkage resolver: every case of lidarscan/linkage.py's rules, with two geometries."""

from __future__ import annotations

import numpy as np
import pytest

import lidarscan as ls
from lidarscan.errors import ConfigError, InfoMismatchError
from lidarscan.linkage import InfoResolver

from helpers import Clock

H, W = 4, 16


def _info(stamp_ns: int, tilt: float = 0.0, width: int = W) -> object:
    return ls.make_info(stamp_ns=stamp_ns, frame_id="lidar",
                        vertical_angles=np.linspace(0.3, -0.3, H) + tilt,
                        horizontal_angles=2 * np.pi * (1 - np.arange(width) / width),
                        as_dataclass=True)


def _scan(info: object, stamp_ns: int, value: float = 1.0) -> object:
    return ls.make_scan(info, {"range": np.full((H, int(info.width)), value, np.float32)},
                        stamp_ns, as_dataclass=True)


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


def test_old_versions_are_evicted_beyond_max_infos_and_their_scans_dropped() -> None:
    resolver = InfoResolver(max_infos=2, max_wait_ns=None)
    infos = [_info(100 * (i + 1), tilt=0.01 * i) for i in range(3)]
    for info in infos:
        resolver.add_info(info)
    assert resolver.info(100) is None and resolver.info(300) is infos[2]
    assert resolver.add_scan(_scan(infos[0], 1)) == []  # dropped at once: never held
    assert resolver.pending == 0
    (dropped,) = resolver.take_dropped()
    assert "evicted" in dropped.reason and "max_infos=2" in dropped.reason


def test_a_version_in_use_outlives_newer_ones_it_is_evicted_least_recently_used() -> None:
    """Eviction order is publication OR use: a version whose scans keep coming stays."""
    resolver = InfoResolver(max_infos=2, max_wait_ns=None)
    a, b, c = (_info(100 * (i + 1), tilt=0.01 * i) for i in range(3))
    resolver.add_info(a)
    resolver.add_info(b)
    scan_a = _scan(a, 1)
    assert resolver.add_scan(scan_a) == [(scan_a, a)]  # a used after b was published
    resolver.add_info(c)                                # evicts b, not a
    assert resolver.info(100) is a and resolver.info(200) is None and resolver.info(300) is c


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


@pytest.mark.parametrize("bad", [{"max_infos": 0}, {"max_digests": -1}, {"max_pending": -1},
                                 {"max_wait_ns": -5}, {"max_infos": 2.5}, {"max_pending": None},
                                 {"max_infos": True}])
def test_bad_configuration_is_rejected(bad: dict[str, object]) -> None:
    with pytest.raises(ConfigError, match=next(iter(bad))):
        InfoResolver(**bad)  # type: ignore[arg-type]


# ------------------------------------------------- eviction: remembered digests, watermark

def _digest(info: object) -> str:
    return ls.geometry.info_key(info)[1]


def test_republish_of_an_evicted_stamp_with_other_geometry_is_a_conflict() -> None:
    """Issue 17 defect 4: with max_infos versions kept, a late scan naming an evicted stamp was
    paired with another geometry re-published under that stamp."""
    events: list[str] = []
    resolver = InfoResolver(max_infos=2, max_wait_ns=None, on_event=events.append)
    old = _info(100)
    for k, stamp in enumerate((100, 200, 300)):
        resolver.add_info(_info(stamp, tilt=0.05 * k))
    assert resolver.info(100) is None  # evicted
    assert resolver.add_info(_info(100, tilt=0.3)) == []  # other content under the old stamp
    assert any("evicted version" in e and "DIFFERENT" in e for e in events)
    assert resolver.info(100) is None
    straggler = _scan(old, 5)
    assert resolver.add_scan(straggler) == []
    (dropped,) = resolver.take_dropped()
    assert dropped.scan is straggler and "ambiguous" in dropped.reason
    assert resolver.state()["conflicting"] == 1 and resolver.conflicts == 1


def test_identical_republish_of_an_evicted_version_brings_it_back() -> None:
    resolver = InfoResolver(max_infos=2, max_wait_ns=None)
    infos = [_info(100 * (k + 1), tilt=0.05 * k) for k in range(3)]
    for info in infos:
        resolver.add_info(info)
    again = _info(100)  # equal content, a new object (e.g. a latched topic re-delivered)
    assert resolver.add_info(again) == []
    assert resolver.info(100) is again and resolver.info(200) is None  # 200 evicted now
    scan = _scan(infos[0], 7)
    assert resolver.add_scan(scan) == [(scan, again)]
    assert resolver.take_dropped() == [] and resolver.conflicts == 0


def test_past_the_digest_bound_unknown_old_stamps_fail_safe() -> None:
    events: list[str] = []
    resolver = InfoResolver(max_infos=1, max_digests=2, max_wait_ns=None, on_event=events.append)
    for k in range(6):  # stamps 100..600: 100, 200, 300 forgotten, 400, 500 digests, 600 held
        resolver.add_info(_info(100 * (k + 1), tilt=0.01 * k))
    state = resolver.state()
    assert state["infos"] == 1 and state["digests"] == 3 and resolver.forgotten_ns == 300
    # a straggler of a forgotten version: dropped, never held (its info could come back wrong)
    assert resolver.add_scan(_scan(_info(200, tilt=0.01), 1)) == []
    assert "forgotten watermark 300" in resolver.take_dropped()[0].reason
    # an info under a forgotten stamp is refused, whatever its content
    assert resolver.add_info(_info(300, tilt=0.02)) == []
    assert resolver.info(300) is None and any("watermark" in e for e in events)
    assert resolver.add_scan(_scan(_info(300, tilt=0.02), 2)) == []
    reason = resolver.take_dropped()[0].reason  # its conflict record may itself be forgotten
    assert "ambiguous" in reason or "watermark" in reason
    # a stamp above the watermark never seen is held as usual; memory stays bounded
    assert resolver.add_scan(_scan(_info(650), 3)) == [] and resolver.pending == 1
    for k in range(50):
        resolver.add_info(_info(1_000 + k, tilt=0.001 * k))
    assert resolver.state()["digests"] <= 1 + 2
    assert resolver.pending == 0  # 650 fell below the watermark: dropped, not kept forever
    assert "watermark" in resolver.take_dropped()[-1].reason


def test_held_scan_of_a_stamp_that_becomes_conflicting_is_dropped() -> None:
    resolver = InfoResolver(max_wait_ns=None)
    resolver.add_info(_info(100))
    held = _scan(_info(300), 1)
    resolver.add_scan(held)
    resolver.add_info(_info(300))
    assert resolver.pending == 0  # released
    resolver.add_scan(_scan(_info(400), 2))
    resolver.add_info(_info(100, tilt=0.4))  # conflict on 100 does not touch 400
    assert resolver.pending == 1 and resolver.take_dropped() == []


def test_reconfiguring_stream_with_stragglers_pairs_no_wrong_geometry() -> None:
    """20 versions through the default resolver (8 kept): each version's stragglers arrive
    after 9 newer versions, and every other evicted stamp is re-published with the geometry of
    a newer version (a driver restarting with a reused stamp). 0 wrong pairs; every scan
    released or reported once."""
    resolver = InfoResolver(max_wait_ns=None)
    truth: dict[int, str] = {}
    sent, released, wrong = 0, 0, 0
    dropped: list[str] = []

    def check(pairs: list[tuple[object, object]]) -> None:
        nonlocal released, wrong
        for scan, info in pairs:
            released += 1
            stamp = ls.to_ns(scan.lidar_info_time)
            wrong += ls.to_ns(info.header.stamp) != stamp or _digest(info) != truth[stamp]

    for k in range(20):
        info = _info(1_000 * (k + 1), tilt=0.02 * k)
        truth[1_000 * (k + 1)] = _digest(info)
        check(resolver.add_info(info))
        for j in range(3):
            sent += 1
            check(resolver.add_scan(_scan(info, 10 * k + j)))
        if k >= 9:
            old = 1_000 * (k - 8)
            if k % 2:
                check(resolver.add_info(_info(old, tilt=0.02 * k)))  # conflicting republish
            sent += 1
            check(resolver.add_scan(_scan(_info(old, tilt=0.02 * (k - 9)), 10_000 + k)))
    resolver.flush()
    dropped = [d.reason for d in resolver.take_dropped()]
    assert wrong == 0
    assert released + len(dropped) == sent
    assert len(dropped) == 11 and all("evicted" in r or "ambiguous" in r for r in dropped)


# ---------------------------------------------------------------- state machine (hypothesis)

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from hypothesis.stateful import (  # noqa: E402
    RuleBasedStateMachine,
    initialize,
    invariant,
    precondition,
    rule,
)

GEOMETRIES = [_info(0, tilt=0.03 * g) for g in range(4)]
STAMPS = st.integers(1, 14).map(lambda k: 100 * k)


class ResolverMachine(RuleBasedStateMachine):
    """Random publications (new stamps, identical and conflicting republishes, stamps below the
    watermark), scans naming any stamp, clock ticks, tiny bounds. The world: each stamp has
    one TRUE geometry, the first one published under it (or fixed when its first scan is
    made); scans are made with it. Checked after every step: every released pair is (scan, the
    info of its stamp with the true geometry) and that stamp never carried two contents; at the
    end every scan was released once or dropped once."""

    @initialize(max_infos=st.integers(1, 3), max_digests=st.integers(0, 3),
                max_pending=st.integers(0, 4), max_wait=st.sampled_from([None, 5, 50]))
    def setup(self, max_infos: int, max_digests: int, max_pending: int,
              max_wait: int | None) -> None:
        self.clock = Clock()
        self.resolver = InfoResolver(max_infos=max_infos, max_digests=max_digests,
                                     max_pending=max_pending, max_wait_ns=max_wait,
                                     clock=self.clock)
        self.true: dict[int, int] = {}          # stamp -> geometry index
        self.published: dict[int, set[int]] = {}  # stamp -> geometries ever published
        self.outcome: dict[int, str] = {}       # scan id -> released / dropped
        self.scans = 0

    def _check(self, pairs: list[tuple[object, object]]) -> None:
        for scan, info in pairs:
            stamp = ls.to_ns(scan.lidar_info_time)
            assert ls.to_ns(info.header.stamp) == stamp
            assert _digest(info) == _digest(GEOMETRIES[self.true[stamp]]), "wrong geometry"
            assert len(self.published[stamp]) == 1, "paired under an ambiguous stamp"
            sid = ls.to_ns(scan.header.stamp)
            assert sid not in self.outcome, "released twice"
            self.outcome[sid] = "released"
        for d in self.resolver.take_dropped():
            assert d.stamp_ns not in self.outcome, "dropped twice"
            self.outcome[d.stamp_ns] = "dropped"

    @rule(stamp=STAMPS, geometry=st.integers(0, 3), same=st.booleans())
    def publish(self, stamp: int, geometry: int, same: bool) -> None:
        if stamp in self.true and (same or stamp not in self.published):
            geometry = self.true[stamp]  # an identical republish / the first publication
        self.true.setdefault(stamp, geometry)
        self.published.setdefault(stamp, set()).add(geometry)
        info = _info(stamp, tilt=0.03 * geometry)
        self._check(self.resolver.add_info(info))

    @rule(stamp=STAMPS, geometry=st.integers(0, 3))
    def scan(self, stamp: int, geometry: int) -> None:
        g = self.true.setdefault(stamp, geometry)
        self.scans += 1
        scan = _scan(_info(stamp, tilt=0.03 * g), self.scans)
        self._check(self.resolver.add_scan(scan))

    @rule(dt=st.integers(0, 30))
    def tick(self, dt: int) -> None:
        self.clock.now += dt
        self.resolver.expire()
        self._check([])

    @invariant()
    def bounded(self) -> None:
        if hasattr(self, "resolver"):
            r = self.resolver
            assert r.pending <= r.max_pending
            assert r.state()["infos"] <= r.max_infos
            assert r.state()["digests"] <= r.max_infos + r.max_digests

    @precondition(lambda self: hasattr(self, "resolver"))
    @rule()
    def teardown_check(self) -> None:
        pending = self.resolver.pending
        accounted = len(self.outcome)
        assert accounted + pending == self.scans


ResolverMachine.TestCase.settings = settings(max_examples=150, stateful_step_count=40,
                                             deadline=None)
test_resolver_state_machine = ResolverMachine.TestCase


def test_resolver_state_machine_flush_accounts_for_every_scan() -> None:
    """The teardown rule above checks the running count; this checks flush() empties it."""
    resolver = InfoResolver(max_pending=3, max_wait_ns=None)
    for k in range(5):
        resolver.add_scan(_scan(_info(100 + k), k))
    resolver.flush()
    assert len(resolver.take_dropped()) == 5 and resolver.pending == 0
