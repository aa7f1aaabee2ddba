"""The info-linkage resolver: pair each LidarScan with the LidarInfo its ``lidar_info_time`` names.

Rules (each pinned by ``tests/test_linkage.py``):

* infos are kept by stamp (the version key), the newest ``max_infos`` versions;
* a scan whose info is known is released at once, after :func:`lidarscan.validate` of the pair
  (a pair that does not fit is dropped with the reason);
* a scan whose info is unknown is held, at most ``max_pending`` scans (the oldest is dropped
  when full) and at most ``max_wait_ns`` (checked on every call and by :meth:`expire`); when its
  info arrives it is released, in arrival order;
* an info re-published with the same stamp and the same content changes nothing; one with the
  same stamp and *different* content makes that stamp ambiguous: it is marked conflicting and
  every scan naming it is dropped (never paired with possibly wrong geometry);
* a scan is never paired with an info of another stamp.

Drops are kept as :class:`Dropped` records (``take_dropped()``) and passed to ``on_event`` with a
one-line reason, so a node can log one clear line per case.
"""

from __future__ import annotations

import time
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from lidarscan.errors import LidarScanError
from lidarscan.geometry import info_key
from lidarscan.scan import validate, validate_info
from lidarscan.stamps import to_ns

__all__ = ["InfoResolver", "Dropped"]


@dataclass(frozen=True)
class Dropped:
    """A scan the resolver gave up on.

    Attributes:
        scan: the scan message.
        stamp_ns: the scan's header.stamp.
        info_stamp_ns: the ``lidar_info_time`` it names.
        reason: one line for a log.
    """

    scan: Any
    stamp_ns: int
    info_stamp_ns: int
    reason: str


class InfoResolver:
    """Holds LidarInfo versions and releases scans paired with their own info.

    Args:
        max_infos: info versions kept (older ones are forgotten).
        max_pending: scans held while their info is missing.
        max_wait_ns: how long a scan may wait for its info (``None``: no time limit, e.g. when
            reading a file; then only ``max_pending`` and :meth:`flush` bound the wait).
        clock: ``() -> int`` ns used when a call passes no ``now_ns`` (default monotonic).
        on_event: called with one line per notable event (drop, conflict, info change).
    """

    def __init__(self, *, max_infos: int = 8, max_pending: int = 16,
                 max_wait_ns: int | None = 2_000_000_000,
                 clock: Callable[[], int] = time.monotonic_ns,
                 on_event: Callable[[str], None] | None = None) -> None:
        if max_infos < 1 or max_pending < 0:
            from lidarscan.errors import ConfigError
            raise ConfigError("max_infos/max_pending", (max_infos, max_pending), ">= 1 / >= 0")
        self.max_infos, self.max_pending, self.max_wait_ns = max_infos, max_pending, max_wait_ns
        self._clock = clock
        self._on_event = on_event
        self._infos: OrderedDict[int, tuple[Any, tuple[int, str]]] = OrderedDict()
        self._conflicts: set[int] = set()
        self._pending: deque[tuple[int, Any, int]] = deque()  # (info stamp, scan, arrival ns)
        self._dropped: list[Dropped] = []
        self.latest_stamp_ns: int | None = None
        self.released = 0

    # ------------------------------------------------------------------------------ events
    def _event(self, line: str) -> None:
        if self._on_event is not None:
            self._on_event(line)

    def _drop(self, scan: Any, info_stamp: int, reason: str) -> None:
        stamp = to_ns(scan.header.stamp)
        record = Dropped(scan, stamp, info_stamp, reason)
        self._dropped.append(record)
        self._event(f"dropped scan stamp={stamp} (lidar_info_time={info_stamp}): {reason}")

    def take_dropped(self) -> list[Dropped]:
        """Drop records since the last call (and forget them)."""
        out, self._dropped = self._dropped, []
        return out

    @property
    def pending(self) -> int:
        """Number of scans waiting for their info."""
        return len(self._pending)

    def info(self, stamp_ns: int) -> Any | None:
        """The info of that version, if held and not conflicting."""
        if stamp_ns in self._conflicts:
            return None
        entry = self._infos.get(stamp_ns)
        return entry[0] if entry else None

    # ------------------------------------------------------------------------------- input
    def add_info(self, info: Any, now_ns: int | None = None) -> list[tuple[Any, Any]]:
        """Add a LidarInfo version; returns the held scans it releases as (scan, info) pairs.

        Raises:
            InfoMismatchError: the info itself is malformed (it is not stored).
        """
        validate_info(info)
        stamp = to_ns(info.header.stamp)
        key = info_key(info)
        known = self._infos.get(stamp)
        if known is not None and known[1] != key:
            if stamp not in self._conflicts:
                self._conflicts.add(stamp)
                self._event(f"LidarInfo stamp={stamp} re-published with DIFFERENT geometry: "
                            "scans naming this stamp are dropped (publish a new stamp on change)")
            self._release_conflicts()
            return []
        if known is None:
            if self.latest_stamp_ns is not None and stamp != self.latest_stamp_ns:
                self._event(f"LidarInfo changed: stamp {self.latest_stamp_ns} -> {stamp}")
            self._infos[stamp] = (info, key)
            while len(self._infos) > self.max_infos:
                self._infos.popitem(last=False)
        else:
            self._infos.move_to_end(stamp)
        if self.latest_stamp_ns is None or stamp >= self.latest_stamp_ns:
            self.latest_stamp_ns = stamp
        return self._release(now_ns)

    def add_scan(self, scan: Any, now_ns: int | None = None) -> list[tuple[Any, Any]]:
        """Add a scan; returns the (scan, info) pairs ready now (this one and/or none)."""
        now = self._clock() if now_ns is None else now_ns
        wanted = to_ns(scan.lidar_info_time, field="LidarScan.lidar_info_time")
        self._expire(now)
        if wanted in self._conflicts:
            self._drop(scan, wanted, "its LidarInfo stamp is ambiguous (two geometries)")
            return []
        entry = self._infos.get(wanted)
        if entry is not None:
            return self._pair(scan, entry[0])
        if self.max_pending == 0:
            self._drop(scan, wanted, "its LidarInfo is unknown and holding is disabled")
            return []
        if len(self._pending) >= self.max_pending:
            _, oldest, _ = self._pending.popleft()
            self._drop(oldest, to_ns(oldest.lidar_info_time),
                       f"pending buffer full ({self.max_pending} scans) before its LidarInfo came")
        self._pending.append((wanted, scan, now))
        return []

    def expire(self, now_ns: int | None = None) -> None:
        """Drop held scans that waited longer than ``max_wait_ns``."""
        self._expire(self._clock() if now_ns is None else now_ns)

    def flush(self) -> None:
        """Drop every held scan (end of a recording / shutdown)."""
        while self._pending:
            wanted, scan, _ = self._pending.popleft()
            self._drop(scan, wanted, "its LidarInfo never arrived")

    # ---------------------------------------------------------------------------- internal
    def _pair(self, scan: Any, info: Any) -> list[tuple[Any, Any]]:
        try:
            validate(scan, info)
        except LidarScanError as err:
            self._drop(scan, to_ns(scan.lidar_info_time), f"does not fit its LidarInfo: {err}")
            return []
        self.released += 1
        return [(scan, info)]

    def _expire(self, now: int) -> None:
        if self.max_wait_ns is None:
            return
        while self._pending and now - self._pending[0][2] > self.max_wait_ns:
            wanted, scan, _ = self._pending.popleft()
            self._drop(scan, wanted, f"its LidarInfo did not arrive within "
                       f"{self.max_wait_ns / 1e9:g} s")

    def _release(self, now_ns: int | None) -> list[tuple[Any, Any]]:
        self._expire(self._clock() if now_ns is None else now_ns)
        out: list[tuple[Any, Any]] = []
        keep: deque[tuple[int, Any, int]] = deque()
        for wanted, scan, arrived in self._pending:
            entry = self._infos.get(wanted)
            if entry is not None and wanted not in self._conflicts:
                out.extend(self._pair(scan, entry[0]))
            else:
                keep.append((wanted, scan, arrived))
        self._pending = keep
        return out

    def _release_conflicts(self) -> None:
        keep: deque[tuple[int, Any, int]] = deque()
        for wanted, scan, arrived in self._pending:
            if wanted in self._conflicts:
                self._drop(scan, wanted, "its LidarInfo stamp is ambiguous (two geometries)")
            else:
                keep.append((wanted, scan, arrived))
        self._pending = keep
