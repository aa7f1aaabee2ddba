"""The decision record and the summary of docs/proposal.md.

The blocks regenerate equal to the document; the check mode fails when a number, a verdict or a
quoted .msg line in them is edited; the statements they make follow from the sections' records
(goals met or not, field counts of the .msg files, CDR sizes written out by hand).

The measurements are the sections' cached records (``lru_cache``), shared with
``tests/test_evidence.py`` in the same session: nothing slow is run twice.
"""

from __future__ import annotations

import re
from typing import Any

import pytest

from converters.edge import evidence
from converters.edge.evidence import codec_study, decision, summary

NAMES = ("decision-msgs", "decision-answers", "decision-compression", "decision-rejected")


@pytest.fixture(scope="module")
def blocks() -> list[Any]:
    # as make evidence builds them: clouds by the numpy reference, whatever is compiled (run
    # alone, outside that context, the C cloud kernel's few-ulp xyz change the zstd-19 sizes)
    with evidence.reference_backends():
        return decision.blocks() + summary.blocks()


def test_the_record_regenerates_equal_to_the_document(blocks: list[Any]) -> None:
    assert tuple(b.name for b in blocks[:4]) == NAMES
    assert all(b.deterministic and not b.placeholder for b in blocks)
    problems = evidence.check(evidence.DOC, blocks)
    assert [p for p in problems if not p.startswith("skipped:")] == [], problems
    # the record is the document's last section before the limits, and registered as a section
    text = evidence.DOC.read_text(encoding="utf-8")
    heads = re.findall(r"^## (.+)$", text, re.MULTILINE)
    assert heads[-2:] == ["Decision record", "Limits of this evidence"]
    assert text.index("evidence:decision-msgs:begin") > text.index("## Decision record")
    assert set(NAMES) <= set(evidence._SECTION_BLOCKS["decision"])


@pytest.mark.parametrize("block,old,new", [
    ("decision-msgs", "float32 range_max", "float64 range_max"),
    ("decision-answers", "15.1 µm", "15.2 µm"),
    ("decision-answers", "151 of 2 000 frames", "150 of 2 000 frames"),
    ("decision-answers", "pairs 0 of 172 scans wrongly", "pairs 1 of 172 scans wrongly"),
    ("decision-answers", "Precision is not the reason", "Precision is the reason"),
    ("decision-compression", "goal ≤ 0.2×: met", "goal ≤ 0.2×: **not met**"),
    ("decision-compression", "Every size goal is met.", "Every size goal is missed."),
    ("decision-rejected", "14 of 172 scans paired wrongly", "13 of 172 scans paired wrongly"),
    ("headline", "1 801 sets mixing frames", "1 800 sets mixing frames"),
    ("headline-compression", "0.215×", "0.199×"),
])
def test_check_fails_when_the_record_is_edited(tmp_path: Any, blocks: list[Any], block: str,
                                               old: str, new: str) -> None:
    text = evidence.DOC.read_text(encoding="utf-8")
    have = evidence.read_blocks(text)[block]
    assert old in have, f"{block} no longer contains {old!r}"
    doc = tmp_path / "proposal.md"
    doc.write_text(text.replace(have, have.replace(old, new, 1)), encoding="utf-8")
    assert any(p.startswith(f"{block}:") for p in evidence.check(doc, blocks))


def test_the_msgs_block_quotes_every_field_of_the_msg_files() -> None:
    code = decision.compact_msgs().strip("`\n")
    quoted: dict[str, list[str]] = {}
    for line in code.splitlines():
        if line.startswith("# "):
            current = quoted.setdefault(line[2:], [])
            continue
        current += line.rstrip(";").split("; ")
    for name in ("LidarScan", "LidarChannel", "LidarInfo"):
        lines = (decision.MSG_DIR / f"{name}.msg").read_text(encoding="utf-8").splitlines()
        fields = [" ".join(x.split("#")[0].split()) for x in lines]
        fields = [f for f in fields if f and "=" not in f]
        assert [q for q in quoted[name] if "=" not in q] == fields, name
    assert quoted["LidarChannel"][0].count("=") == 8      # the eight datatype constants


def test_cpp_facts_count_the_msg_fields() -> None:
    facts = decision.cpp_facts()
    text = "\n".join((decision.MSG_DIR / f"{n}.msg").read_text(encoding="utf-8")
                     for n in ("LidarScan", "LidarChannel", "LidarInfo"))
    field = re.compile(r"^([A-Za-z_][\w/]*)(\[\d*\])? [a-z_]\w*\s*(#.*)?$")
    types = [m.group(1) for m in map(field.match, text.splitlines()) if m]
    assert facts["fields"] == len(types)
    assert facts["primitive"] + sum(facts["other"].values()) == facts["fields"]
    assert facts["unknown"] == []
    assert facts["other"] == {t: types.count(t) for t in set(types) if "/" in t or t[0].isupper()}


def test_per_pixel_tables_cost_two_float64_per_pixel() -> None:
    """Two float64[] sequences of H*W values: 16 B per pixel, plus at most 4 B of alignment
    each (CDR aligns float64 data to 8 after the 4-byte length)."""
    h, w, nbytes = decision._per_pixel_bytes()
    assert 16 * h * w <= nbytes <= 16 * h * w + 8


def test_goal_verdicts_follow_from_the_codec_study() -> None:
    facts = summary.codec_facts()
    records = codec_study.measure(False)
    assert [f["label"] for f in facts] == [r["label"] for r in records]
    for f, rec in zip(facts, records):
        best = codec_study.best_cloud(rec)[1]  # every return the driver publishes
        assert f["all_met"] == (rec["scan"][codec_study.V3] <= 0.2 * best)  # the default
        draco = rec["cloud"].get("Draco 1 mm x,y,z (lossy)")
        if draco:
            assert f["range_met"] == (rec["range"][codec_study.V2] <= 0.4 * draco)
        # the like-for-like comparisons the recommendation rests on
        assert rec["scan"]["zstd-3"] < rec["cloud"]["zstd-3"]
        assert rec["scan"]["raw"] < rec["cloud"]["raw"]
    text = "\n".join(decision._compression())
    missed = any(not f["all_met"] or f["range_met"] is False for f in facts)
    assert ("**Goals not met:**" in text) == missed
    assert ("Every size goal is met." in text) == (not missed)


def test_image_and_key_facts_match_the_section_tables() -> None:
    text = evidence.DOC.read_text(encoding="utf-8")
    blocks = evidence.read_blocks(text)
    img, key = summary.image_facts(), summary.key_facts()
    row = (f"| {img['n']} | {img['p'] * 100:g} % | ExactTime (queue 10) | ")
    assert row in blocks["images-sync"]
    line = next(x for x in blocks["images-sync"].splitlines() if x.startswith(row))
    assert line.split(" | ")[5].replace(" ", "") == str(img["exact_lost"])
    total = next(x for x in blocks["linkage-keys"].splitlines() if x.startswith("| **all**"))
    cells = total.strip("| ").split(" | ")[3:]
    for k, cell in zip(("stamp, no digest check", "stamp + digest check", "UUID",
                        "content hash"), cells):
        _, wrong, dropped = (c.strip("*") for c in cell.split(" / "))
        assert (int(wrong), int(dropped)) == (key["wrong"][k], key["dropped"][k]), k
    assert total.strip("| ").split(" | ")[2] == str(key["total"])
