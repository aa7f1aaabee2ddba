"""The codec study compares like with like (converters.edge.evidence.codec_study).

A dual-return frame's channels (both returns) are divided by every cloud the driver publishes
for it (ouster-ros: ``points`` + ``points2``, two messages; the others: one cloud of every
return), its first-return channels by the first-return cloud; format version 3 is measured
beside version 2 and is never larger.
"""

from __future__ import annotations

import numpy as np

import lidarscan as ls
from converters.edge.evidence import codec_study


def test_second_return_view_and_first_return_scan() -> None:
    from converters.edge.evidence.compression import real_scans
    label, info, scan, _ = next(r for r in real_scans() if r[0].endswith("dual"))
    assert ("range", "range2") in codec_study.second_return_pairs(scan)
    view = codec_study.second_return_view(scan)
    np.testing.assert_array_equal(ls.channel(view, "range").view(np.uint32),
                                  ls.channel(scan, "range2").view(np.uint32))
    np.testing.assert_array_equal(ls.channel(view, "range2").view(np.uint32),
                                  ls.channel(scan, "range").view(np.uint32))
    first = codec_study.first_return_scan(scan, info)
    second = {b for _, b in codec_study.second_return_pairs(scan)}
    assert ls.scan.channel_names(first) == [n for n in ls.scan.channel_names(scan)
                                            if n not in second]
    for name in ls.scan.channel_names(first):
        assert ls.channel(first, name).tobytes() == ls.channel(scan, name).tobytes()
    np.testing.assert_array_equal(first.column_time_offsets, scan.column_time_offsets)
    single = next(r for r in real_scans() if not r[0].endswith("dual"))[2]
    assert codec_study.second_return_pairs(single) == []


def test_dual_frames_are_divided_by_every_return_the_driver_publishes() -> None:
    records = codec_study.measure(False)
    assert any(r.get("cloud_all") for r in records)
    for rec in records:
        dual = bool(rec.get("cloud_all"))
        assert dual == ("scan_first" in rec)
        name, best = codec_study.best_cloud(rec)
        first_name, first = codec_study.best_cloud(rec, "first")
        if not dual:
            assert (name, best) == (first_name, first)
            continue
        if rec["driver"] == "ouster-ros":  # points + points2: twice the first cloud's bytes
            assert rec["cloud_all"]["raw"] == 2 * rec["cloud"]["raw"]
            assert "points2" in codec_study.goal_lines([rec])[0]
        assert best == min(v for k, v in rec["cloud_all"].items() if "lossy" not in k)
        assert first == min(v for k, v in rec["cloud"].items() if "lossy" not in k)
        assert best > first  # the second return costs bytes in the driver's output too
        assert rec["scan_first"][codec_study.V2] < rec["scan"][codec_study.V2]
        assert "First-return channels alone" in codec_study.goal_lines([rec])[0]


def test_version_3_is_measured_and_never_larger() -> None:
    for rec in codec_study.measure(False):
        assert rec["scan"][codec_study.V3] <= rec["scan"][codec_study.V2]
        if rec["label"].startswith("OS-"):  # reflectivity predicted from signal and range
            assert rec["scan"][codec_study.V3] < 0.95 * rec["scan"][codec_study.V2]
