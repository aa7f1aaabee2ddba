"""from_pointcloud2 on real driver clouds: velodyne_pointcloud, Hesai ROS driver, Nebula.

The clouds are written by tests/driver_clouds.py from the decoded Nebula recordings (the packet
decoders are checked against Nebula's ground-truth PCDs elsewhere); every check here compares the
re-imported scan with those decoded points (nearest neighbours, independent of the estimator's
own matching) and, for Hesai, with Nebula's PCD. Targets: >= 98 % of the points kept as valid
pixels, re-projection median <= 2 mm and p99 <= 20 mm. Dual return comes from synthetic Velodyne
packets run through the same decoder and from the synthetic VLP-16 cloud of the issue.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

pytest.importorskip("rosbags")
pytest.importorskip("sensor_msgs.msg")

import lidarscan  # noqa: E402
from converters.pointcloud2 import converter as pc  # noqa: E402
from converters.sources import velodyne  # noqa: E402
from lidarscan.errors import ConversionError  # noqa: E402

import driver_clouds as dc  # noqa: E402
from pcd import read_pcd  # noqa: E402
from test_hesai import nearest_within  # noqa: E402
from cloud_oracles import make_cloud  # noqa: E402

RECORDINGS = ("velodyne_vlp32", "velodyne_vls128", "hesai_xt32", "hesai_pandar64", "hesai_qt64")
KEPT, MEDIAN, P99 = 0.98, 0.002, 0.020


def scan_points(scan: Any, info: Any) -> np.ndarray[Any, Any]:
    """(N, 3) float64 points of every valid pixel of every return of a scan."""
    proj = lidarscan.make_projector(info)
    out = []
    for name in ("range", "range2"):
        if name in lidarscan.scan.channel_names(scan):
            xyz = proj.project(scan, info, name)
            out.append(xyz[np.isfinite(xyz).all(-1)])
    return np.concatenate(out).astype(np.float64)


def check_reimport(cloud: Any, truth: np.ndarray[Any, Any], scan: Any, info: Any
                   ) -> dict[str, float]:
    """Kept share and nearest-neighbour errors of the re-imported scan against the truth."""
    back = scan_points(scan, info)
    kept = back.shape[0] / truth.shape[0]
    names = [f.name for f in cloud.fields]
    sample = truth[::max(1, truth.shape[0] // 20_000)]    # scipy-free search: a sample
    dist = nearest_within(sample, back, 0.03)              # inf: nothing within 3 cm
    figures = {"kept": kept, "median_m": float(np.median(dist)),
               "p99_m": float(np.quantile(dist, 0.99))}
    err = pc.estimation_error(cloud, scan, info) if "ring" in names or "channel" in names else None
    print(f"\nfigures: {cloud.width} points, kept {kept:.4%}, nearest decoded point: median "
          f"{figures['median_m'] * 1e3:.4f} mm, p99 {figures['p99_m'] * 1e3:.4f} mm"
          + (f"; estimation_error median {err.median_m * 1e3:.4f} mm, p99 {err.p99_m * 1e3:.4f}"
             f" mm, max {err.max_m * 1e3:.3f} mm" if err else ""))
    assert kept >= KEPT and kept <= 1.0, figures
    assert figures["median_m"] <= MEDIAN and figures["p99_m"] <= P99, figures
    # what the cloud becomes again (to_pointcloud2, one cloud a return): as many points
    again = 0
    for name in ("range", "range2"):
        if name in lidarscan.scan.channel_names(scan):
            out = pc.read_points(pc.to_pointcloud2(scan, info, range_channel=name))
            xyz = np.stack([out[a].astype(np.float64).ravel() for a in "xyz"], -1)
            again += int(np.isfinite(xyz).all(-1).sum())
    assert again >= KEPT * truth.shape[0], (again, truth.shape[0])
    return figures


def middle_scan(name: str) -> tuple[Any, Any]:
    scans = dc.full_scans(name)
    return scans[len(scans) // 2]


@pytest.mark.parametrize("kind", dc.KINDS)
@pytest.mark.parametrize("name", RECORDINGS)
def test_real_driver_cloud_reimports_within_targets(name: str, kind: str,
                                                    record_property: Any) -> None:
    scan, info = middle_scan(name)
    cloud, truth = dc.driver_cloud(scan, info, kind)
    back, est = pc.from_pointcloud2(cloud, as_dataclass=True)
    lidarscan.validate(back, est)
    figures = check_reimport(cloud, truth, back, est)
    err = pc.estimation_error(cloud, back, est)
    assert err.matched >= KEPT * err.points, err
    assert err.median_m <= MEDIAN and err.p99_m <= P99, err
    for key, value in figures.items():
        record_property(key, value)
    # rows are the sensor's beams (those with points), beam_ids the cloud's ring numbers
    assert back.height <= info.height and back.height >= 0.95 * info.height
    if kind != "velodyne_notime":
        # times come back: each point's time is its pixel's
        assert err.max_time_ns is not None and err.max_time_ns < 1000, err


@pytest.mark.parametrize("name", ("hesai_xt32", "hesai_pandar64", "hesai_qt64"))
def test_nebula_cloud_reimport_matches_nebula_pcd(name: str) -> None:
    """The Nebula-layout cloud of the rotation Nebula's PCD shows re-imports onto the PCD."""
    gt = read_pcd(next((dc.DATA / name).glob("ground_truth_*.pcd"))).astype(np.float64)
    scans = dc.decoded(name)
    hits = [np.isfinite(nearest_within(gt[::50], scan_points(s, i), 0.002)).sum()
            for s, i in scans]
    scan, info = scans[int(np.argmax(hits))]
    cloud, truth = dc.driver_cloud(scan, info, "nebula")
    back, est = pc.from_pointcloud2(cloud, as_dataclass=True)
    sample = gt[::7]
    seen = np.isfinite(nearest_within(sample, truth, 0.002))      # PCD points of this rotation
    again = np.isfinite(nearest_within(sample[seen], scan_points(back, est), 0.002))
    assert seen.mean() > 0.5 and again.mean() >= KEPT, (seen.mean(), again.mean())


# --------------------------------------------------------------------- dual return (decoder)

@pytest.mark.parametrize("kind", dc.KINDS)
@pytest.mark.parametrize(("product", "calib"), [("VLP-16", None),
                                               ("VLP-32C", "velodyne_vlp32/VLP32.yaml"),
                                               ("VLS-128", "velodyne_vls128/VLS128.yaml")])
def test_dual_return_packets_become_range_and_range2(product: str, calib: str | None,
                                                     kind: str) -> None:
    from test_velodyne_packets import MODES, PRODUCTS, synthetic_stream

    packets = synthetic_stream(PRODUCTS[product], MODES["dual"], 400, deg_per_sequence=0.2,
                               seed=5)
    calibration = velodyne.load_calibration(dc.DATA / calib) if calib else None
    results = list(velodyne.decode_packets(packets, calibration, azimuth_model="manual",
                                           as_dataclass=True))       # per-beam, see dc.decoded
    scan, info = max(results, key=lambda r: r[0].width)
    assert "range2" in lidarscan.scan.channel_names(scan)
    cloud, truth = dc.driver_cloud(scan, info, kind)
    back, est = pc.from_pointcloud2(cloud, as_dataclass=True)
    names = lidarscan.scan.channel_names(back)
    assert "range2" in names and "intensity2" in names
    assert back.width <= scan.width + 1                  # one column a firing, not two
    check_reimport(cloud, truth, back, est)
    err = pc.estimation_error(cloud, back, est)
    assert err.matched == err.points and err.p99_m <= P99, err


# ------------------------------------------------------------- synthetic VLP-16 of the issue

def vlp16_dual_cloud(*, with_time: bool = True, seed: int = 7
                     ) -> tuple[Any, np.ndarray[Any, Any]]:
    """velodyne_pointcloud's VLP-16 dual-return cloud: x, y, z, intensity, ring, time.

    16 lasers (-15..15 deg interleaved), one firing every 55.296 us (laser k at +2.304 us k),
    two firings a block, blocks in pairs (last, strongest) with the same azimuth and times, as
    velodyne_pointcloud emits them: per block pair, firing A last, firing B last, A strongest,
    B strongest. 20 % no return (omitted), 40 % of the firings' second return differs.
    """
    rng = np.random.default_rng(seed)
    lasers = np.arange(16)
    elev = np.radians(np.where(lasers % 2 == 0, -15 + lasers, lasers))
    ring = np.argsort(np.argsort(elev))
    firings = 1808
    az = np.radians(np.arange(firings) * 0.2 + rng.normal(0, 0.002, firings))   # clockwise
    t = np.arange(firings)[:, None] * 55_296 + lasers[None, :] * 2_304        # (F, 16) ns
    last = rng.uniform(1, 80, (firings, 16))
    strongest = np.where(rng.random((firings, 16)) < 0.4, rng.uniform(1, 80, (firings, 16)),
                         last)
    present = rng.random((firings, 16)) > 0.2
    order = []                                            # (firing, laser, which return)
    for pair in range(firings // 2):
        for which in (0, 1):
            for f in (2 * pair, 2 * pair + 1):
                order.extend((f, k, which) for k in lasers if present[f, k])
    f, k, w = (np.array(v) for v in zip(*order))
    rho = np.where(w == 0, last[f, k], strongest[f, k])
    theta = -az[f] + np.radians(0.0)
    xyz = np.stack([rho * np.cos(elev[k]) * np.cos(theta), rho * np.cos(elev[k]) * np.sin(theta),
                    rho * np.sin(elev[k])], -1)
    names = ["x", "y", "z", "intensity", "ring"] + (["time"] if with_time else [])
    dtype = np.dtype({"names": names, "formats": ["<f4"] * 4 + ["<u2"] + ["<f4"] * with_time})
    pts = np.zeros(f.size, dtype)
    for j, a in enumerate("xyz"):
        pts[a] = xyz[:, j]
    pts["intensity"] = rng.uniform(0, 255, f.size)
    pts["ring"] = ring[k]
    if with_time:
        pts["time"] = t[f, k] * 1e-9
    cloud = make_cloud(pts, height=1, width=f.size, stamp_ns=1_700_000_000_000_000_000,
                       frame_id="velodyne")
    return cloud, xyz


@pytest.mark.parametrize("with_time", [True, False])
def test_issue_vlp16_dual_return_cloud(with_time: bool) -> None:
    cloud, truth = vlp16_dual_cloud(with_time=with_time)
    scan, info = pc.from_pointcloud2(cloud, as_dataclass=True)
    assert scan.height == 16 and abs(scan.width - 1808) <= 1, (scan.height, scan.width)
    if with_time:
        assert int(info.column_time_increment) == pytest.approx(55_296, abs=10)
    check_reimport(cloud, truth, scan, info)
    err = pc.estimation_error(cloud, scan, info)
    assert err.matched == err.points and err.median_m <= MEDIAN and err.p99_m <= P99, err


# ----------------------------------------------------------------- xyz only + a known LidarInfo

@pytest.mark.parametrize("name", RECORDINGS)
def test_xyz_only_cloud_with_the_decoders_info(name: str) -> None:
    scan, info = middle_scan(name)
    cloud, truth = dc.driver_cloud(scan, info, "velodyne_notime")
    pts = pc.read_points(cloud).reshape(-1)
    xyz_only = np.zeros(pts.size, np.dtype({"names": list("xyz"), "formats": ["<f4"] * 3}))
    for a in "xyz":
        xyz_only[a] = pts[a]
    bare = make_cloud(xyz_only, height=1, width=pts.size, stamp_ns=0)
    back, same = pc.from_pointcloud2(bare, info=info, as_dataclass=True)
    assert same is info
    lidarscan.validate(back, info)
    check_reimport(bare, truth, back, info)


# ----------------------------------------------------------------------- clouds with no grid

def rosette(points: int = 20_000, seed: int = 0) -> np.ndarray[Any, Any]:
    """Livox-like non-repetitive rosette: (N, 3) points, no beams."""
    rng = np.random.default_rng(seed)
    t = np.sort(rng.uniform(0, 0.1, points))
    r = np.radians(35) * np.abs(np.sin(2 * np.pi * 1234.5 * t))
    ang = 2 * np.pi * 87.3 * t
    yaw, pitch = r * np.cos(ang), r * np.sin(ang)
    rho = rng.uniform(2, 40, points)
    return np.stack([rho * np.cos(pitch) * np.cos(yaw), rho * np.cos(pitch) * np.sin(yaw),
                     rho * np.sin(pitch)], -1)


@pytest.mark.parametrize("height", [1, 4])
def test_livox_rosette_is_refused_with_a_clear_error(height: int) -> None:
    xyz = rosette()
    dtype = np.dtype({"names": ["x", "y", "z", "intensity", "tag", "line", "timestamp"],
                      "formats": ["<f4", "<f4", "<f4", "<f4", "u1", "u1", "<f8"]})
    pts = np.zeros(xyz.shape[0], dtype)
    for j, a in enumerate("xyz"):
        pts[a] = xyz[:, j]
    pts["timestamp"] = 1.7e9 + np.arange(xyz.shape[0]) * 5e-6
    cloud = make_cloud(pts, height=height, width=xyz.shape[0] // height)
    with pytest.raises(ConversionError) as exc:
        pc.from_pointcloud2(cloud)
    text = str(exc.value)
    assert "tried" in text and "PointCloud2" in text and "info=" in text, text


def test_ring_cloud_without_structure_is_refused() -> None:
    """Ring numbers on points that follow no firing pattern: refused, not 30 % lost."""
    xyz = rosette(seed=1)
    dtype = np.dtype({"names": ["x", "y", "z", "ring", "time"],
                      "formats": ["<f4", "<f4", "<f4", "<u2", "<f4"]})
    pts = np.zeros(xyz.shape[0], dtype)
    for j, a in enumerate("xyz"):
        pts[a] = xyz[:, j]
    pts["ring"] = np.arange(xyz.shape[0]) % 6
    pts["time"] = np.random.default_rng(2).uniform(0, 0.1, xyz.shape[0])
    with pytest.raises(ConversionError, match="tried"):
        pc.from_pointcloud2(make_cloud(pts, height=1, width=xyz.shape[0]))


def test_cloud_sorted_ring_after_ring_without_times() -> None:
    """A cloud re-sorted by ring (not in firing order) still gets one column a firing."""
    cloud, truth = vlp16_dual_cloud(with_time=False)
    pts = pc.read_points(cloud).reshape(-1)
    order = np.argsort(pts["ring"], kind="stable")
    sorted_cloud = make_cloud(pts[order].copy(), height=1, width=pts.size, stamp_ns=10**18)
    scan, info = pc.from_pointcloud2(sorted_cloud, as_dataclass=True)
    assert scan.height == 16 and abs(scan.width - 1808) <= 1
    check_reimport(sorted_cloud, truth[order], scan, info)


def test_times_shared_by_a_block_fall_back_to_the_point_order() -> None:
    """A driver that stamps whole blocks (4 firings one time): columns from the point order."""
    cloud, truth = vlp16_dual_cloud(with_time=True)
    pts = pc.read_points(cloud).reshape(-1).copy()
    pts["time"] = np.floor(pts["time"] / 221.184e-6) * 221.184e-6
    coarse = make_cloud(pts, height=1, width=pts.size, stamp_ns=10**18)
    scan, info = pc.from_pointcloud2(coarse, as_dataclass=True)
    assert scan.height == 16 and abs(scan.width - 1808) <= 1, (scan.height, scan.width)
    check_reimport(coarse, truth, scan, info)
    assert scan.column_time_offsets is not None and len(scan.column_time_offsets) == scan.width
    err = pc.estimation_error(coarse, scan, info)
    assert err.matched == err.points and err.p99_m <= P99, err
