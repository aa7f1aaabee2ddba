"""Which LidarScan ``lidarscan view`` draws per topic: the ``--index``-th, by default the first
complete rotation.

A recording (or a packet conversion) usually starts in the middle of a rotation: its first scan
covers only part of the turn. A scan's *coverage* is its number of columns with at least one
return (finite range); a scan is *complete* when its coverage is at least
:data:`COMPLETE_FRACTION` of the largest coverage among the topic's first :data:`LOOK_AHEAD`
scans (a sensor with a restricted field of view has columns without returns in every scan, so
the reference is the recording's own, not the width). A chosen scan that is not complete is
drawn with a note saying so.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

#: a scan with this fraction of the best coverage seen is a complete rotation
COMPLETE_FRACTION = 0.95
#: scans per topic looked at to find the best coverage (and the first complete one)
LOOK_AHEAD = 6


def coverage(scan: Any, info: Any) -> int:
    """Columns of ``scan`` with at least one return (finite range > 0)."""
    import numpy as np

    import lidarscan

    ranges = lidarscan.range_m(scan, info)
    return int(np.count_nonzero((np.isfinite(ranges) & (ranges > 0)).any(axis=0)))


@dataclass
class Pick:
    """The scan drawn for one topic: its index in the topic, the note for the title."""

    index: int
    scan: Any
    info: Any
    covered: int
    note: str = ""


@dataclass
class ScanPicker:
    """Feed every linked (scan, info) with :meth:`add`; :meth:`chosen` gives topic -> Pick
    (the topic is the scan's frame_id, as ``view`` names its images)."""

    index: int | None
    counts: dict[str, int] = field(default_factory=dict)
    _first: dict[str, list[Pick]] = field(default_factory=dict)
    _picked: dict[str, Pick] = field(default_factory=dict)

    def add(self, scan: Any, info: Any) -> None:
        topic = scan.header.frame_id
        k = self.counts.get(topic, 0)
        self.counts[topic] = k + 1
        first = self._first.setdefault(topic, [])
        wanted = self.index is not None and k == self.index
        if k < LOOK_AHEAD or wanted:
            pick = Pick(k, scan if self.index is None or wanted else None,
                        info if self.index is None or wanted else None, coverage(scan, info))
            if k < LOOK_AHEAD:
                first.append(pick)
            if wanted:
                self._picked[topic] = pick

    def check_index(self) -> None:
        """ConfigError when ``--index`` is past the last scan of a topic (naming the count)."""
        from lidarscan.errors import ConfigError

        if self.index is None:
            return
        short = {t: n for t, n in self.counts.items() if n <= self.index}
        if short:
            topic, count = min(short.items(), key=lambda tn: tn[1])
            raise ConfigError("--index", self.index, f"an index below {count} (the LidarScans "
                              f"of frame '{topic}' are {count}: 0..{count - 1})")

    def chosen(self) -> dict[str, Pick]:
        """topic -> the Pick to draw, its note saying whether it is complete."""
        out: dict[str, Pick] = {}
        for topic, first in self._first.items():
            best = max(p.covered for p in first)
            enough = COMPLETE_FRACTION * best
            if self.index is None:
                pick = next(p for p in first if p.covered >= enough)
                if pick.index > 0:
                    pick.note = f" (first complete rotation; #0..#{pick.index - 1} partial)"
            else:
                pick = self._picked[topic]
                best = max(best, pick.covered)
                if pick.covered < COMPLETE_FRACTION * best:
                    pick.note = (f" (PARTIAL rotation: {pick.covered} columns with returns, "
                                 f"a complete one has {best})")
            out[topic] = pick
        return out
