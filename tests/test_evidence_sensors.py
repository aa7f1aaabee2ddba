"""Section 4b of docs/proposal.md (real sensors, converters/edge/evidence/sensors.py).

Oracles: brute-force nearest distances, the Ouster vendor formula of tests/test_ouster.py, the
PointCloud2 size of ``_common.pointcloud2_bytes`` for a layout it knows, and the check mode
failing when a number of the section's tables or of its sentence of claims changes. Every
recording is decoded once per session (``sensors.measure`` is cached and shared with
tests/test_evidence.py).
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np
import pytest

from converters.edge import evidence
from converters.edge.evidence import _common, sensors

NAMES = ("sensors-error", "sensors-claims", "sensors-fields", "sensors-size")


@pytest.fixture(scope="module")
def blocks() -> list[Any]:
    return sensors.blocks()


def _by_sensor() -> dict[str, list[dict[str, Any]]]:
    out: dict[str, list[dict[str, Any]]] = {}
    for r in sensors.measure():
        out.setdefault(r["sensor"], []).append(r)
    return out


def test_the_document_holds_what_the_script_writes(blocks: list[Any]) -> None:
    assert [b.name for b in blocks] == list(NAMES)
    assert not any(b.placeholder for b in blocks)
    problems = [p for p in evidence.check(evidence.DOC, blocks) if not p.startswith("skipped:")]
    assert problems == [], "docs/proposal.md is stale; run `make evidence`:\n" + "\n".join(problems)
    text = evidence.DOC.read_text(encoding="utf-8")
    assert text.index("## 4. What omitting") < text.index("## 4b. Real sensors") \
        < text.index("## 5. The info link")


@pytest.mark.parametrize("name", ["sensors-error", "sensors-claims", "sensors-size"])
def test_check_fails_when_a_number_is_edited(name: str, tmp_path: Any, blocks: list[Any]
                                            ) -> None:
    text = evidence.DOC.read_text(encoding="utf-8")
    block = evidence.read_blocks(text)[name]
    first = next(ch for ch in block if ch.isdigit())
    edited = block.replace(first, str((int(first) + 1) % 10), 1)
    assert edited != block
    doc = tmp_path / "proposal.md"
    doc.write_text(text.replace(block, edited), encoding="utf-8")
    assert [p for p in evidence.check(doc, blocks) if p.startswith(name + ":")]
    doc.write_text(text, encoding="utf-8")
    assert not [p for p in evidence.check(doc, blocks) if p.startswith("sensors")]


def test_every_model_is_measured() -> None:
    got = _by_sensor()
    for model in ("Velodyne VLP-32C", "Velodyne VLS-128", "Hesai PandarXT32", "Hesai Pandar64",
                  "Hesai PandarQT64"):
        assert model in got
    assert sum(name.startswith("Ouster") for name in got) == 2      # the two real frames
    assert [len(got[m]) for m in got if m.startswith("Velodyne")] == [2, 2]


def test_the_readings_the_text_makes() -> None:
    for name, records in _by_sensor().items():
        if name.startswith("Ouster"):
            (r,) = records
            assert r["t_max"] < 5e-5 and r["t_within"] == 1.0        # float32 rounding
        elif name.startswith("Hesai"):
            (r,) = records
            assert r["t_within"] == 1.0 and r["t_max"] < 2e-5
            assert r["o_within"] > 0.98
            assert 1.5 * r["n_truth"] < r["n_ours"]                  # both returns kept
        else:
            default, manual = records
            assert default["variant"].startswith("default")
            assert default["t_within"] > 0.99 and default["o_within"] > 0.99
            assert manual["t_within"] < 0.5 and manual["o_within"] < 0.5
            assert 2e-3 < manual["t_median"] < 0.05                  # mm to cm, not metres


def test_nearest_equals_brute_force() -> None:
    rng = np.random.default_rng(3)
    ref = rng.uniform(-30, 30, (1500, 3))
    query = np.concatenate([ref[:300] + rng.normal(0, 1e-3, (300, 3)),
                            rng.uniform(-40, 40, (700, 3)), [[500.0, 0.0, 0.0]]])
    brute = np.sqrt(((query[:, None] - ref[None]) ** 2).sum(-1)).min(1)
    np.testing.assert_allclose(sensors.nearest(query, ref), brute, rtol=0, atol=1e-12)
    bounded = sensors.nearest(query, ref, within=0.5)
    assert np.array_equal(np.isfinite(bounded), brute <= 0.5)
    np.testing.assert_allclose(bounded[brute <= 0.5], brute[brute <= 0.5], rtol=0, atol=1e-12)


def test_ouster_reference_is_the_vendor_formula_of_the_ouster_tests() -> None:
    from test_ouster import DATA, FRAMES, _frame, _vendor_xyz
    for name in FRAMES:
        meta = json.loads((DATA / f"{name}.json").read_text())
        rng = _frame(name)["range_mm"]
        np.testing.assert_allclose(sensors._vendor_xyz(meta, rng)[rng > 0],
                                   _vendor_xyz(meta, rng)[rng > 0], rtol=0, atol=1e-9)


def test_cloud_sizes() -> None:
    hesai_fields, hesai_step = _common.PC2_LAYOUTS["hesai"]
    for n in (0, 1, 12345):
        assert sensors._cloud_bytes(hesai_fields, hesai_step, n) == \
            _common.pointcloud2_bytes("hesai", 1, n, frame_id="lidar")
    sizes = {1: 1, 2: 1, 4: 2, 6: 4, 7: 4}
    end = 0
    for _, offset, datatype in sensors.NEBULA_FIELDS:            # packed, in order
        assert offset == end
        end += sizes[datatype]
    assert end == sensors.NEBULA_STEP == 32


def test_info_fields_per_vendor() -> None:
    for name, records in _by_sensor().items():
        fields = set(sensors.info_fields(records[0]["info"]))
        assert {"vertical_angles", "beam_azimuth_offsets", "range_multiplier"} <= fields
        assert not fields & {"pixel_azimuth_angles", "pixel_altitude_angles"}
        if name.startswith("Ouster"):
            assert {"beam_origins", "lidar_to_sensor_transform", "pixel_shift_by_row"} <= fields
        else:
            assert "beam_time_offsets" in fields and "beam_origins" not in fields
