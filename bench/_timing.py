"""Timing shared by the benchmarks: candidates interleaved round after round."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np


def interleaved_times(candidates: dict[str, Callable[[], Any]], rounds: int, seed: int = 0,
                      clock: Callable[[], float] = time.perf_counter) -> dict[str, list[float]]:
    """Seconds of every call of each candidate, run once first (warm-up, not timed), then in
    turn round after round (shared machine load hits all alike), in a new random order every
    round: what ran just before decides what is left in the caches, so a fixed order would
    always hand one candidate the leftovers of the same (heavy) predecessor. ``clock``: wall
    time by default; ``time.process_time`` for CPU time on a shared machine."""
    times: dict[str, list[float]] = {name: [] for name in candidates}
    order = list(candidates)
    shuffle = np.random.default_rng(seed).shuffle
    for fn in candidates.values():
        fn()
    for _ in range(rounds):
        shuffle(order)
        for name in order:
            fn = candidates[name]
            start = clock()
            fn()
            times[name].append(clock() - start)
    return times
