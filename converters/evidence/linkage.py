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
"""

from __future__ import annotations

import copy
import json
from functools import lru_cache
from typing import Any

import numpy as np

from converters.evidence._common import (
    OUSTER_DATA,
    Block,
    load_frame,
    table,
)

__all__ = ["SCENARIOS", "blocks", "geometries", "run"]

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
    from converters.ouster import info_from_metadata
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
    import dataclasses

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


def blocks(records: list[dict[str, Any]] | None = None) -> list[Block]:
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
    return [Block("linkage", text)]
