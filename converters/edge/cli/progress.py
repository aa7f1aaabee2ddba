"""The progress view and the summary table of a fleet ``convert`` (:mod:`converters.edge.cli.fleet`):
one bar over every recording's input bytes (rate, ETA) on a terminal, one line per 10 %
otherwise; then one row per recording."""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence
from typing import IO, Any

from converters.edge.cli._common import Progress
from converters.edge.cli._describe import human_size as human


def clock(seconds: float) -> str:
    seconds = int(max(seconds, 0))
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


class FleetProgress:
    """Progress of a fleet run on stderr, in input bytes: ``sizes`` maps each recording to
    convert (job index) to its input size; ``count`` is the number of recordings of the run
    (also those skipped)."""

    def __init__(self, sizes: dict[int, int], count: int, *, enabled: bool = True,
                 stream: IO[str] | None = None) -> None:
        self.sizes = sizes
        self.done: dict[int, float] = {}
        self.finished = count - len(sizes)
        self.count = count
        self.start = time.monotonic()
        self.bar = Progress(sum(sizes.values()), f"converting {len(sizes)} of {count} "
                            "recordings", stream=stream or sys.stderr, enabled=enabled)
        self.tty = self.bar.enabled and not self.bar.lines

    def advance(self, index: int, fraction: float, *, force: bool = False) -> None:
        """Recording ``index`` is ``fraction`` (0..1) done."""
        self.done[index] = max(self.done.get(index, 0.0), fraction)
        done = sum(self.sizes.get(i, 0) * f for i, f in self.done.items())
        elapsed = time.monotonic() - self.start
        rate = done / elapsed if elapsed > 0 else 0.0
        eta = (self.bar.total - done) / rate if rate > 0 else 0.0
        self.bar.update(int(done), f"{self.finished}/{self.count} done, {human(done)}, "
                        f"{human(rate)}/s, ETA {clock(eta)}", force=force)

    def finish(self, index: int) -> None:
        self.finished += 1
        self.advance(index, 1.0, force=True)

    def note(self, line: str) -> None:
        """A message line, above the bar."""
        stream = self.bar.stream
        stream.write(("\r\x1b[K" if self.tty and self.bar._shown else "") + line + "\n")
        stream.flush()

    def close(self) -> None:
        self.bar.close()


def table(rows: Sequence[tuple[Any, Any, str]], seconds: float, *, quiet: bool = False
          ) -> list[str]:
    """Lines of the summary: one row per (job, result, note) then a total line; ``quiet``:
    only the rows that are not ok, and the total line only when there are such rows."""
    head = ("recording", "input", "output", "ratio", "messages", "seconds", "status")
    body = []
    for job, result, note in rows:
        if quiet and result.status in ("ok", "redone", "skipped"):
            continue
        ratio = f"{result.out_size / job.size:.2f}" if result.out_size and job.size else "-"
        why = "; ".join(w for w in (note, result.reason) if w)
        body.append((job.rel, human(job.size), human(result.out_size) if result.out_size
                     else "-", ratio, str(result.read) if result.read else "-",
                     f"{result.seconds:.1f}", result.status + (f": {why}" if why else "")))
    if quiet and not body:
        return []
    widths = [max(len(r[k]) for r in [head, *body]) for k in range(len(head) - 1)]
    lines = ["  ".join(c.ljust(w) if k == 0 else c.rjust(w)
                       for k, (c, w) in enumerate(zip(r, widths))) + "  " + r[-1]
             for r in [head, *body]]
    counts: dict[str, int] = {}
    for _, result, _ in rows:
        counts[result.status] = counts.get(result.status, 0) + 1
    size_in = sum(job.size for job, _, _ in rows)
    size_out = sum(result.out_size for _, result, _ in rows)
    lines.append(f"{len(rows)} recordings: " + ", ".join(f"{n} {s}" for s, n in
                                                        sorted(counts.items()))
                 + f"; {human(size_in)} -> {human(size_out)} in {seconds:.1f} s")
    return lines
