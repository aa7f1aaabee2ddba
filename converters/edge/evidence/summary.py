"""The headline numbers of the document, taken from the other modules' (cached) measurements.

Only deterministic figures appear here (sizes, errors, counts), so the block is checked by the
test like the tables it summarises. The ``*_facts`` functions pick the figures out of the
sections' records once; the headline and the decision record
(:mod:`converters.edge.evidence.decision`) both write their sentences from them.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

from converters.edge.evidence._common import Block, fmt_int, have

__all__ = ["blocks", "codec_facts", "image_facts", "key_facts", "range_facts",
           "vendor_facts", "versions"]


def _n(text: str) -> int:
    return int(text.replace(" ", ""))


def _sizes() -> list[str]:
    from converters.edge.evidence import sizes
    recs = sizes.measure()
    big = next(r for r in recs if r["layout"].family == "ouster" and r["layout"].height == 128
               and r["layout"].width == 2048 and not r["layout"].dual)
    ouster = [r["ouster-ros original"] / r["scan"] for r in recs if r["layout"].family == "ouster"]
    spin = [r["velodyne XYZIRT"] / r["scan"] for r in recs if r["layout"].family == "spinning"]
    xyzi = [r["x,y,z,intensity"] / r["scan"] for r in recs if r["layout"].family != "livox"]
    livox = next(r for r in recs if r["layout"].family == "livox")
    return [
        f"**Size (§1).** An Ouster 128×2048 frame is {fmt_int(big['scan'])} bytes as a LidarScan "
        f"with the five canonical channels, {fmt_int(big['ouster-ros original'])} as the "
        f"PointCloud2 ouster-ros publishes and {fmt_int(big['x,y,z,intensity'])} as a minimal "
        f"x,y,z,intensity cloud: {big['scan'] * 10 / 1e6:.1f} vs "
        f"{big['ouster-ros original'] * 10 / 1e6:.1f} MB/s at 10 Hz. Over all Ouster layouts the "
        f"driver's cloud is {min(ouster):.1f}–{max(ouster):.1f}× the LidarScan; over the "
        f"Velodyne/Hesai-style layouts velodyne_pointcloud's cloud is "
        f"{min(spin):.1f}–{max(spin):.1f}×; even x,y,z,intensity alone is "
        f"{min(xyzi):.2f}–{max(xyzi):.2f}× while carrying less. A non-grid Livox frame as a 1×N "
        f"LidarScan gains little (Livox's own 26 B/pt cloud is "
        f"{livox['livox'] / livox['scan']:.2f}× it, x,y,z,intensity "
        f"{livox['x,y,z,intensity'] / livox['scan']:.2f}×): such sensors may stay on "
        "PointCloud2.",
    ]


def _compression() -> list[str]:
    from converters.edge.evidence import compression
    out = []
    sizes = compression.measure(False)
    enc = compression.range_encodings()
    for label, recs in sizes.items():
        if "synthetic" in label:
            continue
        raw = recs["none"]["total"]
        twin = sizes.get(label + " — synthetic twin")
        lossless = {k: v for k, v in recs.items() if k not in ("none", "PNG")}
        best = min(lossless, key=lambda k: lossless[k]["total"])
        r32 = enc[label]["float32 m (canonical)"]["shuffle+zstd-3"]
        rmm = enc[label]["uint32 mm (Ouster native, multiplier 0.001)"]["shuffle+zstd-3"]
        twin_txt = (f"; a noise-free synthetic scan of the same sensor compresses "
                    f"{twin['none']['total'] / twin['zstd-3']['total']:.0f}× with zstd-3, which is "
                    "why only real frames are used" if twin else "")
        out.append(
            f"**Real {label} frame (§1, §3).** zstd-3 shrinks the channel blocks "
            f"{raw / recs['zstd-3']['total']:.2f}×, the best lossless codec ({best}) "
            f"{raw / lossless[best]['total']:.2f}×, lz4 {raw / recs['lz4']['total']:.2f}×"
            f"{twin_txt}. The range block as uint32 mm compresses to "
            f"{rmm / r32:.2f}× the size of float32 metres (shuffle+zstd-3).")
    return out


def range_facts() -> tuple[dict[str, Any], bool]:
    """float32 metres (§3): the worst round-trip record over the surveyed sensors' native units,
    and whether every native integer value is recovered exactly."""
    from converters.edge.evidence import range_error
    recs = [r for r in range_error.measure() if r["unit"] is not None]
    return max(recs, key=lambda r: r["max_err_um"]), all(r["exact"] for r in recs)


def _range() -> list[str]:
    worst, exact = range_facts()
    return [f"**float32 metres (§3).** Worst round-trip error over every native range value of "
            f"the surveyed sensors: {worst['max_err_um']:.1f} µm ({worst['label']}, up to "
            f"{worst['max']:g} m); every native integer value is recovered exactly: "
            f"{'yes' if exact else 'NO'}."]


def _geometry() -> list[str]:
    from converters.edge.evidence import geometry
    recs = geometry.measure()
    origin = [r for r in recs if r["label"].startswith("beam-origin")]
    azim = [r for r in recs if r["label"].startswith("per-beam azimuth (")]
    stag = [r for r in recs if "destagger" in r["label"]]
    parts = ", ".join(f"{r['sensor']} {r['max_mm']:.1f} mm" for r in origin)
    return [f"**Geometry (§4).** Dropping the beam-origin offset (as the 2026 draft does) costs up "
            f"to {parts}; dropping the per-beam azimuth up to "
            f"{max(r['max100_mm'] for r in azim) / 1000:.1f} m at 100 m; reading a staggered "
            f"image as destaggered shifts pixels by up to {max(r['max_col'] for r in stag):.0f} "
            "columns."]


def _linkage() -> list[str]:
    from converters.edge.evidence import linkage
    recs = linkage.run()
    total = sum(r["total"] for r in recs)
    wrong = sum(r["naive"]["wrong"] for r in recs)
    unusable = sum(r["naive"]["unusable"] for r in recs)
    rwrong = sum(r["wrong"] for r in recs)
    dropped = sum(r["dropped"] for r in recs)
    return [f"**Info link (§5).** Over {len(recs)} scenarios ({total} scans) a \"latest info "
            f"wins\" consumer projects {wrong} scans with the wrong geometry and cannot use "
            f"{unusable}; the resolver pairs {rwrong} wrongly and drops {dropped}, each with a "
            "reason."]


def _slicing() -> list[str]:
    ok, _ = have("converters.slices.converter", "SliceConverter")
    ok2, _ = have("converters.merger", "LaserScanMerger")
    out = []
    if ok:
        from converters.edge.evidence import slicing
        rows = slicing.slice_agreement()
        bins = sum(_n(r[2]) for r in rows)
        agree = sum(_n(r[3]) + _n(r[4]) for r in rows)
        out.append(f"**Slicing (§6).** {fmt_int(agree)} of {fmt_int(bins)} slice bins computed "
                   "from the LidarScan equal those computed per point from the PointCloud2 "
                   "within 0.1 mm.")
    if ok and ok2:
        from converters.edge.evidence import slicing
        rows, _ = slicing.merger_quality()
        proj, naive = rows[0], rows[1]
        out.append(f"**Merger (§6).** On the lidars' own grid the project's slice + merge "
                   f"reproduces {proj[4]} of {proj[3]} reference bins within 1 cm; the "
                   f"per-point pipeline deployed today {naive[4]}.")
    return out


# ------------------------------------------------------------------------------ facts

@lru_cache(maxsize=1)
def image_facts() -> dict[str, Any]:
    """One Image per channel vs one LidarScan (§2): sizes and the synchroniser simulation.

    Keys: size_min/size_max (images ÷ LidarScan bytes), lossless (all round trips exact),
    n (largest images per frame), p (1 %), and for that n and p: exact_lost, one_lost (frames
    lost by ExactTime / by one LidarScan per frame), mixed (sets mixing frames with the widest
    ApproximateTime slop), approx_whole (frames it delivers whole), frames.
    """
    from converters.edge.evidence import images
    sizes = images.measure_sizes()
    ratios = [r["images"] / r["scan"] for r in sizes]
    n = max(r["n"] for r in sizes)
    p = 0.01
    rows = [r for r in images.measure_sync() if r["n"] == n and r["p"] == p]
    exact = next(r for r in rows if r["policy"].startswith("ExactTime"))
    one = next(r for r in rows if r["policy"].startswith("one LidarScan"))
    wide = next(r for r in rows if f"slop {max(images.SLOPS_S):g} s" in r["policy"])
    return {"size_min": min(ratios), "size_max": max(ratios),
            "lossless": all(r["lossless"] for r in sizes), "n": n, "p": p,
            "frames": images.FRAMES, "exact_lost": exact["lost"], "one_lost": one["lost"],
            "mixed": wide["mixed"], "approx_whole": wide["whole"],
            "slop": max(images.SLOPS_S)}


@lru_cache(maxsize=1)
def key_facts() -> dict[str, Any]:
    """The version keys (§5): totals per key over the scenarios, and the bytes each adds.

    Keys: scenarios, total, wrong/dropped {key: count}, skew_dropped (scans the content hash
    drops when driver and receiver releases differ), skew_total, scan_adds/info_adds {key: B}.
    """
    from converters.edge.evidence import linkage
    recs = linkage.run_keys()
    skew = next(r for r in recs if r["name"] == "driver and receiver of different releases")
    sizes = {s["key"]: s for s in linkage.key_sizes()}
    return {"scenarios": len(recs), "total": sum(r["total"] for r in recs),
            "wrong": {k: sum(r["keys"][k]["wrong"] for r in recs) for k in linkage.KEYS},
            "dropped": {k: sum(r["keys"][k]["dropped"] for r in recs) for k in linkage.KEYS},
            "skew_dropped": skew["keys"]["content hash"]["dropped"], "skew_total": skew["total"],
            "scan_adds": {k: s["scan_adds"] for k, s in sizes.items()},
            "info_adds": {k: s["info_adds"] for k, s in sizes.items()}}


@lru_cache(maxsize=1)
def vendor_facts() -> dict[str, Any]:
    """The mapping to Ouster's draft (§7) and what the draft's omissions cost (§4, §5).

    Keys: angle_mm (float32 angle tables, mm at 100 m), rows, lost (first cells of the rows of
    the draft table whose mapping says the draft loses something), origin_mm (worst
    beam-origin error dropped by the draft), naive_wrong / naive_total (scans a receiver
    without the link misprojects, §5).
    """
    from converters.edge.evidence import geometry, linkage, vendor_mapping
    text = vendor_mapping.blocks()[0].text
    rows = [line.strip("| ").split(" | ") for line in text.splitlines()[2:]]
    origin = [r["max_mm"] for r in geometry.measure() if r["label"].startswith("beam-origin")]
    recs = linkage.run()
    return {"angle_mm": vendor_mapping.float32_angle_error(), "rows": len(rows),
            "lost": [r[0] for r in rows if "lost" in r[-1] or "loses" in r[-1]],
            "origin_mm": max(origin), "naive_wrong": sum(r["naive"]["wrong"] for r in recs),
            "naive_total": sum(r["total"] for r in recs)}


@lru_cache(maxsize=1)
def codec_facts() -> list[dict[str, Any]]:
    """Compressed vs compressed (§1), per real frame: the figures behind the goals.

    Keys per frame: label, codec (bytes, all channels), best_cloud / best_cloud_name (best
    lossless coding of every cloud the driver publishes: both returns of a dual frame),
    all_ratio / all_met (goal ≤ GOALS["all"]) of the codec's default, format version 3;
    codec_v2 / all_ratio_v2 (format version 2), zstd_ratio (zstd-3 of the scan ÷ zstd-3 of the
    cloud(s)), raw_ratio (raw cloud(s) ÷ raw scan data), range_ratio / range_met (lossless
    range ÷ Draco's lossy x,y,z; None without DracoPy), codec_vs_zstd (the default's bytes ÷
    zstd-3 of the scan).
    """
    from converters.edge.evidence import codec_study
    out = []
    for rec in codec_study.measure(False):
        best_name, best = codec_study.best_cloud(rec)  # every return the driver publishes
        clouds = rec.get("cloud_all") or rec["cloud"]
        ours, ours2 = rec["scan"][codec_study.V3], rec["scan"][codec_study.V2]
        draco = rec["cloud"].get("Draco 1 mm x,y,z (lossy)")
        rng = rec["range"][codec_study.V2] / draco if draco else None
        out.append({"label": rec["label"], "codec": ours, "best_cloud": best,
                    "best_cloud_name": best_name, "all_ratio": ours / best,
                    "all_met": ours / best <= codec_study.GOALS["all"],
                    "codec_v2": ours2, "all_ratio_v2": ours2 / best,
                    "zstd_ratio": rec["scan"]["zstd-3"] / clouds["zstd-3"],
                    "raw_ratio": clouds["raw"] / rec["scan"]["raw"],
                    "range_ratio": rng,
                    "range_met": None if rng is None else rng <= codec_study.GOALS["range"],
                    "codec_vs_zstd": ours / rec["scan"]["zstd-3"]})
    return out


def _new_sections() -> list[str]:
    img, key, ven = image_facts(), key_facts(), vendor_facts()
    return [
        f"**Images instead (§2).** One `sensor_msgs/Image` per channel is "
        f"{img['size_min']:.3f}–{img['size_max']:.3f}× the LidarScan's bytes and cannot carry "
        f"the per-column times or the info link; with {img['n']} image topics and "
        f"{img['p'] * 100:g} % message loss, ExactTime loses {fmt_int(img['exact_lost'])} of "
        f"{fmt_int(img['frames'])} frames (one LidarScan per frame: "
        f"{fmt_int(img['one_lost'])}) and ApproximateTime with a {img['slop']:g} s slop emits "
        f"{fmt_int(img['mixed'])} sets mixing frames.",
        f"**Version key (§5).** Over {key['scenarios']} scenarios ({key['total']} scans) the "
        f"stamp with the digest check pairs {key['wrong']['stamp + digest check']} scans "
        f"wrongly and drops {key['dropped']['stamp + digest check']} with a reason; unchecked it "
        f"pairs {key['wrong']['stamp, no digest check']} wrongly, a UUID "
        f"{key['wrong']['UUID']} (and adds {key['scan_adds']['UUID']} B to each scan and "
        f"{key['info_adds']['UUID']} B to the info); a content hash is never wrong but drops "
        f"{key['skew_dropped']} of {key['skew_total']} scans when driver and receiver releases "
        "hash different fields.",
        f"**Vendor mapping (§7).** Ouster's draft maps field by field except "
        f"{len(ven['lost'])} of the {ven['rows']} rows of the mapping table, which it loses "
        f"({', '.join(ven['lost'])}); its float32 angle tables cost "
        f"{ven['angle_mm']:.3f} mm at 100 m, its missing beam origins up to "
        f"{ven['origin_mm']:.1f} mm and its missing link {ven['naive_wrong']} of "
        f"{ven['naive_total']} scans misprojected (§5).",
    ]


def versions() -> str:
    """The codec libraries every compressed size depends on (§1 compression and codec study)."""
    from converters.edge.evidence import codec_study, compression
    parts = compression._versions().split(", ")
    return ", ".join(parts + [p for p in codec_study._versions().split(", ") if p not in parts])


def _codec() -> list[str]:
    from converters.edge.evidence.codec_study import GOALS
    out = []
    for f in codec_facts():
        rng = ("" if f["range_ratio"] is None else
               f"; its lossless range is {f['range_ratio']:.3f}× Draco's lossy 1 mm x,y,z "
               f"(goal ≤ {GOALS['range']}×: {'met' if f['range_met'] else 'not met'})")
        out.append(f"**Compressed vs compressed, {f['label']} (§1).** `lidarscan.codec` (format "
                   f"version 3, the default) codes all channels in {fmt_int(f['codec'])} B = "
                   f"{f['all_ratio']:.3f}× the best "
                   f"lossless coding of the driver's cloud(s) of every return "
                   f"({f['best_cloud_name']}; goal ≤ {GOALS['all']}×: "
                   f"{'met' if f['all_met'] else 'not met'}; format version 2: "
                   f"{f['all_ratio_v2']:.3f}×){rng}; under the "
                   f"same zstd-3 the LidarScan is {f['zstd_ratio']:.2f}× the cloud.")
    return out


def blocks() -> list[Block]:
    """The ``headline`` block and ``headline-compression`` (its numbers depend on the codec
    library versions, named in its first line, like the compression tables)."""
    lines: list[str] = []
    for part in (_sizes, _range, _geometry, _linkage, _slicing, _new_sections):
        lines += part()
    return [Block("headline", "\n".join(f"- {line}" for line in lines)),
            Block("headline-compression", f"Compression ({versions()}):\n\n"
                  + "\n".join(f"- {line}" for line in _compression() + _codec()))]
