"""Which intra-sequence firing times are physically right: the manuals' or Nebula's? Measured.

``python -m converters.edge.evidence.velodyne_timing`` (reads the real recordings under
``tests/data/nebula/velodyne_*``; ``tests/test_velodyne_packets.py`` runs :func:`measure` too).

Within one firing sequence (one column) the lasers fire at different times ``t_u`` while the
head turns at ``omega``, so laser u looks ``omega * t_u`` further along than the column's
azimuth. The two candidate timings:

* manual (the decoder's ``azimuth_model="manual"``): VLP-32C ``2.304 us * (k // 2)`` (lasers fire in pairs),
  VLS-128 ``2.665 us * (k // 8 + k // 64)`` (8 lasers at a time, a gap after group 7);
* Nebula (its decoder, which made the ground truth): the azimuth interpolated towards the next
  block: VLP-32C ``2.304 us * k``; VLS-128 0 for lasers 0-95 (their blocks share the sequence's
  azimuth) and ``2.665 us * (k // 8 + k // 64)`` for lasers 96-127; both 0 in the last
  sequence of each packet (no next block to interpolate to).

The measurement: a vertical depth edge (pole, wall corner, door) crosses vertically adjacent
beams at the same true azimuth. Per row, depth edges are the column pairs whose range jumps
(> 0.25 m + 5 %); each edge of row u is matched with the nearest edge of the same sign and a
similar near range in the elevation-adjacent row u+1 (within 0.5 deg). Under a timing model M
each pixel's azimuth is ``alpha_c + rot_u - omega * t_M(u, c)``; the mean azimuth difference
of matched edges of a row pair is 0 when M is the sensor's timing (edges are quantised to the
column grid, but their phases are uniform, so the mean is unbiased; slanted edges add noise,
not a per-pair pattern). Figures: the RMS over row pairs of that mean (weighted by edge count),
beside its noise floor (the RMS standard error); and a regression of the pairs' mean shift
under "no intra-sequence timing" against each model's predicted ``omega * (t_u+1 - t_u)``:
the right model has slope 1.
"""

from __future__ import annotations

import math
import sqlite3
import struct
from pathlib import Path
from typing import Any

import numpy as np

DATA = Path(__file__).resolve().parents[3] / "tests" / "data" / "nebula"
#: recording -> (calibration file, cut angle the ground truth used)
RECORDINGS = {"velodyne_vlp32": ("VLP32.yaml", 180.0), "velodyne_vls128": ("VLS128.yaml", 0.0)}


def read_bag(folder: Path) -> list[tuple[int, bytes]]:
    """(stamp ns, payload) of every packet of a rosbag2 sqlite bag of velodyne_msgs/VelodyneScan
    (plain CDR little-endian: header, then a sequence of {stamp, uint8[1206]})."""
    out = []
    for db in sorted((folder / "bag").glob("*.db3")):
        with sqlite3.connect(db) as con:
            for (raw,) in con.execute("SELECT data FROM messages ORDER BY timestamp"):
                pos = 4 + 8                                     # encapsulation, header.stamp
                (length,) = struct.unpack_from("<I", raw, pos)
                pos += 4 + length                               # frame_id
                pos += (-(pos - 4)) % 4                         # CDR alignment
                (count,) = struct.unpack_from("<I", raw, pos)
                pos += 4
                for _ in range(count):
                    pos += (-(pos - 4)) % 4
                    sec, nsec = struct.unpack_from("<iI", raw, pos)
                    out.append((sec * 10**9 + nsec, bytes(raw[pos + 8:pos + 8 + 1206])))
                    pos += 8 + 1206
    return out


def _models(lasers: np.ndarray[Any, Any], product: str) -> dict[str, np.ndarray[Any, Any]]:
    """(H,) firing time (ns) of each row's laser under each model (Nebula: non-last sequences)."""
    k = lasers.astype(np.int64)
    if product == "VLP-32C":
        return {"manual": 2304.0 * (k // 2), "nebula": 2304.0 * k}
    group = 2665.0 * (k // 8 + k // 64)
    return {"manual": group, "nebula": np.where(k >= 96, group, 0.0)}


def _edges(theta: np.ndarray[Any, Any], rng: np.ndarray[Any, Any], ok: np.ndarray[Any, Any]
           ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any], np.ndarray[Any, Any]]:
    """Depth edges of one row: (position rad, sign, near range m)."""
    with np.errstate(invalid="ignore"):
        jump = rng[1:] - rng[:-1]
    near = np.minimum(rng[1:], rng[:-1])
    edge = ok & (np.abs(jump) > 0.25 + 0.05 * near)
    return 0.5 * (theta[1:] + theta[:-1])[edge], np.sign(jump[edge]), near[edge]


def _match(a: tuple[Any, ...], b: tuple[Any, ...], window: float) -> np.ndarray[Any, Any]:
    """Azimuth differences b - a of matched edges (same sign, near ranges within 5 % + 0.1 m)."""
    out = []
    for sign in (-1.0, 1.0):
        pa, ra = a[0][a[1] == sign], a[2][a[1] == sign]
        order = np.argsort(b[0][b[1] == sign])
        pb, rb = b[0][b[1] == sign][order], b[2][b[1] == sign][order]
        if pa.size == 0 or pb.size == 0:
            continue
        idx = np.searchsorted(pb, pa)
        best = np.full(pa.size, np.inf)
        for cand in (idx - 1, idx):
            c = np.clip(cand, 0, pb.size - 1)
            d = pb[c] - pa
            fits = (np.abs(rb[c] - ra) < 0.05 * ra + 0.1) & (np.abs(d) < np.abs(best))
            best = np.where(fits, d, best)
        out.append(best[np.abs(best) < window])
    return np.concatenate(out) if out else np.zeros(0)


def measure(packets: list[tuple[int, bytes]], calib: dict[str, Any], cut: float
            ) -> dict[str, Any]:
    """Edge alignment of elevation-adjacent rows under each timing model, over all rotations.

    Returns model -> (weighted RMS of the per-pair mean shift in millidegrees, its noise floor),
    the regression slopes, edge and pair counts, and omega (deg/s).
    """
    import lidarscan
    from converters.sources.velodyne import MODELS, decode_packets

    rot_by_id = {int(las["laser_id"]): float(las.get("rot_correction", 0.0))
                 for las in calib["lasers"]}
    shifts: dict[str, dict[int, list[np.ndarray[Any, Any]]]] = {}
    names = ("none", "manual", "nebula")
    for scan, info in decode_packets(packets, calib, cut_angle_deg=cut, as_dataclass=True):
        model = MODELS[{"VLP-32C": 0x28, "VLS-128": 0xA1}[info.model]]
        lasers = np.asarray(info.beam_ids, np.int64)
        rot = np.array([rot_by_id[int(k)] for k in lasers])
        times = np.asarray(scan.column_time_offsets, np.float64)
        alpha = np.asarray(scan.column_azimuth_angles, np.float64)       # ccw
        real = np.append(np.diff(times) > 0, False) & (times >= 0)
        if real.sum() < 100:
            continue
        dt, da = np.diff(times), np.diff(np.unwrap(alpha))
        regular = (dt > 0) & (dt < 1.5 * model.sequence_ns)           # consecutive firings
        omega = -da[regular].sum() / (dt[regular].sum() * 1e-9)       # rad/s, clockwise
        last = np.append(np.abs(dt - round(model.sequence_ns)) > 1, True)  # last of its packet
        gap = np.where(last, 0.0, -np.append(da, 0.0))                # rad to the next block
        t_model = _models(lasers, info.model)
        rng = lidarscan.range_m(scan, info).astype(np.float64) + np.asarray(
            info.beam_range_offsets)[:, None]
        valid = np.isfinite(rng) & (rng > 1.0)
        steady = np.append(regular, False)                              # c, c+1 consecutive
        theta0 = np.unwrap(alpha)[None, :] + rot[:, None]
        thetas = {"none": theta0,
                  "manual": theta0 - omega * t_model["manual"][:, None] * 1e-9,
                  "nebula": theta0 - gap[None, :] * (t_model["nebula"][:, None]
                                                     / model.sequence_ns)}
        for name in names:
            th = thetas[name]
            edges = [_edges(th[u], rng[u], valid[u, 1:] & valid[u, :-1] & steady[:-1])
                     for u in range(th.shape[0])]
            for u in range(th.shape[0] - 1):
                d = _match(edges[u], edges[u + 1], math.radians(0.5))
                shifts.setdefault(name, {}).setdefault(u, []).append(d)
        last_info = (info.model, omega, t_model, np.asarray(info.vertical_angles))
    product, omega, t_model, elevations = last_info
    result: dict[str, Any] = {"model": product, "omega_deg_s": math.degrees(omega)}
    means: dict[str, np.ndarray[Any, Any]] = {}
    for name in names:
        per_pair = [np.concatenate(shifts[name][u]) for u in sorted(shifts[name])]
        n = np.array([p.size for p in per_pair], np.float64)
        mean = np.array([p.mean() if p.size else 0.0 for p in per_pair])
        err = np.array([p.std() / math.sqrt(p.size) if p.size > 1 else 0.0 for p in per_pair])
        means[name] = mean
        w = n / n.sum()
        result[name] = (math.degrees(math.sqrt((w * mean**2).sum())) * 1e3,
                        math.degrees(math.sqrt((w * err**2).sum())) * 1e3)
        result["edges"], result["pairs"] = int(n.sum()), int((n > 0).sum())
        result["weights"] = n
    # The pairs' mean shift with no intra-sequence timing, fitted by each model's prediction
    # plus two nuisance terms: a constant and the pair's elevation step (a sensor rolled
    # against the vertical structures slants their edges by a fixed angle).
    frac = {"manual": 1.0, "nebula": 1.0 - (1.0 / 12.0 if product == "VLP-32C" else 1.0 / 3.0)}
    n = result.pop("weights")
    y = means["none"]
    step = np.diff(elevations)
    sw = np.sqrt(n)
    for name in ("manual", "nebula"):
        predicted = omega * np.diff(t_model[name]) * 1e-9 * frac[name]
        x = np.stack([predicted, step, np.ones_like(step)], 1)
        coef = np.linalg.lstsq(x * sw[:, None], y * sw, rcond=None)[0]
        resid = y - x @ coef
        result[f"slope_{name}"] = float(coef[0])
        result[f"fit_{name}"] = math.degrees(math.sqrt((n * resid**2).sum() / n.sum())) * 1e3
    x = np.stack([omega * np.diff(t_model[m]) * 1e-9 * frac[m] for m in ("manual", "nebula")]
                 + [step, np.ones_like(step)], 1)
    coef = np.linalg.lstsq(x * sw[:, None], y * sw, rcond=None)[0]
    result["joint"] = (float(coef[0]), float(coef[1]))
    return result


def main() -> None:
    from converters.sources.velodyne import load_calibration

    for folder, (calib_name, cut) in RECORDINGS.items():
        root = DATA / folder
        r = measure(read_bag(root), load_calibration(root / calib_name), cut)
        print(f"{folder} ({r['model']}, {r['omega_deg_s'] / 6:.0f} rpm): {r['edges']} matched "
              f"edges on {r['pairs']} row pairs")
        for name in ("none", "manual", "nebula"):
            rms, floor = r[name]
            print(f"  {name:7s}: RMS of per-pair mean edge shift {rms:6.1f} mdeg "
                  f"(noise floor {floor:.1f} mdeg)")
        print(f"  untimed shifts fitted by each model's prediction (+ roll, constant): "
              f"manual slope {r['slope_manual']:.2f}, residual {r['fit_manual']:.1f} mdeg; "
              f"nebula slope {r['slope_nebula']:.2f}, residual {r['fit_nebula']:.1f} mdeg; "
              f"both together: manual {r['joint'][0]:.2f}, nebula {r['joint'][1]:.2f} "
              "(1 = the sensor's timing)")


if __name__ == "__main__":
    main()
