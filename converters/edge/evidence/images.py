"""Question 2b: the image alternative, one ``sensor_msgs/Image`` per channel, vs one LidarScan.

Sizes: the CDR bytes of the images :func:`converters.images.to_images` makes from the real
frames (destaggered, one image per channel, lossless) against the LidarScan's, and what the
images cannot carry. Transport (timing block): serialize, publish -> callback through real rclpy
(:class:`converters.edge.evidence.transport._Ros`, the transport section's harness) for the N images
of a frame vs its one LidarScan, plus the conversions.

Synchronisation: a receiver of N image topics needs a synchroniser to rebuild a frame. The two
policies of ``message_filters`` as its Python package implements them are rewritten here from
their documented semantics (:class:`ExactTimeSync`: a set is emitted when every topic has a
message of the same stamp, per-topic queues of ``queue_size`` drop their oldest;
:class:`ApproximateTimeSync`: on every arrival, the first combination of queued messages, one
per other topic, each within ``slop`` of the new message and spanning less than ``slop``, is
emitted and every message up to it is removed). A deterministic simulation feeds them frames
at 10 Hz, images arriving in channel order, each image lost with probability p (seeded), and
counts frames delivered whole, lost, and delivered *mixed* (images of different frames).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from functools import lru_cache
from typing import Any

import numpy as np

from converters.edge.evidence._common import Block, fmt_int, have, pending, table, time_call

__all__ = ["ApproximateTimeSync", "ExactTimeSync", "blocks", "simulate"]

PERIOD_NS = 100_000_000  # 10 Hz
FRAMES = 2000
DROP_P = (0.001, 0.01, 0.05)
SLOPS_S = (0.05, 0.15)


class _Policy:
    """Per-topic queues (stamp ns -> message) of at most ``queue_size``, oldest dropped."""

    def __init__(self, n: int, queue_size: int, callback: Callable[..., None]) -> None:
        self.queues: list[dict[int, Any]] = [{} for _ in range(n)]
        self.queue_size = queue_size
        self.callback = callback

    def _enqueue(self, msg: Any, stamp: int, index: int) -> None:
        queue = self.queues[index]
        queue[stamp] = msg
        while len(queue) > self.queue_size:
            del queue[min(queue)]


class ExactTimeSync(_Policy):
    """``message_filters.TimeSynchronizer`` semantics: equal stamps on every topic."""

    def add(self, msg: Any, stamp: int, index: int) -> None:
        self._enqueue(msg, stamp, index)
        common = set.intersection(*(set(q) for q in self.queues))
        for t in sorted(common):
            self.callback(*(q[t] for q in self.queues))
            for q in self.queues:
                del q[t]


class ApproximateTimeSync(_Policy):
    """``message_filters.ApproximateTimeSynchronizer`` (Python) semantics, stamps in ns."""

    def __init__(self, n: int, queue_size: int, slop_ns: int,
                 callback: Callable[..., None]) -> None:
        super().__init__(n, queue_size, callback)
        self.slop = slop_ns

    def add(self, msg: Any, stamp: int, index: int) -> None:
        self._enqueue(msg, stamp, index)
        others = [q for i, q in enumerate(self.queues) if i != index]
        candidates = []
        for q in others:
            near = sorted((abs(s - stamp), s) for s in q if abs(s - stamp) <= self.slop)
            if not near:
                return
            candidates.append([s for _, s in near])
        for combo in itertools.product(*candidates):
            stamps = list(combo)
            stamps.insert(index, stamp)
            if max(stamps) - min(stamps) < self.slop and all(
                    t in q for q, t in zip(self.queues, stamps)):
                self.callback(*(q[t] for q, t in zip(self.queues, stamps)))
                for q, t in zip(self.queues, stamps):
                    for old in [s for s in q if s <= t]:
                        del q[old]
                break


def simulate(n_topics: int, drop_p: float, make: Callable[[Callable[..., None]], Any],
             frames: int = FRAMES, seed: int = 7) -> dict[str, int]:
    """Feed ``frames`` frames of ``n_topics`` images (message = its frame number) to the
    synchroniser ``make(callback)``; each image lost with probability ``drop_p``.

    Returns:
        {"whole": sets of one frame, "mixed": sets mixing frames, "lost": frames never delivered
        whole, "dropped": images lost, "frames_hit": frames with at least one image lost}.
    """
    rng = np.random.default_rng(seed)
    sets: list[tuple[int, ...]] = []
    sync = make(lambda *msgs: sets.append(tuple(msgs)))
    dropped = rng.random((frames, n_topics)) < drop_p
    for f in range(frames):
        for i in range(n_topics):
            if not dropped[f, i]:
                sync.add(f, f * PERIOD_NS, i)
    whole = {s[0] for s in sets if len(set(s)) == 1}
    return {"whole": len(whole), "mixed": sum(1 for s in sets if len(set(s)) > 1),
            "lost": frames - len(whole), "dropped": int(dropped.sum()),
            "frames_hit": int(dropped.any(axis=1).sum())}


def _frames() -> list[tuple[str, Any, Any]]:
    from converters.edge.evidence.compression import real_scans
    return [(label, info, scan) for label, info, scan, _ in real_scans()]


@lru_cache(maxsize=1)
def measure_sizes() -> list[dict[str, Any]]:
    """Per real frame: LidarScan CDR bytes, the images' CDR bytes, image count, lossless."""
    import lidarscan as ls
    from converters.images import from_images, to_images
    out = []
    for label, info, scan in _frames():
        imgs = to_images(scan, info, as_dataclass=True)
        back = from_images(imgs, info, is_destaggered=bool(scan.is_destaggered),
                           datatypes={c.name: 6 for c in scan.channels if c.datatype == 6},
                           column_time_offsets=scan.column_time_offsets, as_dataclass=True)
        out.append({"label": label, "n": len(imgs), "scan": len(ls.encode(scan)),
                    "images": sum(len(ls.encode(i)) for i in imgs.values()),
                    "image_each": {k: len(ls.encode(i)) for k, i in imgs.items()},
                    "lossless": ls.encode(back) == ls.encode(scan),
                    "column_arrays": 8 * int(scan.width) * (1 + (len(scan.column_azimuth_angles)
                                                                 > 0))})
    return out


@lru_cache(maxsize=1)
def measure_sync() -> list[dict[str, Any]]:
    """Synchroniser simulation per channel count of the real frames, drop rate and policy."""
    counts = sorted({rec["n"] for rec in measure_sizes()})
    rows = []
    for n in counts:
        for p in DROP_P:
            cases: list[tuple[str, Callable[[Callable[..., None]], Any]]] = [
                ("ExactTime (queue 10)", lambda cb: ExactTimeSync(n, 10, cb))]
            for slop in SLOPS_S:
                cases.append((f"ApproximateTime (queue 10, slop {slop:g} s)",
                              lambda cb, s=slop: ApproximateTimeSync(n, 10, int(s * 1e9), cb)))
            for name, make in cases:
                rows.append({"n": n, "p": p, "policy": name, **simulate(n, p, make)})
            one = simulate(1, p, lambda cb: ExactTimeSync(1, 10, cb))
            rows.append({"n": n, "p": p, "policy": "one LidarScan per frame (no synchroniser)",
                         **one})
    return rows


def _sizes_block() -> Block:
    rows = []
    for rec in measure_sizes():
        rows.append([rec["label"], fmt_int(rec["scan"]), str(rec["n"]), fmt_int(rec["images"]),
                     f"{rec['images'] / rec['scan']:.3f}",
                     "yes" if rec["lossless"] else "**no**"])
    return Block("images-sizes", table(
        ["frame", "LidarScan bytes", "images (one per channel)", "images bytes, total",
         "images ÷ LidarScan", "round trip bit-exact (given the column times)"], rows,
        ["l", "r", "r", "r", "r", "l"]))


def _sync_block() -> Block:
    rows = []
    for r in measure_sync():
        rows.append([str(r["n"]), f"{r['p'] * 100:g} %", r["policy"], fmt_int(r["frames_hit"]),
                     fmt_int(r["whole"]), fmt_int(r["lost"]),
                     f"**{fmt_int(r['mixed'])}**" if r["mixed"] else "0"])
    return Block("images-sync", f"{FRAMES} frames at 10 Hz per row:\n\n" + table(
        ["images per frame", "loss per message", "receiver", "frames with a message lost",
         "frames delivered whole", "frames lost", "sets mixing frames (silently wrong)"], rows,
        ["r", "r", "l", "r", "r", "r", "r"]))


def _timing_block() -> Block:
    from rclpy.serialization import serialize_message

    import lidarscan as ls
    from converters.edge.evidence.transport import N_MESSAGES, _Ros
    from converters.images import from_images, to_images
    rows = []
    ros = _Ros()
    try:
        for label, info, scan in _frames():
            rscan = ls.make_scan(info, {c.name: ls.channel(scan, c.name) for c in scan.channels},
                                 ls.to_ns(scan.header.stamp),
                                 column_time_offsets=scan.column_time_offsets)
            imgs = list(to_images(scan, info).values())
            cases = {"one LidarScan": [rscan], f"{len(imgs)} Images": imgs}
            base: dict[str, float] = {}
            for name, msgs in cases.items():
                ser = time_call(lambda m=msgs: [serialize_message(x) for x in m], repeat=5)
                wall, cpu = ros.roundtrip(msgs, N_MESSAGES, depth=max(4, len(msgs)))
                if not base:
                    base = {"cpu": cpu}
                rows.append([label, name, f"{ser * 1e3:.2f}", f"{wall * 1e3:.2f}",
                             f"{cpu * 1e3:.2f}", f"{cpu / base['cpu']:.1f}×"])
            dc = {k: v for k, v in to_images(scan, info, as_dataclass=True).items()}
            t_to = time_call(lambda: to_images(scan, info, as_dataclass=True), repeat=5)
            t_from = time_call(lambda: from_images(dc, info, is_destaggered=False,
                                                   as_dataclass=True), repeat=5)
            rows.append([label, "conversion: to_images ms (col. 3), from_images ms (col. 4); "
                         "destaggering, dataclasses",
                         f"{t_to * 1e3:.2f}", f"{t_from * 1e3:.2f}", "—", "—"])
    finally:
        ros.close()
    return Block("timing-images", table(
        ["frame", "messages per frame", "serialize ms", "publish→callback ms (wall)",
         "CPU ms per frame (both ends)", "CPU ÷ LidarScan"], rows,
        ["l", "l", "r", "r", "r", "r"]), deterministic=False)


def blocks(timing: bool = True) -> list[Block]:
    """``images-sizes``, ``images-sync`` (deterministic) and ``timing-images``."""
    out = [_sizes_block(), _sync_block()]
    if timing:
        ok, why = have("rclpy")
        if ok:
            ok, why = have("sensor_msgs.msg", "Image")
        out.append(_timing_block() if ok else
                   pending("timing-images", "images through rclpy", why, False))
    return out
