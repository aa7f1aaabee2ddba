"""from_pointcloud2 on VLP-16 dual-return clouds as ROS 2's velodyne_pointcloud publishes them.

The clouds come from tests/velodyne_pointcloud_rules.py: the real VLP-32C packets of
tests/data/nebula/velodyne_vlp32 re-packed as VLP-16 dual-return packets (real echoes, real
packet receive stamps), turned into clouds by the driver's rules (rings by rising elevation; the
last packet's stamp; the single-return timing table on dual packets; both points of an identical
pair; one silent laser). Checked here: each rule of the generator on small packets built by hand,
then the import of the real-data clouds, with and without the ``time`` field: >= 98 % of the
cloud's points have a re-projected pixel within 2 mm (nearest neighbours, independent of the
importer's own matching), every point is a pixel, the silent laser's ring is no row, each
firing's two echoes are ``range`` / ``range2`` of one pixel, and the first returns' times come
back exactly.
"""

from __future__ import annotations

import struct
import tempfile
from functools import cache, lru_cache
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("rosbags")

import velodyne_pointcloud_rules as rules
from cloud_oracles import make_cloud
from test_hesai import nearest_within
from test_velodyne_packets import _read_bag, build_packet

import lidarscan
from converters import pointcloud2 as pc
from converters import velodyne

DATA = Path(__file__).parent / "data" / "nebula" / "velodyne_vlp32"
WITHIN_M, KEPT = 0.002, 0.98
PAIRED = 0.97          # pixels holding both echoes of one firing (see the importer test)
STAMP = 1_700_000_000_000_000_000


@lru_cache(maxsize=1)
def recording() -> tuple[tuple[int, tuple[tuple[int, bytes], ...]], ...]:
    with tempfile.TemporaryDirectory() as tmp:
        messages = _read_bag(DATA, Path(tmp))
    return tuple((rec, tuple(pk)) for rec, pk in messages)


@cache
def vlp16(message: int) -> tuple[list[tuple[int, bytes]], dict[str, Any]]:
    """VLP-16 dual packets of one VelodyneScan of the recording, and their calibration."""
    cal32 = velodyne.load_calibration(DATA / "VLP32.yaml")
    return rules.vlp16_dual_packets(recording()[message][1], cal32), rules.vlp16_calibration(cal32)


def scan_points(scan: Any, info: Any) -> np.ndarray[Any, Any]:
    """(N, 3) float64 points of every valid pixel of every return of a scan."""
    proj = lidarscan.make_projector(info)
    pts = []
    for name in lidarscan.scan.return_channels("range", lidarscan.scan.channel_names(scan)):
        xyz = proj.project(scan, info, name).astype(np.float64)
        pts.append(xyz[np.isfinite(xyz).all(-1)])
    return np.concatenate(pts)


# --------------------------------------------------------------- the generator's rules

def _packets(count: int = 2, stamps: Any = None) -> list[tuple[int, bytes]]:
    """Hand-made VLP-16 dual-return packets: block pair k of packet p at azimuth
    100 + 40 (6 p + k) (0.01 deg; 0.2 deg a firing sequence), laser d of firing sequence f at
    1000 + 10 d + f units (2 mm), reflectivity d."""
    out = []
    for p in range(count):
        az = [(100 + 40 * (6 * p + b // 2)) % 36000 for b in range(12)]
        dist = np.array([[1000 + 10 * (k % 16) + k // 16 for k in range(32)]] * 12)
        refl = np.array([[k % 16 for k in range(32)]] * 12)
        stamp = STAMP + p * 663_552 if stamps is None else stamps[p]
        out.append((stamp, build_packet(0x22, 0x39, 1000 + p * 664, az, dist, refl)))
    return out


def _cloud_fields(cloud: Any) -> np.ndarray[Any, Any]:
    """The cloud's finite points, in cloud order (what ``source`` describes)."""
    pts = pc.read_points(cloud).reshape(-1)
    return pts[np.isfinite(pts["x"])]


def test_rule_rings_rise_with_elevation_and_the_silent_laser_has_none() -> None:
    cal = velodyne.load_calibration(velodyne.VLP16_CALIBRATION)
    vert = [laser["vert_correction"] for laser in cal["lasers"]]
    assert list(rules.laser_rings(vert)) == [0, 8, 1, 9, 2, 10, 3, 11, 4, 12, 5, 13, 6, 14, 7, 15]
    packets, cal16 = vlp16(1)
    rings = rules.laser_rings([laser["vert_correction"] for laser in cal16["lasers"]])
    silent = rings[rules.SILENT_LASER]
    for organized in (True, False):
        cloud, source = rules.velodyne_cloud(packets[:20], cal16, organize_cloud=organized)
        pts = _cloud_fields(cloud)
        assert np.array_equal(pts["ring"], rings[source["laser"]])
        assert silent not in set(pts["ring"].tolist())
        assert not np.any(source["laser"] == rules.SILENT_LASER)
        everything = pc.read_points(cloud)
        if organized:      # one row a firing sequence, column = ring; the silent ring all NaN
            assert (cloud.height, cloud.width) == (20 * 24, 16)
            assert np.array_equal(everything["ring"], np.broadcast_to(np.arange(16), (480, 16)))
            assert np.isnan(everything["x"][:, silent]).all()
        else:
            assert cloud.height == 1 and np.isfinite(everything["x"]).all()


def test_rule_last_packet_stamp_and_negative_jittery_times() -> None:
    stamps = [STAMP, STAMP + 527_000, STAMP + 527_000 + 799_000]
    packets = _packets(count=3, stamps=stamps)
    cloud, source = rules.velodyne_cloud(packets, velodyne.VLP16_CALIBRATION)
    assert lidarscan.to_ns(cloud.header.stamp) == stamps[-1]
    pts = _cloud_fields(cloud)
    table = rules.timing_offsets()
    f32 = np.float32      # float offset + float (packet stamp - cloud stamp), as the driver
    want = (table[source["block"], 16 * source["firing"] + source["laser"]].astype(f32)
            + ((np.asarray(stamps)[source["packet"]] - stamps[-1]) * 1e-9).astype(f32))
    assert np.array_equal(pts["time"], want)
    assert pts["time"][source["packet"] == 0].max() < 0 < pts["time"][source["packet"] == 2].max()


def test_rule_single_return_table_on_dual_packets() -> None:
    table = rules.timing_offsets()
    assert table[11, 31] == pytest.approx(1306.368e-6) and table[0, 0] == 0.0
    packets = _packets(count=1)
    cloud, source = rules.velodyne_cloud(packets, velodyne.VLP16_CALIBRATION)
    t = _cloud_fields(cloud)["time"].astype(np.float64)
    for k in range(6):                 # block 2k: last, 2k+1: strongest of the same firings
        first = (source["block"] == 2 * k)
        second = (source["block"] == 2 * k + 1)
        assert np.allclose(t[second] - t[first], 110.592e-6, atol=1e-9)
    assert t.max() - t.min() == pytest.approx(1306.368e-6, abs=1e-9)


def test_rule_identical_pairs_published_twice_and_the_ros2_azimuths() -> None:
    packets = _packets(count=1)
    cal = velodyne.VLP16_CALIBRATION
    cloud, source = rules.velodyne_cloud(packets, cal, organize_cloud=False)
    assert cloud.width == 12 * 32                          # every point, both of a pair
    xyz = source["xyz"]
    block = source["block"]
    first, second = block % 2 == 0, block % 2 == 1
    rng = np.linalg.norm(xyz, axis=1)
    assert np.allclose(rng[first], rng[second], atol=1e-5)  # the same echo
    az = np.degrees(np.arctan2(-xyz[:, 1], xyz[:, 0])) % 360   # clockwise, as the sensor
    block_az = np.array([100 + 40 * (b // 2) for b in block]) / 100
    # gap to the next block: 0 for even blocks (one azimuth a pair), and for block 11 (it
    # takes block 10's); the odd blocks 1..9 interpolate over the pair (0.4 deg, 110.592 us)
    flat = first | (block == 11)
    assert np.allclose(az[flat], block_az[flat], atol=1e-3)
    want = block_az + 0.4 * (2.304 * source["laser"] + 55.296 * source["firing"]) / 110.592
    assert np.allclose(az[~flat], want[~flat], atol=0.0051)         # rounded to 0.01 deg
    assert not np.allclose(az[~flat], block_az[~flat], atol=1e-3)


def test_rule_odd_block_before_a_wrap_is_skipped() -> None:
    """A pair whose next pair wraps past 0 deg: its even block has gap 0 (kept), its odd block
    a negative gap after a zero one (skipped: the driver's ``continue``)."""
    az = [35960, 35960, 0, 0, 40, 40, 80, 80, 120, 120, 160, 160]
    dist = np.full((12, 32), 1000)
    refl = np.ones((12, 32), int)
    packet = (STAMP, build_packet(0x22, 0x39, 1000, az, dist, refl))
    cloud, source = rules.velodyne_cloud([packet], velodyne.VLP16_CALIBRATION)
    assert sorted(set(source["block"].tolist())) == [0, *range(2, 12)]
    assert cloud.height == 22                     # organized: no rows for the skipped block


def test_rule_point_layout_with_and_without_time() -> None:
    packets = _packets(count=1)
    cloud, _ = rules.velodyne_cloud(packets, velodyne.VLP16_CALIBRATION)
    assert [(f.name, f.offset, f.datatype) for f in cloud.fields] == list(rules.FIELDS)
    assert cloud.point_step == 22
    bare, _ = rules.velodyne_cloud(packets, velodyne.VLP16_CALIBRATION, with_time=False)
    assert [f.name for f in bare.fields] == ["x", "y", "z", "intensity", "ring"]


# --------------------------------------------------------------------- the importer

@pytest.mark.parametrize("organized", [True, False])
@pytest.mark.parametrize("with_time", [True, False])
@pytest.mark.parametrize("message", [1, 3])
def test_real_vlp16_dual_cloud_imports_within_2mm(message: int, with_time: bool,
                                                  organized: bool) -> None:
    packets, cal16 = vlp16(message)
    cloud, source = rules.velodyne_cloud(packets, cal16, with_time=with_time,
                                         organize_cloud=organized)
    scan, info = pc.from_pointcloud2(cloud, as_dataclass=True)
    lidarscan.validate(scan, info)
    names = lidarscan.scan.channel_names(scan)
    assert {"range", "range2", "intensity", "intensity2", "azimuth", "azimuth2"} <= set(names)
    pts = _cloud_fields(cloud)
    rings = sorted(set(pts["ring"].tolist()))
    assert scan.height == len(rings) == 15 and sorted(info.beam_ids) == rings
    back = scan_points(scan, info)
    assert back.shape[0] == pts.size                    # every point is a pixel, pairs too
    dist = nearest_within(source["xyz"], back, WITHIN_M)
    within = float(np.isfinite(dist).mean())
    # the firings (columns): a pair's first echoes share one azimuth, so the columns come from
    # the cloud order; the sensor's own firing of a point is known here
    fired = 12 * source["packet"] + 2 * (source["block"] // 2) + source["firing"]
    r1, r2 = (np.asarray(lidarscan.scan.channel(scan, n)) for n in ("range", "range2"))
    both = np.isfinite(r1) & np.isfinite(r2)
    same = both & np.isclose(r1, r2, rtol=1e-5, atol=1e-5)
    print(f"\n{pts.size} points, {within:.4%} within {WITHIN_M * 1e3:.0f} mm, "
          f"{scan.width} columns for {np.ptp(fired) + 1} firings, "
          f"{same.sum() / np.isfinite(r1).sum():.4%} pixels with both echoes of one firing")
    assert within >= KEPT, within
    # both echoes of a firing in one pixel (one echo a firing here: range2 equals range); a
    # lone echo at its pair's azimuth may take the pair's other firing (measured: 97.6 %, 97.9 %)
    assert same.sum() >= PAIRED * np.isfinite(r1).sum()
    assert scan.width <= 2 * (np.ptp(fired) + 1)
    if with_time:
        stamp = lidarscan.to_ns(cloud.header.stamp)
        t_cloud = np.rint(pts["time"].astype(np.float64) * 1e9).astype(np.int64) + stamp
        first = source["block"] % 2 == 0
        proj = lidarscan.make_projector(info)
        times = proj.pixel_times(scan) + np.int64(lidarscan.to_ns(scan.header.stamp))
        xyz1 = proj.project(scan, info, "range").astype(np.float64)
        # a first return's pixel time is its cloud time (float32 seconds: <= 8 ns): of the
        # pixels within 2 mm of the point (a pair's two first echoes share one direction, so
        # both of one range are), the one nearest in time
        ok = np.isfinite(xyz1).all(-1)
        d, idx = _nearest(source["xyz"][first], xyz1[ok], t_cloud[first], times[ok])
        good = d <= WITHIN_M
        assert good.mean() >= KEPT
        exact = np.abs(times[ok][idx[good]] - t_cloud[first][good]) <= 8
        assert exact.mean() >= KEPT, exact.mean()
        # beams fire 2.304 us apart, as the times say
        offsets = np.asarray(info.beam_time_offsets, np.float64)
        assert np.allclose(offsets, 2304 * np.rint(offsets / 2304), atol=8)     # float32 s
        assert offsets.max() <= 15 * 2304 + 8


def _nearest(a: np.ndarray[Any, Any], b: np.ndarray[Any, Any], time_a: Any = None,
             time_b: Any = None) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
    """Distance and index of the nearest point of b for every point of a (grid search); with
    times, of the points of b within WITHIN_M the one nearest in time."""
    cell = 0.05
    keys = np.floor(b / cell).astype(np.int64)
    table: dict[tuple[int, int, int], list[int]] = {}
    for i, key in enumerate(map(tuple, keys)):
        table.setdefault(key, []).append(i)
    dist = np.full(a.shape[0], np.inf)
    index = np.zeros(a.shape[0], np.int64)
    for j, p in enumerate(a):
        base = np.floor(p / cell).astype(np.int64)
        cand = [i for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1)
                for i in table.get((base[0] + dx, base[1] + dy, base[2] + dz), [])]
        if cand:
            dd = np.linalg.norm(b[cand] - p, axis=1)
            k = int(np.argmin(dd))
            if time_a is not None and dd[k] <= WITHIN_M:
                near = np.flatnonzero(dd <= WITHIN_M)
                k = int(near[np.argmin(np.abs(np.asarray(time_b)[np.asarray(cand)[near]]
                                              - time_a[j]))])
            dist[j], index[j] = dd[k], cand[k]
    return dist, index


def test_importer_unit_negative_times_empty_ring_and_pairs() -> None:
    """A small velodyne-layout cloud: times all negative (stamp after the last firing), ring 2
    empty, every firing's echo twice (identical pair) with its copy stamped 2 firings later:
    rows are the rings with points, the pair is range/range2 of one pixel, column times are the
    first echoes' (absolute), beam offsets the lasers'."""
    period, lag, beams = 50_000, 2_000, [0, 1, 3]
    firings = 400
    names = ["x", "y", "z", "intensity", "ring", "time"]
    pts = np.zeros(2 * firings * len(beams),
                   np.dtype({"names": names, "formats": ["<f4"] * 4 + ["<u2", "<f4"]}))
    stamp = STAMP + firings * period
    i = 0
    for f in range(firings):
        az = -np.radians(0.9 * f)
        for copy in (0, 1):
            for b in beams:
                elev = np.radians(-10 + 5 * b)
                r = 5 + (f % 7) + b
                pts[i] = (r * np.cos(elev) * np.cos(az), r * np.cos(elev) * np.sin(az),
                          r * np.sin(elev), 10 * b, b,
                          (f * period + b * lag + copy * 2 * period - firings * period) * 1e-9)
                i += 1
    cloud = make_cloud(pts, height=1, width=pts.size, stamp_ns=stamp, frame_id="velodyne")
    scan, info = pc.from_pointcloud2(cloud, as_dataclass=True)
    assert scan.height == 3 and sorted(info.beam_ids) == beams
    assert abs(int(scan.width) - firings) <= 1
    r1, r2 = (np.asarray(lidarscan.scan.channel(scan, n)) for n in ("range", "range2"))
    assert np.array_equal(r1, r2) and np.isfinite(r1).sum() == firings * len(beams)
    assert lidarscan.to_ns(scan.header.stamp) == pytest.approx(STAMP, abs=100)
    assert sorted(np.asarray(info.beam_time_offsets).tolist()) == pytest.approx(
        [0, lag, 3 * lag], abs=100)
    assert int(info.column_time_increment) == pytest.approx(period, rel=0.01)


def test_importer_unit_jittery_column_times() -> None:
    """Column times of a cloud stamped per packet with jitter (all points of a packet share
    their packet's receive time): the increment is the firings' period, not a jitter step."""
    rng = np.random.default_rng(3)
    period, per_packet, packets, beams = 55_296, 12, 60, 4
    jitter = rng.integers(-130_000, 130_000, packets)
    names = ["x", "y", "z", "intensity", "ring", "time"]
    n = packets * per_packet * beams
    pts = np.zeros(n, np.dtype({"names": names, "formats": ["<f4"] * 4 + ["<u2", "<f4"]}))
    i = 0
    for p in range(packets):
        for s in range(per_packet):
            f = p * per_packet + s
            az = -np.radians(0.2 * f)
            for b in range(beams):
                elev = np.radians(-6 + 4 * b)
                pts[i] = (8 * np.cos(elev) * np.cos(az), 8 * np.cos(elev) * np.sin(az),
                          8 * np.sin(elev), 1, b,
                          (p * per_packet * period + jitter[p]) * 1e-9 - 0.05)
                i += 1
    cloud = make_cloud(pts, height=1, width=n, stamp_ns=STAMP, frame_id="velodyne")
    scan, info = pc.from_pointcloud2(cloud, as_dataclass=True)
    assert abs(int(scan.width) - packets * per_packet) <= 1
    assert int(info.column_time_increment) == pytest.approx(period, rel=0.1)


def test_generated_packets_decode_like_the_source() -> None:
    """The re-packed VLP-16 packets are valid: the project's decoder reads them as VLP-16 dual
    return with both returns equal, and their first 16 lasers' echoes are the VLP-32C's."""
    packets, cal16 = vlp16(1)
    data = packets[0][1]
    assert len(data) == 1206 and data[1204:] == bytes([0x39, 0x22])
    src = recording()[1][1][0][1]
    lasers = rules.vlp16_lasers(velodyne.load_calibration(DATA / "VLP32.yaml"))
    for d in range(16):
        raw32 = struct.unpack_from("<H", src, 4 + 3 * lasers[d])[0]
        raw16 = struct.unpack_from("<H", data, 4 + 3 * d)[0]
        want = 0 if d == rules.SILENT_LASER or 2 * raw32 > 0xFFFF else 2 * raw32
        assert raw16 == want
    scans = list(velodyne.decode_packets(packets, cal16, as_dataclass=True))
    scan, _ = max(scans, key=lambda s: s[0].width)
    r1, r2 = (np.asarray(lidarscan.scan.channel(scan, n)) for n in ("range", "range2"))
    assert np.array_equal(r1, r2)


def test_runs_of_one_azimuth_without_a_firing_structure_are_refused() -> None:
    """Every point twice in a row (runs of one azimuth, as a block pair's first echoes) on a
    ring cloud that follows no firing pattern: the block-pair layout does not hold it either,
    and the refusal says everything that was tried."""
    rng = np.random.default_rng(4)
    n = 6000
    yaw = rng.uniform(-np.pi, np.pi, n)
    pitch = np.radians(rng.uniform(-15, 15, n))
    rho = rng.uniform(2, 40, n)
    xyz = np.repeat(np.stack([rho * np.cos(pitch) * np.cos(yaw),
                              rho * np.cos(pitch) * np.sin(yaw), rho * np.sin(pitch)], -1),
                    2, axis=0)
    pts = np.zeros(2 * n, np.dtype({"names": ["x", "y", "z", "intensity", "ring"],
                                    "formats": ["<f4"] * 4 + ["<u2"]}))
    for j, a in enumerate("xyz"):
        pts[a] = xyz[:, j]
    pts["ring"] = np.repeat(np.arange(n) % 8, 2)
    with pytest.raises(lidarscan.errors.ConversionError) as exc:
        pc.from_pointcloud2(make_cloud(pts, height=1, width=2 * n, stamp_ns=STAMP))
    text = str(exc.value)
    assert "without a pixel" in text and "block pairs" in text and "info=" in text, text
