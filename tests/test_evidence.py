"""The evidence document: its deterministic tables equal what the script computes, and the
measurements behind them agree with independent loop-based oracles.

The deterministic blocks (sizes, errors, counts) are computed once per session (about 10 s);
timings are never computed here.
"""

from __future__ import annotations

import math
import struct
import subprocess
import sys
from typing import Any

import numpy as np
import pytest

from converters.edge import evidence
from converters.edge.evidence import (
    _common,
    codec_study,
    compression,
    geometry,
    images,
    linkage,
    range_error,
    sizes,
    units,
)


@pytest.fixture(scope="module")
def blocks() -> list[Any]:
    return evidence.generate(fast=True)


def test_document_tables_equal_the_scripts_output(blocks: list[Any]) -> None:
    problems = evidence.check(evidence.DOC, blocks)
    real = [p for p in problems if not p.startswith("skipped:")]
    assert real == [], "docs/proposal.md is stale; run `make evidence`:\n" + "\n".join(real)


def test_every_generated_block_has_markers_and_no_placeholder_is_left(blocks: list[Any]) -> None:
    present = evidence.read_blocks(evidence.DOC.read_text(encoding="utf-8"))
    names = [b.name for b in blocks]
    assert len(names) == len(set(names))
    assert set(names) <= set(present)
    for timing in ("timing-compression", "timing-transport", "timing-receiver", "timing-slicing",
                   "timing-codec", "timing-images", "timing-int-vs-float", "machine"):
        assert timing in present, f"the document lost its {timing} block"
    assert [b.name for b in blocks if b.placeholder] == []
    assert "Not yet measured" not in "".join(present.values())


def test_check_cli_passes_on_the_committed_document(capsys: pytest.CaptureFixture[str]) -> None:
    assert evidence.main(["--check"]) == 0
    out = capsys.readouterr().out
    assert "CPU:" in out and "Python" in out and "document up to date" in out


def test_render_writes_only_between_markers() -> None:
    text = ("intro\n<!-- evidence:a:begin -->\nold\n<!-- evidence:a:end -->\nmiddle\n"
            "<!-- evidence:b:begin -->\n<!-- evidence:b:end -->\nend\n")
    out = evidence.render(text, [_common.Block("a", "new | table"), _common.Block("b", "x")])
    assert out == ("intro\n<!-- evidence:a:begin -->\nnew | table\n<!-- evidence:a:end -->\n"
                   "middle\n<!-- evidence:b:begin -->\nx\n<!-- evidence:b:end -->\nend\n")
    assert evidence.read_blocks(out) == {"a": "new | table", "b": "x"}
    assert evidence.render(out, [_common.Block("a", "new | table"), _common.Block("b", "x")]) \
        == out  # idempotent
    with pytest.raises(KeyError, match="no markers"):
        evidence.render(text, [_common.Block("missing", "x")])


def test_check_reports_a_changed_number(tmp_path: Any, blocks: list[Any]) -> None:
    doc = tmp_path / "proposal.md"
    text = evidence.DOC.read_text(encoding="utf-8")
    sizes_block = evidence.read_blocks(text)["sizes"]
    doc.write_text(text.replace(sizes_block, sizes_block.replace("2 638 020", "2 638 021")),
                   encoding="utf-8")
    assert any(p.startswith("sizes:") for p in evidence.check(doc, blocks))


def test_check_skips_library_dependent_blocks_when_versions_differ(tmp_path: Any,
                                                                    blocks: list[Any]) -> None:
    doc = tmp_path / "proposal.md"
    text = evidence.DOC.read_text(encoding="utf-8")
    old = evidence.read_blocks(text)["compression"]
    first = old.split("\n", 1)[0]
    doc.write_text(text.replace(old, old.replace(first, first.replace("zstandard ", "zstandard 0"))
                                .replace("| 3.47 |", "| 9.99 |")), encoding="utf-8")
    problems = evidence.check(doc, blocks)
    assert [p for p in problems if "compression" in p and p.startswith("skipped:")]
    assert not [p for p in problems if p.startswith("compression:")]


def test_core_evidence_import_does_not_import_rclpy() -> None:
    code = ("import sys, converters.edge.evidence as e; from converters.edge.evidence import sizes;"
            "sizes.scan_bytes(sizes.LAYOUTS[0]); print('rclpy' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=60, check=True)
    assert out.stdout.strip() == "False"


# ------------------------------------------------------------------------------ oracles

def _cdr_pointcloud2_size(frame_id: str, fields: list[tuple[str, int, int]], n: int,
                          step: int) -> int:
    """CDR size written out field by field (XCDR1, alignment from after the 4-byte header)."""
    pos = 0

    def align(k: int) -> None:
        nonlocal pos
        pos += -pos % k

    pos += 8                                     # stamp sec, nanosec
    pos += 4 + len(frame_id) + 1                 # frame_id
    align(4)
    pos += 8                                     # height, width
    pos += 4                                     # fields count
    for name, _, _ in fields:
        align(4)
        pos += 4 + len(name) + 1                 # name
        align(4)
        pos += 4 + 1                             # offset, datatype
        align(4)
        pos += 4                                 # count
    pos += 1                                     # is_bigendian
    align(4)
    pos += 8                                     # point_step, row_step
    pos += 4 + n * step                          # data
    pos += 1                                     # is_dense
    return 4 + pos


@pytest.mark.parametrize("layout", sorted(_common.PC2_LAYOUTS))
def test_pointcloud2_sizes_match_a_hand_written_cdr_size(layout: str) -> None:
    fields, step = _common.PC2_LAYOUTS[layout]
    for height, width in ((1, 1), (16, 1800), (128, 2048)):
        assert _common.pointcloud2_bytes(layout, height, width) == _cdr_pointcloud2_size(
            "os_sensor", fields, height * width, step)


def test_lidarscan_sizes_grow_by_exactly_the_channel_bytes() -> None:
    for layout in sizes.LAYOUTS[:4]:
        per_pixel = sum(np.dtype(t).itemsize for _, t in layout.channels)
        per_column = 8 * (2 if layout.azimuth_per_column else 1)
        wider = sizes.Layout(**{**layout.__dict__, "width": layout.width + 8})
        grown = sizes.scan_bytes(wider) - sizes.scan_bytes(layout)
        assert grown == 8 * (layout.height * per_pixel + per_column)


def test_float32_roundtrip_against_struct_loop() -> None:
    unit, top = 0.001, 300.0
    rec = range_error.roundtrip(unit, top)
    worst = 0.0
    for raw in range(0, int(top / unit) + 1, 997):      # every 997th value, plus the worst
        value = raw * unit
        back = struct.unpack("<f", struct.pack("<f", value))[0]
        worst = max(worst, abs(back - value))
        assert round(back / unit) == raw
    at = rec["at_m"]
    back = struct.unpack("<f", struct.pack("<f", at))[0]
    assert abs(back - at) * 1e6 == pytest.approx(rec["max_err_um"], rel=1e-9)
    assert worst * 1e6 <= rec["max_err_um"] + 1e-9
    assert rec["max_err_um"] <= 2.0 ** (8 - 24) * 1e6   # half a float32 step in [256, 512) m


def test_beam_origin_error_matches_the_ouster_formula_loop() -> None:
    """Dropping the beam origin = dropping Ouster's `off` term: |off| per pixel (rotation kept)."""
    import json
    meta = next(m for m, _ in _common.ouster_files() if "os1" in m.name)
    data = json.loads(meta.read_text())
    width = int(data["data_format"]["columns_per_frame"])
    n = float(data["lidar_origin_to_beam_origin_mm"])
    worst = 0.0
    for u, (alt, az) in enumerate(zip(data["beam_altitude_angles"],
                                      data["beam_azimuth_angles"])):
        phi = math.radians(alt)
        for v in range(0, width, 7):
            theta_e = 2 * math.pi - v * 2 * math.pi / width
            theta = theta_e - math.radians(az)
            dx, dy, dz = (math.cos(theta) * math.cos(phi), math.sin(theta) * math.cos(phi),
                          math.sin(phi))
            off = (n * math.cos(theta_e) - n * dx, n * math.sin(theta_e) - n * dy, -n * dz)
            worst = max(worst, math.sqrt(sum(c * c for c in off)))
    rec = next(r for r in geometry.measure()
               if r["sensor"].startswith("OS-1-128") and r["label"].startswith("beam-origin"))
    assert rec["max_mm"] == pytest.approx(worst, abs=0.01)


def test_resolver_never_pairs_wrong_geometry_while_naive_does() -> None:
    records = linkage.run()
    assert all(r["wrong"] == 0 for r in records)
    assert sum(r["naive"]["wrong"] for r in records) > 0
    for r in records:
        assert r["paired"] + r["dropped"] == r["total"], r["name"]


def test_lossless_codecs_roundtrip_every_real_block() -> None:
    assert compression.check_lossless() == []


def test_png_range_image_is_the_4mm_ouster_ros_encoding() -> None:
    r = np.array([[0.0, 1.0, 262.14, 262.2, np.inf, 0.0021]], np.float32)
    img = compression.png_image(r)
    assert img.dtype == np.uint16
    assert img.tolist() == [[0, 250, 65535, 0, 0, 1]]


# ------------------------------------------------------------- codec study, images, units

def test_check_reports_a_changed_goal_claim(tmp_path: Any, blocks: list[Any]) -> None:
    doc = tmp_path / "proposal.md"
    text = evidence.DOC.read_text(encoding="utf-8")
    goals = evidence.read_blocks(text)["codec-goals"]
    changed = goals.replace("**not met**", "met", 1) if "**not met**" in goals else \
        goals.replace(" met", " **not met**", 1)
    assert changed != goals
    doc.write_text(text.replace(goals, changed), encoding="utf-8")
    assert any(p.startswith("codec-goals:") for p in evidence.check(doc, blocks))


def test_codec_goals_follow_from_the_size_table() -> None:
    for rec in codec_study.measure(False):
        clouds = rec.get("cloud_all") or rec["cloud"]  # like for like: every return
        lossless = {k: v for k, v in clouds.items() if "lossy" not in k}
        line = next(x for x in codec_study.goal_lines([rec]))
        ratio = rec["scan"][codec_study.V3] / min(lossless.values())  # the default version
        assert f"{ratio:.3f}×" in line
        assert ("goal ≤ 0.2× met" in line) == (ratio <= 0.2)
        assert f"{rec['scan'][codec_study.V2] / min(lossless.values()):.3f}×" in line
        # the codec beats zstd of the raw buffer (what MCAP's chunk compression does)
        assert rec["scan"][codec_study.V2] < rec["scan"]["zstd-3"]
        assert rec["scan"][codec_study.V2] < rec["scan"]["zstd-19"]


def _feed(sync: Any, arrivals: list[tuple[int, int]]) -> None:
    for frame, topic in arrivals:
        sync.add(frame, frame * images.PERIOD_NS, topic)


def test_exact_time_emits_only_complete_equal_stamp_sets() -> None:
    got: list[tuple[int, ...]] = []
    sync = images.ExactTimeSync(3, 10, lambda *m: got.append(m))
    _feed(sync, [(0, 0), (0, 1), (0, 2), (1, 0), (1, 2), (2, 0), (2, 1), (2, 2)])
    assert got == [(0, 0, 0), (2, 2, 2)]          # frame 1 lost its topic-1 image
    for i in range(12):                           # queue_size bounds the leftovers
        sync.add(100 + i, (100 + i) * images.PERIOD_NS, 0)
    assert len(sync.queues[0]) == 10


def test_approximate_time_mixes_frames_when_slop_exceeds_the_period() -> None:
    arrivals = [(0, 0), (0, 1), (1, 1), (2, 0), (2, 1), (3, 0), (3, 1)]  # frame 1 topic 0 lost
    wide: list[tuple[int, ...]] = []
    _feed(images.ApproximateTimeSync(2, 10, int(0.15e9), lambda *m: wide.append(m)), arrivals)
    assert wide[0] == (0, 0) and (2, 1) in wide    # frame 2's topic 0 paired with frame 1
    narrow: list[tuple[int, ...]] = []
    _feed(images.ApproximateTimeSync(2, 10, int(0.05e9), lambda *m: narrow.append(m)), arrivals)
    assert narrow == [(0, 0), (2, 2), (3, 3)]


def test_sync_simulation_counts_are_consistent() -> None:
    for r in images.measure_sync():
        assert r["whole"] + r["lost"] == images.FRAMES
        assert r["lost"] >= r["frames_hit"] or "one LidarScan" in r["policy"]
        if "ExactTime" in r["policy"] or "slop 0.05" in r["policy"]:
            assert r["mixed"] == 0 and r["lost"] == r["frames_hit"]


def test_images_carry_exactly_the_channel_bytes() -> None:
    import lidarscan as ls
    from converters.images import to_images
    for _, info, scan in images._frames():
        imgs = to_images(scan, info, as_dataclass=True)
        assert sum(i.data.size for i in imgs.values()) == sum(
            ls.channel(scan, c.name).nbytes for c in scan.channels)
    assert all(rec["lossless"] for rec in images.measure_sizes())


def test_units_precision_against_a_struct_loop() -> None:
    import lidarscan as ls
    for label, info, scans, _ in units._scans():
        int_form = next(f for f in scans if f != units.FLOAT_FORM)
        mult = float(info.range_multiplier)
        mm = ls.channel(scans[int_form], "range").reshape(-1)
        worst = 0.0
        for raw in mm[mm > 0][::97].tolist():
            back = struct.unpack("<f", struct.pack("<f", raw * mult))[0]
            worst = max(worst, abs(back - raw * mult))
            assert round(back / mult) == raw
        rec = next(r for r in units.measure() if r["label"] == label and r["form"] == "float32 m")
        assert worst * 1e6 <= rec["err_um"] + 1e-9 and rec["exact"]


# --------------------------------------------- codec study: Velodyne / Hesai and the prose

NEBULA_SENSORS = ("Velodyne VLP-32C", "Velodyne VLS-128", "Hesai PandarXT32", "Hesai Pandar64",
                  "Hesai PandarQT64")


def test_codec_study_has_every_real_sensor_and_every_driver_layout() -> None:
    records = {r["label"]: r for r in codec_study.measure(False)}
    assert set(NEBULA_SENSORS) <= set(records)
    for label in NEBULA_SENSORS:
        rec = records[label]
        nebula = {k: v for k, v in (rec.get("cloud_all") or rec["cloud"]).items()
                  if k.startswith(codec_study.NEBULA_CLOUD)}  # every return: cloud_all if dual
        assert set(nebula) == {f"{codec_study.NEBULA_CLOUD} {c}"
                               for c in ("raw", "lz4", "zstd-3", "zstd-19")}
        assert not rec["organized"]
        assert rec["driver"] == ("velodyne_pointcloud XYZIRT" if label.startswith("Velodyne")
                                 else "HesaiLidar_ROS_2.0")
        # the baseline is the smallest lossless coding over both layouts
        best = codec_study.best_cloud(rec)[1]  # every return: both of a dual frame
        clouds = rec.get("cloud_all") or rec["cloud"]
        assert best == min(v for k, v in clouds.items() if "lossy" not in k)


def test_nebula_cloud_is_32_bytes_per_return_with_our_points() -> None:
    import lidarscan as ls
    from converters.edge.evidence import sensors
    rec = next(r for r in sensors.measure() if r["sensor"] == "Hesai PandarQT64")
    scan, info = rec["scan"], rec["info"]
    raw = codec_study.nebula_cloud(scan, info)
    returns = sum(int(np.isfinite(ls.range_m(scan, info, n)).sum()) for n in ("range", "range2"))
    assert len(raw) == 32 * returns
    pts = np.frombuffer(raw, np.dtype({"names": ["x", "y", "z", "rt", "ch", "dist"],
                                       "formats": ["<f4", "<f4", "<f4", "u1", "<u2", "<f4"],
                                       "offsets": [0, 4, 8, 13, 14, 24], "itemsize": 32}))
    first = pts[pts["rt"] == 1]
    xyz = ls.make_projector(info).project(scan, info)
    row = xyz[int(first["ch"][0])]
    c = int(np.nanargmin(np.abs(row[:, 0] - first["x"][0]) + np.abs(row[:, 1] - first["y"][0])))
    assert np.allclose(row[c], [first["x"][0], first["y"][0], first["z"][0]], atol=1e-6)
    assert set(np.unique(pts["rt"])) == {1, 2}


def test_the_compression_prose_matches_the_codec_facts() -> None:
    text = evidence.DOC.read_text(encoding="utf-8")
    facts = {f["label"]: f for f in summary_codec_facts()}
    off = [1 - f["codec_vs_zstd"] for f in facts.values()]
    assert (f"takes a further {round(min(off) * 100)}–{round(max(off) * 100)} % off zstd-3"
            in " ".join(text.split()))
    nebula = [facts[s]["all_ratio"] for s in NEBULA_SENSORS]
    assert f"all channels take {min(nebula):.2f}–{max(nebula):.2f}× the best lossless" in \
        " ".join(text.split())
    assert all(facts[s]["all_met"] for s in NEBULA_SENSORS)
    # the default (format version 3) meets it on OS-2-128, version 2 does not
    os2_facts = facts["OS-2-128 1024x10"]
    assert os2_facts["all_met"] and os2_facts["all_ratio"] <= 0.2 < os2_facts["all_ratio_v2"]
    assert f"OS-2-128 to {facts['OS-2-128 1024x10']['all_ratio']:.3f}×" in \
        " ".join(text.split())
    assert all(f["range_met"] for f in facts.values())
    assert "the range channel meets ≤ 0.4× Draco on every sensor" in " ".join(text.split())
    # the version 2 figures quoted in the format paragraph
    os2 = next(r for r in codec_study.measure(False) if r["label"] == "OS-2-128 1024x10")
    p64 = next(r for r in codec_study.measure(False) if r["label"] == "Hesai Pandar64")
    flat = " ".join(text.split())
    assert f"to {fmt(os2['scan'][codec_study.V2])} B and the range from 162 340 to " \
           f"{fmt(os2['range'][codec_study.V2])} B" in flat
    assert f"from 200 697 to {fmt(p64['scan'][codec_study.V2])} B" in flat


def test_units_cover_every_real_sensor_and_recover_every_integer() -> None:
    records = units.measure()
    labels = {r["label"] for r in records}
    assert set(NEBULA_SENSORS) <= labels
    for label in NEBULA_SENSORS:
        forms = {r["form"]: r for r in records if r["label"] == label}
        assert set(forms) == {"float32 m", "uint16 native units (range_multiplier 0.004)"}
        assert all(r["exact"] for r in forms.values())
        assert forms["float32 m"]["raw"] == 2 * forms[
            "uint16 native units (range_multiplier 0.004)"]["raw"]


def summary_codec_facts() -> list[dict[str, Any]]:
    from converters.edge.evidence import summary
    return summary.codec_facts()


def fmt(n: int) -> str:
    from converters.edge.evidence._common import fmt_int
    return fmt_int(n)
