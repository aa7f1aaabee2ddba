"""The info-linkage resolver: pair each LidarScan with the LidarInfo its ``lidar_info_time`` names.

Guarantee: **a scan is released only with the one content ever seen under its stamp.** A scan
is never paired with an info of another stamp, nor with an info whose stamp has carried two
different contents (as far back as the resolver remembers), nor with an info whose stamp may have
been forgotten. When the resolver cannot be sure, the scan is dropped and reported; it never
guesses. Rules (each pinned by ``tests/test_linkage.py``):

* the ``max_infos`` versions most recently published *or paired with a scan* are kept whole
  and can be paired (so every sensor still sending scans keeps its version, however many other
  sensors or versions a shared resolver -- e.g. one reading a multi-sensor recording -- sees);
* a version pushed out of them is *evicted*: its info is forgotten but its content digest
  (:func:`lidarscan.geometry.info_key`, 16 bytes) is remembered, for at most ``max_digests``
  evicted versions. A scan naming an evicted version is dropped ("evicted"); the same content
  re-published under that stamp brings the version back; other content makes it a conflict;
* past ``max_digests`` the evicted version with the smallest stamp is forgotten entirely and
  the *forgotten watermark* rises to its stamp. A stamp at or below the watermark that the
  resolver does not remember might be a forgotten version: a scan naming it is dropped and an
  info published under it is refused (recorded as a conflict) -- fail safe, never a guess.
  Senders publish a new, later stamp for a new geometry, so this only hits a sender that goes
  back in time after more than ``max_infos + max_digests`` versions (then restart the resolver);
* an info re-published with the same stamp and the same content changes nothing; one with the
  same stamp and *different* content makes that stamp ambiguous: it is marked conflicting (a
  conflict is remembered like any other version, within the same bound) and every scan naming
  it, held or arriving later, is dropped;
* a scan whose info is known is released at once, after :func:`lidarscan.validate` of the
  pair (a pair that does not fit is dropped with the reason);
* a scan whose info is unknown (a stamp above the watermark never seen) is held, at most
  ``max_pending`` scans (the oldest is dropped when full) and at most ``max_wait_ns`` (checked
  on every call and by :meth:`expire`); when its info arrives it is released, in arrival order.

Memory is bounded: ``max_infos`` infos, ``max_infos + max_digests`` digests, ``max_pending``
scans. Drops are kept as :class:`Dropped` records (``take_dropped()``) and passed to
``on_event`` with a one-line reason, so a node can log one clear line per case; :meth:`state`
summarises the resolver for diagnostics.
"""

from __future__ import annotations

import heapq
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

#: Marker of a conflicting stamp in the digest memory.
_CONFLICT = "conflict"


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
    """Holds LidarInfo versions and releases scans paired with their own info (module docstring:
    the guarantee and every rule).

    Args:
        max_infos: info versions kept whole (pairable); the least recently published or used
            is evicted to a digest.
        max_digests: evicted versions whose content digest is remembered; past it the smallest
            stamp is forgotten and the forgotten watermark rises (fail safe, see the module).
        max_pending: scans held while their info is missing.
        max_wait_ns: how long a scan may wait for its info (``None``: no time limit, e.g. when
            reading a file; then only ``max_pending`` and :meth:`flush` bound the wait).
        clock: ``() -> int`` ns used when a call passes no ``now_ns`` (default monotonic).
        on_event: called with one line per notable event (drop, conflict, info change).

    Raises:
        ConfigError: a bound below its minimum (max_infos >= 1, max_digests >= 0,
            max_pending >= 0, max_wait_ns >= 0 or None).
    """

    def __init__(self, *, max_infos: int = 8, max_digests: int = 4096, max_pending: int = 16,
                 max_wait_ns: int | None = 2_000_000_000,
                 clock: Callable[[], int] = time.monotonic_ns,
                 on_event: Callable[[str], None] | None = None) -> None:
        from lidarscan.errors import ConfigError

        for name, value, low in (("max_infos", max_infos, 1), ("max_digests", max_digests, 0),
                                 ("max_pending", max_pending, 0)):
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise ConfigError(name, value, f"an integer >= {low}")
        if max_wait_ns is not None and (isinstance(max_wait_ns, bool) or
                                        not isinstance(max_wait_ns, int) or max_wait_ns < 0):
            raise ConfigError("max_wait_ns", max_wait_ns, "an integer >= 0 (ns) or None")
        self.max_infos, self.max_digests = max_infos, max_digests
        self.max_pending, self.max_wait_ns = max_pending, max_wait_ns
        self._clock = clock
        self._on_event = on_event
        self._infos: OrderedDict[int, Any] = OrderedDict()  # pairable, least recently used first
        self._digests: dict[int, str] = {}  # every remembered stamp -> digest or _CONFLICT
        self._pending: deque[tuple[int, Any, int]] = deque()  # (info stamp, scan, arrival ns)
        self._dropped: list[Dropped] = []
        self.latest_stamp_ns: int | None = None
        #: the largest stamp forgotten entirely (None: nothing forgotten yet)
        self.forgotten_ns: int | None = None
        self.released = 0
        self.conflicts = 0
        self.dropped_total = 0

    # ------------------------------------------------------------------------------ events
    def _event(self, line: str) -> None:
        if self._on_event is not None:
            self._on_event(line)

    def _drop(self, scan: Any, info_stamp: int, reason: str) -> None:
        stamp = to_ns(scan.header.stamp)
        record = Dropped(scan, stamp, info_stamp, reason)
        self._dropped.append(record)
        self.dropped_total += 1
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
        """The info of that version, if held (not evicted) and not conflicting."""
        return self._infos.get(stamp_ns)

    def state(self) -> dict[str, Any]:
        """Counters and sizes for diagnostics: held infos, remembered digests, conflicting
        stamps remembered, pending scans, released / dropped totals, latest and forgotten
        stamps."""
        return {"infos": len(self._infos), "digests": len(self._digests),
                "conflicting": sum(1 for d in self._digests.values() if d == _CONFLICT),
                "conflicts": self.conflicts, "pending": len(self._pending),
                "released": self.released, "dropped": self.dropped_total,
                "latest_stamp_ns": self.latest_stamp_ns, "forgotten_ns": self.forgotten_ns}

    def _unsafe(self, stamp: int) -> str | None:
        """Why a scan naming ``stamp`` cannot be paired now and never will be (None: it is
        held or paired)."""
        digest = self._digests.get(stamp)
        if digest == _CONFLICT:
            return "its LidarInfo stamp is ambiguous (two geometries)"
        if digest is not None and stamp not in self._infos:
            return (f"its LidarInfo version was evicted (more than max_infos={self.max_infos} "
                    "versions published or used since)")
        if digest is None and self.forgotten_ns is not None and stamp <= self.forgotten_ns:
            return (f"its LidarInfo stamp is at or below the forgotten watermark "
                    f"{self.forgotten_ns} (more than max_infos + max_digests = "
                    f"{self.max_infos + self.max_digests} versions since): it may be a "
                    "forgotten version")
        return None

    # ------------------------------------------------------------------------------- input
    def add_info(self, info: Any, now_ns: int | None = None) -> list[tuple[Any, Any]]:
        """Add a LidarInfo version; returns the held scans it releases as (scan, info) pairs.

        Raises:
            InfoMismatchError: the info itself is malformed (it is not stored).
        """
        validate_info(info)
        stamp, digest = info_key(info)
        known = self._digests.get(stamp)
        if known == _CONFLICT:
            return self._release(now_ns)
        if known is None and self.forgotten_ns is not None and stamp <= self.forgotten_ns:
            self._conflict(stamp, f"LidarInfo stamp={stamp} is at or below the forgotten "
                           f"watermark {self.forgotten_ns}: it cannot be told from a forgotten "
                           "version, so it is refused and scans naming it are dropped (publish "
                           "a later stamp)")
            return self._release(now_ns)
        if known is not None and known != digest:
            where = "" if stamp in self._infos else " (an evicted version)"
            self._conflict(stamp, f"LidarInfo stamp={stamp}{where} re-published with DIFFERENT "
                           "geometry: scans naming this stamp are dropped (publish a new stamp "
                           "on change)")
            return self._release(now_ns)
        if known is None:
            if self.latest_stamp_ns is not None and stamp != self.latest_stamp_ns:
                self._event(f"LidarInfo changed: stamp {self.latest_stamp_ns} -> {stamp}")
            self._digests[stamp] = digest
        self._infos[stamp] = info  # new, or an evicted version re-published identically
        self._infos.move_to_end(stamp)
        while len(self._infos) > self.max_infos:
            self._infos.popitem(last=False)  # evicted: its digest stays
        self._forget()
        if self.latest_stamp_ns is None or stamp >= self.latest_stamp_ns:
            self.latest_stamp_ns = stamp
        return self._release(now_ns)

    def add_scan(self, scan: Any, now_ns: int | None = None) -> list[tuple[Any, Any]]:
        """Add a scan; returns the (scan, info) pairs ready now (this one and/or none)."""
        now = self._clock() if now_ns is None else now_ns
        wanted = to_ns(scan.lidar_info_time, field="LidarScan.lidar_info_time")
        self._expire(now)
        why = self._unsafe(wanted)
        if why is not None:
            self._drop(scan, wanted, why)
            return []
        info = self._infos.get(wanted)
        if info is not None:
            return self._pair(scan, info)
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
    def _conflict(self, stamp: int, line: str) -> None:
        self._digests[stamp] = _CONFLICT
        self._infos.pop(stamp, None)
        self.conflicts += 1
        self._event(line)
        self._forget()

    def _forget(self) -> None:
        """Keep at most ``max_digests`` digests besides the held infos: forget the smallest
        evicted stamps and raise the watermark to them."""
        excess = len(self._digests) - len(self._infos) - self.max_digests
        if excess <= 0:
            return
        for stamp in heapq.nsmallest(excess, (s for s in self._digests if s not in self._infos)):
            del self._digests[stamp]
            if self.forgotten_ns is None or stamp > self.forgotten_ns:
                self.forgotten_ns = stamp

    def _pair(self, scan: Any, info: Any) -> list[tuple[Any, Any]]:
        stamp = to_ns(scan.lidar_info_time)
        try:
            validate(scan, info)
        except LidarScanError as err:
            self._drop(scan, stamp, f"does not fit its LidarInfo: {err}")
            return []
        self._infos.move_to_end(stamp)  # in use: the last to be evicted
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
        """Pair held scans whose info is now known; drop those that became unsafe."""
        self._expire(self._clock() if now_ns is None else now_ns)
        out: list[tuple[Any, Any]] = []
        keep: deque[tuple[int, Any, int]] = deque()
        for wanted, scan, arrived in self._pending:
            why = self._unsafe(wanted)
            if why is not None:
                self._drop(scan, wanted, why)
                continue
            info = self._infos.get(wanted)
            if info is not None:
                out.extend(self._pair(scan, info))
            else:
                keep.append((wanted, scan, arrived))
        self._pending = keep
        return out
