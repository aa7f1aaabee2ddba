"""Question 5: the info link. Scenario counts from the resolver vs a "latest info wins" consumer.

Two real geometries of the same grid size (128 x 1024): A = the OS-2-128 fixture, B = the
OS-1-128 fixture's calibration run in 1024x10 mode (its JSON with ``lidar_mode`` 1024x10, 1024
columns and the pixel shifts halved, as the sensor reports them in that mode): a unit swap or a
recalibration on the same topic, which changes no size a receiver could check. C = the OS-2-128
in 2048x10 mode (a mode change: the size changes). Every scan carries the real OS-2-128 frame's
ranges; only the geometry it was produced under differs.

Each scenario is a list of arrival events on the receiver (info and scan topics are separate
DDS topics, so their relative order is not guaranteed). Two receivers consume the same events:

* naive: keeps the most recent LidarInfo and projects every scan with it (scans before any info,
  or of another size, are unusable);
* resolver: :class:`lidarscan.linkage.InfoResolver` (pairs by ``lidar_info_time``, holds scans
  whose info is missing, drops them with a reason when it never comes).

A misprojected scan is one projected with the geometry of another stamp; its error is measured
pixel by pixel against the correct projection (real ranges, every return).

**Version keys** (:func:`run_keys`, "why a timestamp, not a UUID or a content hash?"). The same
geometries go through scenarios where keys behave differently (republish, late join, a recording
cut in two, two drivers on one topic, simulated time restarting at 0, a driver reusing a stamp).
Each scenario is a list of *versions* (what a driver publishes: geometry, the stamp it sets, the
UUID it would draw: a new one at start-up and on every change it notices) and arrival events.
Four receivers, one per key, replay the same events:

* stamp, no digest check: :class:`KeyedResolver` keyed by ``lidar_info_time`` that trusts the key
  (a republish under a known key replaces the stored info, as a plain dict does);
* stamp + digest check: the real :class:`lidarscan.linkage.InfoResolver` (public API, so the table
  follows the resolver's behaviour);
* UUID: :class:`KeyedResolver` keyed by a 16-byte id the driver would carry in both messages;
* content hash: :class:`KeyedResolver` keyed by the digest of the geometry (the receiver computes
  it from the info it receives; the scan carries the one the driver computed).

The UUID and hash the messages would carry are kept in a side table (the project's messages have
no such fields); the bytes each key adds are measured by encoding variants of the messages.
"""

from __future__ import annotations

import copy
import dataclasses
import json
from collections import OrderedDict, deque
from collections.abc import Callable, Hashable
from functools import lru_cache
from typing import Any

import numpy as np

from converters.edge.evidence._common import (
    OUSTER_DATA,
    Block,
    load_frame,
    table,
)

__all__ = ["KEYS", "KEY_SCENARIOS", "SCENARIOS", "KeyedResolver", "Version", "blocks",
           "geometries", "key_sizes", "run", "run_keys"]

OS2 = "OS-2-128-U1_v2.3.0_1024x10"
OS1 = "2_0_0_os1-992008000494-128_col_win_legacy"


def _remode(data: dict[str, Any], width: int) -> dict[str, Any]:
    """The same sensor's metadata in another ``<width>x10`` mode (shifts scale with width)."""
    out = copy.deepcopy(data)
    fmt = out["data_format"]
    old = int(fmt["columns_per_frame"])
    out["lidar_mode"] = f"{width}x10"
    fmt["columns_per_frame"] = width
    fmt["column_window"] = [0, width - 1]
    fmt["pixel_shift_by_row"] = [int(s) * width // old for s in fmt["pixel_shift_by_row"]]
    return out


def geometries() -> dict[str, Any]:
    """Infos A, B (same size, other geometry) and C (other size), stamps 1 s, 2 s, 3 s."""
    from converters.sources.ouster.metadata import info_from_metadata
    os2 = json.loads((OUSTER_DATA / f"{OS2}.json").read_text())
    os1 = json.loads((OUSTER_DATA / f"{OS1}.json").read_text())
    return {
        "A": info_from_metadata(os2, stamp_ns=1_000_000_000, as_dataclass=True),
        "B": info_from_metadata(_remode(os1, 1024), stamp_ns=2_000_000_000, as_dataclass=True),
        "C": info_from_metadata(_remode(os2, 2048), stamp_ns=3_000_000_000, as_dataclass=True),
    }


def _ranges(width: int) -> np.ndarray[Any, Any]:
    frame = load_frame(OUSTER_DATA / f"{OS2}_frame1259.npz")
    mm = np.asarray(frame["range_mm"], np.float64)
    r = np.where(mm > 0, mm / 1000.0, np.inf).astype(np.float32)
    return r if width == r.shape[1] else np.repeat(r, width // r.shape[1], axis=1)


#: name -> (what happens, events). Events: ("info", key) or ("scan", key, count).
SCENARIOS: dict[str, tuple[str, list[tuple[Any, ...]]]] = {
    "reconfigured, new info late": (
        "unit swapped/recalibrated (A → B, same size); the first 3 B scans arrive before info B",
        [("info", "A"), ("scan", "A", 10), ("scan", "B", 3), ("info", "B"), ("scan", "B", 7)]),
    "reconfigured, old scans in flight": (
        "A → B; info B overtakes the last 2 A scans (separate topics)",
        [("info", "A"), ("scan", "A", 8), ("info", "B"), ("scan", "A", 2), ("scan", "B", 10)]),
    "mode change": (
        "1024x10 → 2048x10 (A → C, size changes); info C arrives 2 scans late",
        [("info", "A"), ("scan", "A", 10), ("scan", "C", 2), ("info", "C"), ("scan", "C", 8)]),
    "late joiner": (
        "subscriber joins after the change: the latched info B comes after 4 scans, "
        "2 A scans still queued",
        [("scan", "A", 2), ("scan", "B", 2), ("info", "B"), ("scan", "B", 16)]),
    "late joiner, stale cached info": (
        "consumer restarted with yesterday's info A cached; sensor now B; info B delayed 5 scans",
        [("info", "A"), ("scan", "B", 5), ("info", "B"), ("scan", "B", 15)]),
    "bag replay, both infos latched": (
        "bag holds A (10 scans) then B (10 scans); replay with a transient-local override "
        "delivers both infos first",
        [("info", "A"), ("info", "B"), ("scan", "A", 10), ("scan", "B", 10)]),
    "bag replay from an offset": (
        "same bag played from after the change (`--start-offset`): no info is replayed",
        [("scan", "B", 10)]),
    "same stamp, other geometry": (
        "a driver re-publishes info with the old stamp but geometry B",
        [("info", "A"), ("scan", "A", 5), ("info", "A≠"), ("scan", "A", 5)]),
}


#: which geometry each info key really holds ("A≠" has A's stamp but B's geometry)
_GEOMETRY = {"A": "A", "B": "B", "C": "C", "A≠": "B"}


def _projection_errors(infos: dict[str, Any]) -> dict[tuple[str, str], tuple[float, float]]:
    """(true, used) -> (max, median) point error in metres over every return of the frame."""
    from lidarscan.geometry import exact_xyz
    out = {}
    for true, used in (("A", "B"), ("B", "A")):
        ranges = _ranges(int(infos[true].width))
        good = exact_xyz(infos[true], ranges)
        bad = exact_xyz(infos[used], ranges)
        valid = np.isfinite(ranges)
        err = np.linalg.norm(good - bad, axis=-1)[valid]
        out[(true, used)] = (float(err.max()), float(np.median(err)))
    return out


@lru_cache(maxsize=1)
def run() -> list[dict[str, Any]]:
    """Replay every scenario through both receivers; one record of counts per scenario."""
    import lidarscan as ls
    from lidarscan.linkage import InfoResolver

    infos = geometries()
    # "A≠": stamp of A, geometry of B (a re-publication with changed content)
    infos["A≠"] = dataclasses.replace(infos["B"], header=infos["A"].header)
    errors = _projection_errors(infos)
    records = []
    for name, (what, events) in SCENARIOS.items():
        truth: dict[int, str] = {}
        naive_info: str | None = None
        naive = {"ok": 0, "wrong": 0, "unusable": 0, "max_err": 0.0, "median_err": 0.0}
        resolver = InfoResolver(max_pending=16, max_wait_ns=None)
        pairs: list[tuple[Any, Any]] = []
        stamp = 10_000_000_000
        for event in events:
            if event[0] == "info":
                key = event[1]
                naive_info = key
                pairs += resolver.add_info(infos[key])
                continue
            _, key, count = event
            true_key = key
            info = infos[true_key]
            for _ in range(count):
                stamp += 100_000_000
                scan = ls.make_scan(info, {"range": _ranges(int(info.width))}, stamp,
                                    as_dataclass=True)
                truth[id(scan)] = true_key
                # naive consumer
                used = naive_info
                if used is None or int(infos[used].width) != int(info.width):
                    naive["unusable"] += 1
                elif _GEOMETRY[used] == true_key:
                    naive["ok"] += 1
                else:
                    naive["wrong"] += 1
                    mx, med = errors[(true_key, _GEOMETRY[used])]
                    naive["max_err"] = max(naive["max_err"], mx)
                    naive["median_err"] = max(naive["median_err"], med)
                pairs += resolver.add_scan(scan)
        resolver.flush()
        dropped = resolver.take_dropped()
        wrong = 0
        for scan, info in pairs:
            keys = [k for k, v in infos.items() if v is info]
            if truth[id(scan)] not in keys:
                wrong += 1
        total = sum(e[2] for e in events if e[0] == "scan")
        reasons = sorted({d.reason.split(":")[0] for d in dropped})
        records.append({"name": name, "what": what, "total": total, "naive": naive,
                        "paired": len(pairs), "wrong": wrong, "dropped": len(dropped),
                        "reasons": reasons})
    return records


# ------------------------------------------------------------------------------ version keys

_S = 1_000_000_000


@dataclasses.dataclass(frozen=True)
class Version:
    """One LidarInfo publication as a driver makes it.

    Attributes:
        geometry: which real geometry it holds ("A" or "B" of :func:`geometries`).
        stamp_ns: the ``header.stamp`` the driver sets (int ns).
        uuid: the UUID a UUID-keyed driver would carry (drawn at start-up and on every change
            the driver notices; a small int stands for the 16 random bytes).
    """

    geometry: str
    stamp_ns: int
    uuid: int


def _interleave(a: str, b: str, count: int) -> list[tuple[Any, ...]]:
    out: list[tuple[Any, ...]] = []
    for _ in range(count):
        out += [("scan", a, 1), ("scan", b, 1)]
    return out


#: name -> (what happens, versions, events). Events: ("info", version) or ("scan", version, n).
KEY_SCENARIOS: dict[str, tuple[str, dict[str, Version], list[tuple[Any, ...]]]] = {
    "identical republish": (
        "the driver re-publishes its unchanged info mid-stream (same stamp, same UUID)",
        {"a": Version("A", 1 * _S, 1)},
        [("info", "a"), ("scan", "a", 5), ("info", "a"), ("scan", "a", 5)]),
    "changed republish, same key": (
        "the driver changes the geometry (A → B) in place and re-publishes under its old "
        "stamp/UUID; 2 A scans still in flight",
        {"a": Version("A", 1 * _S, 1), "b": Version("B", 1 * _S, 1)},
        [("info", "a"), ("scan", "a", 5), ("info", "b"), ("scan", "a", 2), ("scan", "b", 5)]),
    "late joiner": (
        "subscriber joins mid-stream: 3 scans arrive before the latched info",
        {"a": Version("A", 1 * _S, 1)},
        [("scan", "a", 3), ("info", "a"), ("scan", "a", 7)]),
    "recording cut in two": (
        "the second half of a split recording is replayed alone, with the info re-created from "
        "the vendor metadata saved beside it (same geometry, new stamp and UUID)",
        {"a": Version("A", 1 * _S, 1), "a'": Version("A", 7200 * _S, 2)},
        [("info", "a'"), ("scan", "a", 10)]),
    "two drivers, one topic": (
        "two sensors' drivers publish on the same topics (namespace forgotten); wall-clock "
        "stamps, so the two infos differ in stamp",
        {"a": Version("A", 1 * _S + 200_000_000, 1), "b": Version("B", 1 * _S + 700_000_000, 2)},
        [("info", "a"), ("info", "b")] + _interleave("a", "b", 10)),
    "two drivers, one topic, sim time": (
        "the same with simulated time: both infos stamped at the first /clock tick (0.1 s)",
        {"a": Version("A", _S // 10, 1), "b": Version("B", _S // 10, 2)},
        [("info", "a"), ("info", "b")] + _interleave("a", "b", 10)),
    "sim restart, same sensor": (
        "/clock restarts at 0 (simulation reset) while the receiver keeps running; the "
        "simulated sensor re-publishes its unchanged info at 0.1 s (new UUID)",
        {"a": Version("A", _S // 10, 1), "a2": Version("A", _S // 10, 2)},
        [("info", "a"), ("scan", "a", 10), ("info", "a2"), ("scan", "a2", 10)]),
    "sim restart, changed sensor": (
        "the same, but the simulated sensor was reconfigured (A → B) before the reset",
        {"a": Version("A", _S // 10, 1), "b": Version("B", _S // 10, 2)},
        [("info", "a"), ("scan", "a", 10), ("info", "b"), ("scan", "b", 10)]),
    "clock steps back, then a change": (
        "the clock is stepped back 5 s (NTP/PTP correction), then the sensor is recalibrated "
        "(A → B): the new stamp is older than the old one",
        {"a": Version("A", 10 * _S, 1), "b": Version("B", 6 * _S, 2)},
        [("info", "a"), ("scan", "a", 10), ("info", "b"), ("scan", "b", 10)]),
    "driver restart reusing a stamp": (
        "unit swapped (A → B); the restarted driver stamps the new info with the stamp it used "
        "before (e.g. a fixed time from its metadata file); 2 A scans in flight",
        {"a": Version("A", 1 * _S, 1), "b": Version("B", 1 * _S, 2)},
        [("info", "a"), ("scan", "a", 8), ("info", "b"), ("scan", "a", 2), ("scan", "b", 10)]),
    "driver and receiver of different releases": (
        "the receiver's release hashes one more LidarInfo field (`vendor_metadata`) than the "
        "driver's: the content hash's input must be defined exactly, the other keys have none",
        {"a": Version("A", 1 * _S, 1)},
        [("info", "a"), ("scan", "a", 10)]),
}

#: scenarios whose receiver computes the content hash over a larger input than the driver did
_HASH_SKEW = {"driver and receiver of different releases"}


class KeyedResolver:
    """A resolver that pairs scans with infos by an arbitrary version key.

    The same interface and holding rules as :class:`lidarscan.linkage.InfoResolver` (held
    scans, ``max_pending``, :meth:`flush`, :meth:`take_dropped`), without a digest check: the key
    is trusted, and an info re-published under a known key replaces the stored one (a dict).

    Args:
        info_key: the key of a received LidarInfo.
        scan_key: the key a LidarScan names.
        max_infos: versions kept (the oldest is forgotten).
        max_pending: scans held while their info is missing (the oldest is dropped when full).
    """

    def __init__(self, info_key: Callable[[Any], Hashable], scan_key: Callable[[Any], Hashable],
                 *, max_infos: int = 8, max_pending: int = 16) -> None:
        self._info_key, self._scan_key = info_key, scan_key
        self.max_infos, self.max_pending = max_infos, max_pending
        self._infos: OrderedDict[Hashable, Any] = OrderedDict()
        self._pending: deque[tuple[Hashable, Any]] = deque()
        self._dropped: list[Any] = []

    def _drop(self, scan: Any, reason: str) -> None:
        from lidarscan.linkage import Dropped
        from lidarscan.stamps import to_ns
        self._dropped.append(Dropped(scan, to_ns(scan.header.stamp),
                                     to_ns(scan.lidar_info_time), reason))

    def add_info(self, info: Any) -> list[tuple[Any, Any]]:
        """Store (or replace) the info under its key; returns the held scans it releases."""
        key = self._info_key(info)
        self._infos[key] = info
        self._infos.move_to_end(key)
        while len(self._infos) > self.max_infos:
            self._infos.popitem(last=False)
        out, keep = [], deque()
        for wanted, scan in self._pending:
            if wanted in self._infos:
                out.append((scan, self._infos[wanted]))
            else:
                keep.append((wanted, scan))
        self._pending = keep
        return out

    def add_scan(self, scan: Any) -> list[tuple[Any, Any]]:
        """The (scan, info) pair if its key is known; else the scan is held."""
        key = self._scan_key(scan)
        if key in self._infos:
            return [(scan, self._infos[key])]
        if len(self._pending) >= self.max_pending:
            self._drop(self._pending.popleft()[1], "pending buffer full before its LidarInfo came")
        self._pending.append((key, scan))
        return []

    def flush(self) -> None:
        """Drop every held scan (end of the stream)."""
        while self._pending:
            self._drop(self._pending.popleft()[1], "its LidarInfo never arrived")

    def take_dropped(self) -> list[Any]:
        """Drop records since the last call (and forget them)."""
        out, self._dropped = self._dropped, []
        return out


def _content_hash(info: Any, skew: bool = False) -> str:
    """The content key: digest of every geometry field (``lidarscan.geometry.info_key``, stamp
    excluded); ``skew`` also hashes ``vendor_metadata`` (a release that hashes one more field)."""
    import hashlib

    from lidarscan.geometry import info_key
    digest = info_key(info)[1]
    if skew:
        digest = hashlib.blake2b((digest + info.vendor_metadata).encode(),
                                 digest_size=16).hexdigest()
    return digest


def _key_resolvers(carried: dict[tuple[str, int], Hashable], hash_skew: bool = False
                   ) -> dict[str, Callable[[], Any]]:
    """Key name -> factory of a fresh resolver. ``carried[(kind, id(msg))]`` is the UUID or
    hash a driver would have written into the message."""
    from lidarscan.linkage import InfoResolver
    from lidarscan.stamps import to_ns
    return {
        "stamp, no digest check": lambda: KeyedResolver(
            lambda i: to_ns(i.header.stamp), lambda s: to_ns(s.lidar_info_time)),
        "stamp + digest check": lambda: InfoResolver(max_pending=16, max_wait_ns=None),
        "UUID": lambda: KeyedResolver(lambda i: carried[("uuid", id(i))],
                                      lambda s: carried[("uuid", id(s))]),
        "content hash": lambda: KeyedResolver(lambda i: _content_hash(i, hash_skew),
                                              lambda s: carried[("hash", id(s))]),
    }


#: the receivers of :func:`run_keys`, in table order
KEYS = ("stamp, no digest check", "stamp + digest check", "UUID", "content hash")


@lru_cache(maxsize=1)
def run_keys() -> list[dict[str, Any]]:
    """Replay every :data:`KEY_SCENARIOS` entry through one receiver per key.

    Returns:
        One record per scenario: name, what, total scans, and per key (``rec["keys"][key]``) a
        dict of ``right``, ``wrong`` (paired with another geometry) and ``dropped`` counts plus
        the drop reasons.
    """
    import lidarscan as ls
    from lidarscan.stamps import time_msg
    from lidarscan.types import Header

    geos = geometries()
    records = []
    for name, (what, versions, events) in KEY_SCENARIOS.items():
        carried: dict[tuple[str, int], Hashable] = {}
        infos, geometry_of = {}, {}
        for vname, ver in versions.items():
            base = geos[ver.geometry]
            info = dataclasses.replace(base, header=Header(time_msg(ver.stamp_ns),
                                                           base.header.frame_id))
            infos[vname] = info
            geometry_of[id(info)] = ver.geometry
            carried[("uuid", id(info))] = ver.uuid
        # the scans, made once: each names its version by stamp, UUID and content hash
        stream: list[tuple[str, Any]] = []
        truth: dict[int, str] = {}
        stamp = 100 * _S
        for event in events:
            if event[0] == "info":
                stream.append(("info", infos[event[1]]))
                continue
            _, vname, count = event
            info = infos[vname]
            for _ in range(count):
                stamp += 100_000_000
                scan = ls.make_scan(info, {"range": _ranges(int(info.width))}, stamp,
                                    as_dataclass=True)
                truth[id(scan)] = versions[vname].geometry
                carried[("uuid", id(scan))] = versions[vname].uuid
                carried[("hash", id(scan))] = _content_hash(info)
                stream.append(("scan", scan))
        per_key = {}
        for key, factory in _key_resolvers(carried, name in _HASH_SKEW).items():
            resolver = factory()
            pairs: list[tuple[Any, Any]] = []
            for kind, msg in stream:
                pairs += resolver.add_info(msg) if kind == "info" else resolver.add_scan(msg)
            resolver.flush()
            dropped = resolver.take_dropped()
            wrong = sum(1 for scan, info in pairs if geometry_of[id(info)] != truth[id(scan)])
            per_key[key] = {"right": len(pairs) - wrong, "wrong": wrong,
                            "dropped": len(dropped),
                            "reasons": sorted({d.reason.split(":")[0] for d in dropped})}
        records.append({"name": name, "what": what, "total": len(truth), "keys": per_key})
    return records


def _birthday(bits: int) -> str:
    """Number of random keys after which a collision has a 50 % chance, e.g. '2.7e18'."""
    import math
    return f"{math.sqrt(2 * math.log(2) * 2.0 ** bits):.1e}".replace("e+", "e")


#: key -> (scan field the key needs, info field, collision behaviour)
_KEY_FIELDS = {
    "stamp": ("builtin_interfaces/Time lidar_info_time", "",
              "two versions collide when a publisher reuses a stamp (sim time, fixed stamps); "
              "the digest check turns that into drops"),
    "UUID": ("uint8[16] lidar_info_uuid", "uint8[16] uuid",
             f"random 122 bits: a 50 % chance of one collision after {_birthday(122)} "
             "versions; a driver that keeps its UUID across a change is not detected"),
    "content hash": ("uint8[16] lidar_info_digest", "",
                     f"128-bit digest: a 50 % chance of one collision after {_birthday(128)} "
                     "distinct geometries; a changed geometry always gets a new key"),
}


def key_sizes() -> list[dict[str, Any]]:
    """Bytes each key adds, measured by CDR-encoding variants of the real 128×1024 messages.

    The LidarScan variant without any key field is the baseline; each key replaces
    ``lidar_info_time`` by its own field. For the LidarInfo, the stamp reuses ``header.stamp``
    (every message has a header) and the content hash is computed by the receiver, so only the
    UUID needs a field.
    """
    from types import SimpleNamespace

    import lidarscan as ls
    from lidarscan.msgdef import find_msg_text, register_msg_text

    info = geometries()["A"]
    scan = ls.make_scan(info, {"range": _ranges(int(info.width))}, 100 * _S, as_dataclass=True)
    scan_text = find_msg_text("lidarscan_msgs/msg/LidarScan").replace(
        "LidarChannel[] channels", "lidarscan_msgs/LidarChannel[] channels")
    info_text = find_msg_text("lidarscan_msgs/msg/LidarInfo")
    line = "builtin_interfaces/Time lidar_info_time"
    if line not in scan_text:
        raise LookupError(f"LidarScan.msg has no line {line!r} (the field this measurement swaps)")

    def size(name: str, text: str, msg: Any, extra: dict[str, Any]) -> int:
        register_msg_text(f"evidence_keys/msg/{name}", text)
        fields = {f.name: getattr(msg, f.name) for f in dataclasses.fields(msg)}
        fields.pop("lidar_info_time", None)
        return len(ls.encode(SimpleNamespace(**fields, **extra), f"evidence_keys/msg/{name}"))

    base_scan = size("ScanNoKey", scan_text.replace(line + "\n", ""), scan, {})
    base_info = size("InfoNoKey", info_text, info, {})
    out = []
    for key, (scan_field, info_field, collision) in _KEY_FIELDS.items():
        name = key.title().replace(" ", "")
        value = scan.lidar_info_time if key == "stamp" else bytes(16)
        scan_bytes = size(f"Scan{name}", scan_text.replace(line, scan_field), scan,
                          {scan_field.split()[1]: value})
        info_bytes = base_info
        if info_field:
            info_bytes = size(f"Info{name}", f"{info_text}\n{info_field}\n", info,
                              {info_field.split()[1]: bytes(16)})
        out.append({"key": key, "scan_field": scan_field, "info_field": info_field,
                    "scan_adds": scan_bytes - base_scan, "info_adds": info_bytes - base_info,
                    "scan_bytes": scan_bytes, "collision": collision})
    return out


def _keys_table(records: list[dict[str, Any]]) -> str:
    rows = []
    totals = {k: {"right": 0, "wrong": 0, "dropped": 0} for k in KEYS}

    def cell(c: dict[str, int]) -> str:
        wrong = f"**{c['wrong']}**" if c["wrong"] else "0"
        return f"{c['right']} / {wrong} / {c['dropped']}"

    for r in records:
        for k in KEYS:
            for f in ("right", "wrong", "dropped"):
                totals[k][f] += r["keys"][k][f]
        rows.append([r["name"], r["what"], str(r["total"])] + [cell(r["keys"][k]) for k in KEYS])
    rows.append(["**all**", f"{len(records)} scenarios", str(sum(r["total"] for r in records))]
                + [cell(totals[k]) for k in KEYS])
    return table(["scenario", "what happens", "scans"]
                 + [f"{k}: right / wrong / dropped" for k in KEYS], rows,
                 ["l", "l", "r"] + ["r"] * len(KEYS))


def _sizes_table(sizes: list[dict[str, Any]]) -> str:
    from converters.edge.evidence._common import fmt_int
    implicit = {"stamp": "— (header.stamp)", "content hash": "— (computed by the receiver)"}
    rows = []
    for s in sizes:
        info_field = f"`{s['info_field']}`" if s["info_field"] else implicit[s["key"]]
        rows.append([s["key"], f"`{s['scan_field']}`", str(s["scan_adds"]), info_field,
                     str(s["info_adds"]), f"{s['scan_adds'] / s['scan_bytes'] * 1e6:.1f}",
                     s["collision"]])
    head = ("Bytes each key adds to the messages (CDR, measured by encoding variants of the real "
            f"OS-2-128 128×1024 scan, range channel only: {fmt_int(sizes[0]['scan_bytes'])} "
            "bytes with the stamp key; a frame with every channel is larger and the share "
            "smaller):\n\n")
    return head + table(["key", "LidarScan field", "LidarScan bytes", "LidarInfo field",
                         "LidarInfo bytes", "per million scan bytes", "collisions"], rows,
                        ["l", "l", "r", "l", "r", "r", "l"])


def _where(records: list[dict[str, Any]], key: str, field: str) -> list[str]:
    return [r["name"] for r in records if r["keys"][key][field]]


def _keys_reading(records: list[dict[str, Any]]) -> str:
    """One generated line per key: what it got wrong, what it dropped, and where."""
    total = sum(r["total"] for r in records)
    lines = []
    for k in KEYS:
        wrong = sum(r["keys"][k]["wrong"] for r in records)
        dropped = sum(r["keys"][k]["dropped"] for r in records)
        w = ("never pairs a scan with the wrong geometry" if not wrong else
             f"pairs **{wrong}** of {total} scans with the wrong geometry "
             f"({'; '.join(_where(records, k, 'wrong'))})")
        d = ("drops none" if not dropped else
             f"drops {dropped} ({'; '.join(_where(records, k, 'dropped'))})")
        lines.append(f"- **{k}** {w}; it {d}.")
    return "\n".join(lines)


def blocks(records: list[dict[str, Any]] | None = None) -> list[Block]:
    """The ``linkage`` table, the version-key comparison (``linkage-keys``,
    ``linkage-key-sizes``, ``linkage-keys-reading``) and, because it is the same question of
    what a receiver can rely on, the vendor mapping of :mod:`converters.edge.evidence.vendor_mapping`
    (kept out of ``converters/edge/evidence/__init__.py`` so that file needs no new section)."""
    from converters.edge.evidence import vendor_mapping
    out = [_linkage_block(records)]
    keys = run_keys()
    out += [Block("linkage-keys", _keys_table(keys)),
            Block("linkage-key-sizes", _sizes_table(key_sizes())),
            Block("linkage-keys-reading", _keys_reading(keys))]
    return out + vendor_mapping.blocks()


def _linkage_block(records: list[dict[str, Any]] | None = None) -> Block:
    """The ``linkage`` table."""
    records = run() if records is None else records
    rows = []
    for r in records:
        n = r["naive"]
        err = (f"{n['max_err']:.2f} m max, {n['median_err'] * 100:.1f} cm median"
               if n["wrong"] else "—")
        rows.append([r["name"], r["what"], str(r["total"]), str(n["ok"]), f"**{n['wrong']}**"
                     if n["wrong"] else "0", str(n["unusable"]), err, str(r["paired"]),
                     str(r["wrong"]), str(r["dropped"]),
                     "; ".join(r["reasons"]) if r["reasons"] else "—"])
    text = table(["scenario", "what happens", "scans", "naive: right", "naive: misprojected",
                  "naive: unusable", "naive: error of misprojected points",
                  "resolver: paired", "resolver: wrong pairs", "resolver: dropped",
                  "resolver: drop reason"], rows,
                 ["l", "l", "r", "r", "r", "r", "l", "r", "r", "r", "l"])
    return Block("linkage", text)
