"""Fuzz targets of ``bench/fuzz.py`` for the converters: mutated Ouster metadata, PointCloud2
input, LaserScan sweeps, merger inputs and the LidarInfo linkage under eviction; the merger
adapter the fault tests reuse."""

from __future__ import annotations

import collections
import copy
import dataclasses
import functools
import json
import math
import random
from collections.abc import Callable
from typing import Any

import numpy as np

import lidarscan as ls
from lidarscan import types as lt

import fuzz_common
from fuzz_common import (  # bench/ is on sys.path: see fuzz.py
    CONV,
    exercise_scan,
    H,
    mutate_bytes,
    Target,
    W,
)

def _metadata_seed() -> dict[str, Any]:
    path = (fuzz_common.ROOT / "converters" / "data"
            / "2_0_0_os1-992008000494-128_col_win_legacy.json")
    meta: dict[str, Any] = json.loads(path.read_text())
    return meta


def _json_paths(node: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    out = [prefix] if prefix else []
    if isinstance(node, dict):
        for key, value in node.items():
            out += _json_paths(value, prefix + (key,))
    elif isinstance(node, list) and len(node) <= 16:
        for i, value in enumerate(node):
            out += _json_paths(value, prefix + (i,))
    return out


def mutate_json(rnd: random.Random, data: Any) -> Any:
    """Delete a key, change a value's type, length or value (NaN, Inf, huge, negative)."""
    data = copy.deepcopy(data)
    paths = _json_paths(data)
    for _ in range(rnd.randint(1, 3)):
        path = rnd.choice(paths)
        parent = data
        try:
            for key in path[:-1]:
                parent = parent[key]
            value = parent[path[-1]]
        except (KeyError, IndexError, TypeError):
            continue
        if not isinstance(parent, (dict, list)):  # an earlier mutation replaced a container
            continue
        kind = rnd.randrange(6)
        if kind == 0 and isinstance(parent, dict):
            del parent[path[-1]]
            continue
        if kind == 1:
            new: Any = rnd.choice([None, "", "x", "1024x10", "0x0", "99999999x1", [], {}, True,
                                   -1, 0, 2**31, 10**12, 1e308, math.nan, math.inf, 0.5])
        elif kind == 2 and isinstance(value, list):
            new = value[:rnd.randrange(len(value) + 1)] if rnd.random() < 0.5 else value + value
        elif kind == 3 and isinstance(value, list) and value:
            new = list(value)
            new[rnd.randrange(len(new))] = rnd.choice([math.nan, math.inf, -math.inf, None, "a",
                                                       [1, 2], 1e308])
        elif kind == 4 and isinstance(value, (int, float)) and not isinstance(value, bool):
            new = rnd.choice([value * -1, value * 1000, 0, value + 1, 2**40, math.nan])
        else:
            new = rnd.choice([str(value), [value], {"v": value}])
        parent[path[-1]] = new
    return data


class OusterJson(Target):
    """Ouster metadata: structural mutations of the shipped JSON, or byte mutations of its text."""
    name = "ouster_json"
    needs = ("info_from_metadata",)

    def setup(self) -> None:
        self.meta = _metadata_seed()
        self.text = json.dumps(self.meta)

    def case(self, rnd: random.Random) -> tuple[str, Callable[[], str]]:
        convert = CONV["info_from_metadata"]
        if rnd.random() < 0.75:
            text = json.dumps(mutate_json(rnd, self.meta))  # NaN/Infinity stay valid JSON here
        else:
            raw = mutate_bytes(rnd, self.text.encode())
            text = raw.decode("utf-8", errors="replace")
            if not text.lstrip().startswith("{"):
                text = "{" + text  # a str not starting with "{" is taken as a path

        def run() -> str:
            info = convert(text, stamp_ns=1, as_dataclass=True)
            ls.validate_info(info)
            return "converted"
        return text, run


class PointCloud2Input(Target):
    """PointCloud2 dataclasses with inconsistent fields into from_pointcloud2."""
    name = "pointcloud2"
    needs = ("from_pointcloud2",)

    def setup(self) -> None:
        self.cls = lt.message_class("sensor_msgs/msg/PointCloud2")
        self.field_cls = lt.message_class("sensor_msgs/msg/PointField")

    def case(self, rnd: random.Random) -> tuple[str, Callable[[], str]]:
        rows = rnd.choice([1, 2, 4, 16])
        n = rnd.choice([0, 1, 2, 7, 64])
        organized = rnd.random() < 0.5
        height, width = (rows, n) if organized else (1, rows * n)
        fields = [self.field_cls(name=name, offset=off, datatype=dt, count=1)
                  for name, off, dt in (("x", 0, 7), ("y", 4, 7), ("z", 8, 7),
                                        ("intensity", 12, 7), ("ring", 16, 4), ("t", 20, 6))]
        if rnd.random() < 0.3:
            fields.pop(rnd.choice([3, 4, 5]))
        point_step = 24
        pts = np.zeros((rows, n), np.dtype({"names": ["x", "y", "z", "i", "ring", "t"],
                                           "formats": ["<f4", "<f4", "<f4", "<f4", "<u2", "<u4"],
                                           "offsets": [0, 4, 8, 12, 16, 20], "itemsize": 24}))
        az = np.linspace(0, 2 * np.pi, max(n, 1), endpoint=False)[:n]
        el = np.linspace(0.2, -0.2, rows)[:, None]
        r = np.array([[rnd.uniform(1, 50) for _ in range(n)] for _ in range(rows)])
        pts["x"] = r * np.cos(el) * np.cos(az)
        pts["y"] = r * np.cos(el) * np.sin(az)
        pts["z"] = r * np.sin(el)
        pts["ring"] = np.arange(rows)[:, None]
        pts["t"] = np.arange(n)[None, :] * 1000
        flat = pts.reshape(-1)
        for _ in range(rnd.randint(0, 4)):
            if flat.size:
                flat[rnd.choice("xyz")][rnd.randrange(flat.size)] = rnd.choice(
                    [np.nan, np.inf, -np.inf, 0.0, 1e30])
        if not organized:
            flat = flat[np.argsort(pts["t"].reshape(-1), kind="stable")]
        data = flat.tobytes()
        row_step = width * point_step
        for _ in range(rnd.randint(0, 3)):
            kind = rnd.randrange(9)
            if kind == 0:
                point_step = rnd.choice([0, 1, 4, 12, 23, 2**31, 2**32 - 1])
            elif kind == 1:
                row_step = rnd.choice([0, row_step - 1, row_step + 1, 2**32 - 1])
            elif kind == 2:
                data = data[:rnd.randrange(len(data) + 1)]
            elif kind == 3:
                i = rnd.randrange(len(fields))
                fields[i] = dataclasses.replace(fields[i], offset=rnd.choice([13, 22, 24, 2**31,
                                                                               2**32 - 1]))
            elif kind == 4:
                i = rnd.randrange(len(fields))
                fields[i] = dataclasses.replace(fields[i], datatype=rnd.choice([0, 9, 255, 1, 8]))
            elif kind == 5:
                i = rnd.randrange(len(fields))
                fields[i] = dataclasses.replace(fields[i], count=rnd.choice([0, 2, 2**31]))
            elif kind == 6:
                fields.pop(rnd.randrange(len(fields)))
            elif kind == 7:
                width = rnd.choice([0, 2**31, 2**32 - 1, width + 1])
                height = rnd.choice([0, 2**31, 2**32 - 1, height])
            else:
                fields.append(dataclasses.replace(fields[rnd.randrange(len(fields))]))
        msg = self.cls(header=lt.Header(lt.Time(1, 0), "lidar"), height=height, width=width,
                       fields=tuple(fields), is_bigendian=rnd.random() < 0.05,
                       point_step=point_step, row_step=row_step,
                       data=np.frombuffer(data, np.uint8), is_dense=rnd.random() < 0.5)
        convert = CONV["from_pointcloud2"]
        layout = rnd.choice(["auto", "auto", "organized", "ring"])

        def run() -> str:
            scan, info = convert(msg, layout=layout, as_dataclass=True)
            exercise_scan(scan, info)
            return "converted"
        return repr(msg)[:4000], run


def _laser(rnd: random.Random, stamp_ns: int, frame: str = "laser") -> Any:
    cls = lt.message_class("sensor_msgs/msg/LaserScan")
    n = rnd.choice([0, 1, 2, 5, 360])
    ranges = np.array([rnd.uniform(0, 20) for _ in range(n)], np.float32)
    for _ in range(rnd.randint(0, 3)):
        if n:
            ranges[rnd.randrange(n)] = rnd.choice([np.nan, np.inf, -np.inf, 0.0, -1.0])
    inc = rnd.choice([2 * math.pi / max(n, 1), 0.0, -0.01, math.nan, math.inf, 1e-300, 10.0])
    amin = rnd.choice([-math.pi, 0.0, math.nan, -math.inf, 1e308])
    amax = rnd.choice([amin + inc * max(n - 1, 0), amin, math.nan, amin - 1])
    inten_n = rnd.choice([n, n, 0, n + 1, max(n - 1, 0)])
    sec, nsec = divmod(stamp_ns, 1_000_000_000)
    return cls(header=lt.Header(lt.Time(sec, nsec), frame), angle_min=amin, angle_max=amax,
               angle_increment=inc, time_increment=rnd.choice([0.0, 1e-5, -1e-5, math.nan]),
               scan_time=rnd.choice([0.1, 0.0, math.nan]),
               range_min=rnd.choice([0.1, 0.0, -1.0, math.nan, 30.0]),
               range_max=rnd.choice([30.0, 0.0, math.inf, math.nan, 0.05]),
               ranges=ranges, intensities=np.ones(inten_n, np.float32))


class LaserScanSweep(Target):
    """LaserScan inputs with inconsistent fields into sweep.from_laserscan_sweep."""
    name = "laserscan_sweep"
    needs = ("from_laserscan_sweep",)

    def case(self, rnd: random.Random) -> tuple[str, Callable[[], str]]:
        scans = [_laser(rnd, 1_000_000_000 + i) for i in range(rnd.choice([0, 1, 2, 5]))]
        if scans and rnd.random() < 0.7:  # mostly consistent geometry, so the deep code runs
            scans = [dataclasses.replace(s, angle_min=scans[0].angle_min,
                                         angle_increment=scans[0].angle_increment,
                                         ranges=np.resize(s.ranges, len(scans[0].ranges)),
                                         intensities=np.resize(s.intensities,
                                                               len(scans[0].ranges)))
                     for s in scans]
        joints = rnd.choice([np.linspace(-0.5, 0.5, len(scans)), np.full(len(scans), np.nan),
                             np.zeros(len(scans) + 1), np.zeros((len(scans), 2))])
        convert = CONV["from_laserscan_sweep"]
        return repr(scans)[:4000], lambda: (convert(scans, joints, as_dataclass=True),
                                            "converted")[1]


class MergerInputs(Target):
    """LaserScan inputs (bad fields, odd stamps) into LaserScanMerger: push then merge."""
    name = "merger"
    needs = ("merger",)

    def setup(self) -> None:
        self.mod = CONV["merger"]

    def case(self, rnd: random.Random) -> tuple[str, Callable[[], str]]:
        scans = [(rnd.choice(["front", "rear"] * 8 + ["nope"]),
                  _laser(rnd, rnd.choice([0, 1_000_000_000, 1_000_000_000 + i * 50_000_000,
                                          2**62, 5])))
                 for i in range(rnd.randint(1, 6))]

        def run() -> str:
            merger = make_merger(self.mod)
            for name, scan in scans:
                merger_push(merger, name, scan)
            merger_merge(merger, 1_000_000_000 + 300_000_000)
            return "merged"
        return repr(scans)[:4000], run


class WrongGeometry(Exception):
    """A scan released with an info that is not the one true geometry of its stamp (a failure:
    not a LidarScanError, so the runner counts it as a crash)."""


class LinkageEviction(Target):
    """Reconfiguring LidarInfo streams through InfoResolver with tiny bounds (1-3 infos kept,
    0-3 digests remembered): new versions, identical and conflicting republishes (also under
    evicted and forgotten stamps), stragglers naming old stamps, clock ticks. Each stamp has one
    true geometry (its first publication); a release with any other info, or under a stamp that
    carried two contents, raises WrongGeometry. Every scan must be released or dropped once."""
    name = "linkage_eviction"

    def setup(self) -> None:
        from lidarscan.geometry import info_key
        from lidarscan.linkage import InfoResolver

        self.resolver_class = InfoResolver
        self.key = info_key
        self.geometries = [self._info(0, g) for g in range(4)]
        self.digests = [info_key(g)[1] for g in self.geometries]
        self.totals: collections.Counter[str] = collections.Counter()

    @staticmethod
    @functools.lru_cache(maxsize=4096)
    def _info(stamp: int, g: int) -> Any:
        return ls.make_info(stamp_ns=stamp, frame_id="lidar",
                            vertical_angles=np.radians([15.0, 5.0, -5.0, -15.0]) + 0.03 * g,
                            horizontal_angles=2 * np.pi * (1 - np.arange(W) / W),
                            as_dataclass=True)

    def case(self, rnd: random.Random) -> tuple[str, Callable[[], str]]:
        bounds = {"max_infos": rnd.randint(1, 3), "max_digests": rnd.randint(0, 3),
                  "max_pending": rnd.randint(0, 4),
                  "max_wait_ns": rnd.choice([None, 5, 50])}
        ops = []
        newest = 0
        for _ in range(rnd.randint(5, 60)):
            r = rnd.random()
            if r < 0.25:  # a new version, usually later than the newest
                newest += rnd.randint(1, 3)
                ops.append(("info", 100 * newest, rnd.randrange(4), False))
            elif r < 0.4:  # republish any stamp: identical or not
                ops.append(("info", 100 * rnd.randint(1, newest + 2), rnd.randrange(4),
                            rnd.random() < 0.5))
            elif r < 0.9:  # a scan naming a recent stamp or a straggler
                back = 0 if rnd.random() < 0.6 else rnd.randint(1, 12)
                ops.append(("scan", 100 * max(1, newest - back), rnd.randrange(4), False))
            else:
                ops.append(("tick", rnd.randint(0, 30), 0, False))

        def run() -> str:
            clock = [0]
            resolver = self.resolver_class(clock=lambda: clock[0], **bounds)
            true: dict[int, int] = {}
            published: dict[int, set[int]] = {}
            outcome: dict[int, str] = {}
            scans = 0

            def check(pairs: list[tuple[Any, Any]]) -> None:
                for scan, info in pairs:
                    stamp = ls.to_ns(scan.lidar_info_time)
                    if (ls.to_ns(info.header.stamp) != stamp
                            or self.key(info)[1] != self.digests[true[stamp]]
                            or len(published.get(stamp, ())) != 1):
                        raise WrongGeometry(f"scan naming {stamp} paired wrongly")
                    sid = ls.to_ns(scan.header.stamp)
                    if sid in outcome:
                        raise WrongGeometry(f"scan {sid} released twice")
                    outcome[sid] = "released"
                for d in resolver.take_dropped():
                    if d.stamp_ns in outcome:
                        raise WrongGeometry(f"scan {d.stamp_ns} reported twice")
                    outcome[d.stamp_ns] = "dropped"

            for kind, a, g, same in ops:
                if kind == "info":
                    if a in true and (same or a not in published):
                        g = true[a]
                    true.setdefault(a, g)
                    published.setdefault(a, set()).add(g)
                    check(resolver.add_info(self._info(a, g)))
                elif kind == "scan":
                    g = true.setdefault(a, g)
                    scans += 1
                    check(resolver.add_scan(ls.make_scan(
                        self._info(a, g), {"range": np.ones((H, W), np.float32)}, scans,
                        as_dataclass=True)))
                else:
                    clock[0] += a
                    resolver.expire()
                    check([])
            resolver.flush()
            check([])
            if len(outcome) != scans:
                raise WrongGeometry(f"{scans - len(outcome)} scans lost silently")
            counts = collections.Counter(outcome.values())
            self.totals.update(counts)
            self.totals["scans"] += scans
            self.totals["conflicts"] += resolver.conflicts
            self.totals["forgotten"] += resolver.forgotten_ns is not None
            return "linked"
        return repr((bounds, ops))[:4000], run

    def summary(self) -> str:
        t = self.totals
        return (f"{t['scans']} scans: released {t['released']}, dropped {t['dropped']}, "
                f"0 wrong-geometry pairs unless reported as failures above; conflicts "
                f"{t['conflicts']}; cases past the digest bound {t['forgotten']}")


# The merger's API is bound once known (see _bind_merger); kept as module functions so the
# fault tests can reuse the same adapter.
def make_merger(mod: Any) -> Any:
    return _MERGER_ADAPTER["make"](mod)


def merger_push(merger: Any, name: str, scan: Any) -> Any:
    return _MERGER_ADAPTER["push"](merger, name, scan)


def merger_merge(merger: Any, now_ns: int) -> Any:
    return _MERGER_ADAPTER["merge"](merger, now_ns)


_MERGER_ADAPTER: dict[str, Callable[..., Any]] = {}
