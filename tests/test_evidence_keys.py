"""The version-key comparison and the vendor mapping of docs/proposal.md (§5, §7).

Oracles: counts derived by hand from each scenario's definition, CDR sizes written out by hand,
the statements the document's prose makes about the table, and the check mode failing when a
number or a generated sentence in the document changes.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from converters.edge import evidence
from converters.edge.evidence import linkage, vendor_mapping


@pytest.fixture(scope="module")
def records() -> dict[str, dict[str, Any]]:
    return {r["name"]: r for r in linkage.run_keys()}


def _counts(rec: dict[str, Any], key: str) -> tuple[int, int, int]:
    c = rec["keys"][key]
    return c["right"], c["wrong"], c["dropped"]


def test_every_scan_is_counted_once_per_key(records: dict[str, dict[str, Any]]) -> None:
    assert set(records) == set(linkage.KEY_SCENARIOS)
    for name, rec in records.items():
        events = linkage.KEY_SCENARIOS[name][2]
        assert rec["total"] == sum(e[2] for e in events if e[0] == "scan")
        for key in linkage.KEYS:
            assert sum(_counts(rec, key)) == rec["total"], (name, key)


# Expected (right, wrong, dropped) per key, derived by hand from the scenario definitions:
# stamp-no-check = dict by stamp (replace), digest = lidarscan.linkage (ambiguous stamp -> drop),
# UUID = dict by UUID, hash = dict by content digest.
HAND = {
    "changed republish, same key": {
        # 5 A, then info B under A's stamp/UUID, then 2 A in flight and 5 B
        "stamp, no digest check": (10, 2, 0), "stamp + digest check": (5, 0, 7),
        "UUID": (10, 2, 0), "content hash": (12, 0, 0)},
    "recording cut in two": {
        "stamp, no digest check": (0, 0, 10), "stamp + digest check": (0, 0, 10),
        "UUID": (0, 0, 10), "content hash": (10, 0, 0)},
    "two drivers, one topic, sim time": {
        # info B replaces A under the shared stamp before any scan: every A scan gets B
        "stamp, no digest check": (10, 10, 0), "stamp + digest check": (0, 0, 20),
        "UUID": (20, 0, 0), "content hash": (20, 0, 0)},
    "driver restart reusing a stamp": {
        "stamp, no digest check": (18, 2, 0), "stamp + digest check": (8, 0, 12),
        "UUID": (20, 0, 0), "content hash": (20, 0, 0)},
    "driver and receiver of different releases": {
        "stamp, no digest check": (10, 0, 0), "stamp + digest check": (10, 0, 0),
        "UUID": (10, 0, 0), "content hash": (0, 0, 10)},
    "late joiner": {k: (10, 0, 0) for k in linkage.KEYS},
    "clock steps back, then a change": {k: (20, 0, 0) for k in linkage.KEYS},
}


@pytest.mark.parametrize("name", sorted(HAND))
def test_counts_match_the_hand_derivation(records: dict[str, dict[str, Any]], name: str) -> None:
    for key, expected in HAND[name].items():
        assert _counts(records[name], key) == expected, key


def _stamp_reused_for_other_geometry(name: str) -> bool:
    versions = linkage.KEY_SCENARIOS[name][1].values()
    by_stamp: dict[int, set[str]] = {}
    for v in versions:
        by_stamp.setdefault(v.stamp_ns, set()).add(v.geometry)
    return any(len(g) > 1 for g in by_stamp.values())


def test_the_documents_statements_about_the_keys(records: dict[str, dict[str, Any]]) -> None:
    """What §5's prose says, checked against the table."""
    reuse = {n for n in records if _stamp_reused_for_other_geometry(n)}
    assert reuse  # the table has such scenarios
    recreated = {"recording cut in two"}
    for name, rec in records.items():
        # the checked stamp is never wrong; it drops only on reuse or a re-created info
        assert rec["keys"]["stamp + digest check"]["wrong"] == 0
        if rec["keys"]["stamp + digest check"]["dropped"]:
            assert name in reuse | recreated, name
        # without the check, exactly the reuse cases with scans of both geometries misproject
        if rec["keys"]["stamp, no digest check"]["wrong"]:
            assert name in reuse, name
        # the UUID is wrong only when a driver keeps its UUID across a change
        if rec["keys"]["UUID"]["wrong"]:
            versions = list(linkage.KEY_SCENARIOS[name][1].values())
            assert len({v.uuid for v in versions}) < len({v.geometry for v in versions})
        # the content hash is never wrong and drops only when the releases disagree
        assert rec["keys"]["content hash"]["wrong"] == 0
        if rec["keys"]["content hash"]["dropped"]:
            assert name == "driver and receiver of different releases"
    # the UUID fixes nothing the checked stamp leaves wrong (it leaves nothing wrong)...
    total = {k: sum(r["keys"][k]["wrong"] for r in records.values()) for k in linkage.KEYS}
    assert total["stamp + digest check"] == 0 and total["UUID"] > 0
    assert total["stamp, no digest check"] > total["UUID"]
    # ... and the content hash drops fewer scans than the checked stamp in this table
    drops = {k: sum(r["keys"][k]["dropped"] for r in records.values()) for k in linkage.KEYS}
    assert drops["content hash"] < drops["stamp + digest check"]
    # identical republish, late join, clock steps and an unchanged sim reset: all keys right
    for name in ("identical republish", "late joiner", "clock steps back, then a change",
                 "sim restart, same sensor", "two drivers, one topic"):
        for key in linkage.KEYS:
            assert records[name]["keys"][key]["right"] == records[name]["total"], (name, key)


def test_key_sizes_match_hand_written_cdr() -> None:
    """Time = int32 + uint32 (8 bytes, 4-aligned); uint8[16] = 16 bytes and the next field
    (uint32 height) stays 4-aligned, so no padding appears or disappears."""
    sizes = {s["key"]: s for s in linkage.key_sizes()}
    assert (sizes["stamp"]["scan_adds"], sizes["stamp"]["info_adds"]) == (8, 0)
    assert (sizes["UUID"]["scan_adds"], sizes["UUID"]["info_adds"]) == (16, 16)
    assert (sizes["content hash"]["scan_adds"], sizes["content hash"]["info_adds"]) == (16, 0)
    import lidarscan as ls
    info = linkage.geometries()["A"]
    scan = ls.make_scan(info, {"range": np.zeros((128, 1024), np.float32)}, 5,
                        as_dataclass=True)
    assert sizes["stamp"]["scan_bytes"] == len(ls.encode(scan))


def test_keyed_resolver_holds_replaces_and_flushes() -> None:
    class Msg:
        def __init__(self, key: int, stamp: int = 0) -> None:
            from lidarscan.types import Time
            self.key, self.header = key, type("H", (), {"stamp": Time(0, stamp)})()
            self.lidar_info_time = Time(0, key)

    r = linkage.KeyedResolver(lambda i: i.key, lambda s: s.key, max_infos=2, max_pending=2)
    held = [Msg(1, 10), Msg(1, 11), Msg(1, 12)]
    for s in held:
        assert r.add_scan(s) == []
    assert [d.reason for d in r.take_dropped()] == \
        ["pending buffer full before its LidarInfo came"]        # the oldest of 3 held
    info1, info1b = Msg(1), Msg(1)
    assert [p[0] for p in r.add_info(info1)] == held[1:]          # released in arrival order
    r.add_info(info1b)                                            # same key: replaces
    assert r.add_scan(held[0])[0][1] is info1b
    r.add_info(Msg(2))
    r.add_info(Msg(3))                                            # max_infos 2: key 1 forgotten
    r.add_scan(Msg(1, 13))
    r.flush()
    assert [d.reason for d in r.take_dropped()] == ["its LidarInfo never arrived"]
    assert r.take_dropped() == []


def test_float32_angles_cost_micrometres() -> None:
    """Rounding the angle tables to float32 moves a 100 m point by about 2π·2^-24 rad·100 m
    (half a float32 step at 2π, plus the beam tables): tens of µm, never a millimetre."""
    err = vendor_mapping.float32_angle_error()
    assert 0.005 < err < 0.1
    half_ulp_2pi = np.spacing(np.float32(2 * np.pi)) / 2
    assert err >= half_ulp_2pi * 100e3 * 0.5


def test_point_type_sizes() -> None:
    assert vendor_mapping.point_bytes("ouster-ros `original`") == (30, 48)
    assert vendor_mapping.point_bytes("velodyne XYZIRT") == (22, 22)
    assert vendor_mapping.point_bytes("Nebula PointXYZIRCAEDT") == (32, None)
    from converters.edge.evidence._common import PC2_LAYOUTS
    # the same published steps as the layouts §1 sizes with
    assert PC2_LAYOUTS["ouster-ros original"][1] == 48
    assert PC2_LAYOUTS["velodyne XYZIRT"][1] == 22


@pytest.mark.parametrize("block,old,new", [
    ("linkage-keys", "113 / 0 / 59", "114 / 0 / 58"),
    ("linkage-keys-reading", "never pairs a scan", "rarely pairs a scan"),
    ("linkage-key-sizes", "| 16 | `uint8[16] uuid` | 16 |", "| 16 | `uint8[16] uuid` | 17 |"),
    ("vendor-draft", "0.024 mm at 100 m", "0.001 mm at 100 m"),
    ("vendor-clouds", "48 B/point", "40 B/point"),
])
def test_check_fails_when_a_claim_no_longer_matches(tmp_path: Any, block: str, old: str,
                                                    new: str) -> None:
    text = evidence.DOC.read_text(encoding="utf-8")
    have = evidence.read_blocks(text)[block]
    assert old in have, f"{block} no longer contains {old!r}"
    doc = tmp_path / "proposal.md"
    doc.write_text(text.replace(have, have.replace(old, new)), encoding="utf-8")
    blocks = linkage.blocks()
    assert any(p.startswith(f"{block}:") for p in evidence.check(doc, blocks))
    assert not [p for p in evidence.check(evidence.DOC, blocks) if not p.startswith("skipped")]
