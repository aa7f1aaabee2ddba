"""Damaged MCAP files: every good message is read byte-identical, every damaged part reported.

The recordings are written with many small chunks and strictly increasing log times; which
messages a chunk holds is taken from the ``mcap`` package's own reading of the intact file
(its chunk index), then the file is damaged: a byte flipped inside a chunk (CRC mismatch), a
zstd stream made undecompressable, the file cut inside a chunk or after the data section
(summary missing), the summary damaged, a chunk's record length damaged (resync on the next
chunk, from the summary or by scanning), an attachment's bytes altered, a byte outside the
chunks altered (data-section CRC). ``lidarscan convert`` on each: exit 1, the damage listed,
every good message copied.
"""

from __future__ import annotations

import io
import struct
from pathlib import Path
from typing import Any

import pytest

from lidarscan.errors import LidarScanError
from lidarscan.mcap import BadMessage, McapMessage, McapWriter, read_messages

TOPICS = ("/a", "/b")
N = 60


def _recording(compression: str = "zstd", **kw: Any) -> bytes:
    """N String-like messages (std_msgs/String CDR) on two topics, ~6 per chunk."""
    buf = io.BytesIO()
    with McapWriter(buf, compression=compression, chunk_size=600, **kw) as writer:
        for k in range(N):
            text = f"message {k:03d} ".encode() * 8
            payload = b"\x00\x01\x00\x00" + struct.pack("<I", len(text) + 1) + text + b"\x00"
            writer.write(TOPICS[k % 2], payload, msgtype="std_msgs/msg/String",
                         log_time_ns=1_000_000_000 + k * 1000)
    return buf.getvalue()


def _truth(data: bytes) -> tuple[list[tuple[str, int, bytes]], list[Any]]:
    """(topic, log time, payload) of every message and the chunk indexes, by the mcap package."""
    from mcap.reader import make_reader

    reader = make_reader(io.BytesIO(data))
    messages = [(ch.topic, m.log_time, bytes(m.data)) for _, ch, m in reader.iter_messages()]
    summary = reader.get_summary()
    assert summary is not None
    chunks = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    return messages, chunks


def _read(data: bytes | Path) -> tuple[list[McapMessage], list[BadMessage]]:
    good, bad = [], []
    for item in read_messages(data):
        (good if isinstance(item, McapMessage) else bad).append(item)
    for item in bad:
        assert isinstance(item.error, LidarScanError)
        assert item.reason.strip()
    return good, bad


def _key(m: McapMessage) -> tuple[str, int, bytes]:
    return m.topic, m.log_time_ns, m.payload


def _in_chunk(messages: list[tuple[str, int, bytes]], chunk: Any) -> list[tuple[str, int, bytes]]:
    return [m for m in messages if chunk.message_start_time <= m[1] <= chunk.message_end_time]


def _flip(data: bytes, offset: int) -> bytes:
    return data[:offset] + bytes([data[offset] ^ 0x5A]) + data[offset + 1:]


def test_intact_file_reads_like_the_mcap_package() -> None:
    data = _recording()
    truth, chunks = _truth(data)
    good, bad = _read(data)
    assert not bad and len(chunks) > 5
    assert [_key(m) for m in good] == truth
    assert [m.index for m in good] == list(range(N))


@pytest.mark.parametrize("compression", ["none", "zstd", "lz4"])
def test_byte_flipped_inside_a_chunk_is_reported_and_the_rest_read(compression: str) -> None:
    data = _recording(compression)
    truth, chunks = _truth(data)
    victim = chunks[3]
    # a byte in the middle of the chunk's (compressed) records
    damaged = _flip(data, victim.chunk_start_offset + victim.chunk_length - 20)
    good, bad = _read(damaged)
    lost = _in_chunk(truth, victim)
    assert [_key(m) for m in good] == [m for m in truth if m not in lost]
    (report,) = bad
    assert report.offset == victim.chunk_start_offset
    assert f"offset {victim.chunk_start_offset}" in report.reason
    assert (report.log_time_ns, report.end_time_ns) == (victim.message_start_time,
                                                        victim.message_end_time)
    assert f"{len(lost)} message(s)" in report.reason  # counted from the message indexes
    # indices after the damaged chunk still count the lost messages
    assert [m.index for m in good] == [i for i, m in enumerate(truth) if m not in lost]


def test_undecompressable_zstd_chunk() -> None:
    data = _recording("zstd")
    truth, chunks = _truth(data)
    victim = chunks[2]
    raw = bytearray(data)
    frame = raw.index(b"\x28\xb5\x2f\xfd", victim.chunk_start_offset)  # zstd frame magic
    raw[frame:frame + 4] = b"XXXX"
    good, bad = _read(bytes(raw))
    assert [_key(m) for m in good] == [m for m in truth if m not in _in_chunk(truth, victim)]
    (report,) = bad
    assert "zstd" in report.reason and report.offset == victim.chunk_start_offset


def test_first_chunk_damaged_channels_come_from_the_summary() -> None:
    data = _recording("none")
    truth, chunks = _truth(data)
    victim = chunks[0]  # holds the schema and both channel records
    damaged = _flip(data, victim.chunk_start_offset + victim.chunk_length - 20)
    good, bad = _read(damaged)
    assert [_key(m) for m in good] == [m for m in truth if m not in _in_chunk(truth, victim)]
    assert len(bad) == 1


def test_truncated_inside_a_chunk() -> None:
    data = _recording()
    truth, chunks = _truth(data)
    victim = chunks[4]
    cut = data[:victim.chunk_start_offset + victim.chunk_length // 2]
    good, bad = _read(cut)
    before = [m for m in truth if m[1] < victim.message_start_time]
    assert [_key(m) for m in good] == before
    (report,) = bad
    assert report.offset == victim.chunk_start_offset and "truncated" in report.reason


def test_summary_missing_file_cut_after_the_data_section() -> None:
    data = _recording()
    truth, _ = _truth(data)
    footer_start = struct.unpack_from("<Q", data, len(data) - 8 - 20)[0]  # summary_start
    good, bad = _read(data[:footer_start])
    assert [_key(m) for m in good] == truth
    (report,) = bad
    assert "truncated" in report.reason or "ends" in report.reason


def test_damaged_summary_is_reported_and_not_needed() -> None:
    data = _recording()
    truth, _ = _truth(data)
    summary_start = struct.unpack_from("<Q", data, len(data) - 8 - 20)[0]
    good, bad = _read(_flip(data, summary_start + 30))
    assert [_key(m) for m in good] == truth
    (report,) = bad
    assert "summary CRC" in report.reason


@pytest.mark.parametrize("summary", [True, False])
def test_damaged_record_length_resyncs_on_the_next_chunk(summary: bool) -> None:
    data = _recording()
    truth, chunks = _truth(data)
    victim = chunks[3]
    raw = bytearray(data)
    raw[victim.chunk_start_offset + 1:victim.chunk_start_offset + 9] = struct.pack("<Q", 2**40)
    if not summary:  # also drop the summary: resync by scanning for a chunk header
        raw = raw[:struct.unpack_from("<Q", data, len(data) - 8 - 20)[0]]
    good, bad = _read(bytes(raw))
    assert [_key(m) for m in good] == [m for m in truth if m not in _in_chunk(truth, victim)]
    assert bad[0].offset == victim.chunk_start_offset
    assert f"resumes at the next chunk, offset {chunks[4].chunk_start_offset}" in bad[0].reason
    assert len(bad) == (1 if summary else 2)  # + the missing summary/footer


def test_attachment_and_data_section_crcs() -> None:
    from mcap.writer import Writer

    def build() -> tuple[bytes, int, int]:
        buf = io.BytesIO()
        writer = Writer(buf, chunk_size=200, enable_data_crcs=True)
        writer.start(profile="ros2", library="test")
        sid = writer.register_schema("std_msgs/msg/String", "ros2msg", b"string data")
        cid = writer.register_channel("/s", "cdr", sid)
        for k in range(20):
            writer.add_message(cid, log_time=k, publish_time=k,
                               data=b"\x00\x01\x00\x00\x02\x00\x00\x00x\x00")
        at = buf.tell()
        writer.add_attachment(create_time=1, log_time=7, name="calib.yaml",
                              media_type="text/yaml", data=b"lasers: []\n" * 10)
        writer.finish()
        return buf.getvalue(), at, len(buf.getvalue())

    data, attachment_at, _ = build()
    assert len(_read(data)[0]) == 20 and not _read(data)[1]
    # a byte of the attachment's data: its CRC (and the data-section CRC, not reported twice)
    good, bad = _read(_flip(data, attachment_at + 9 + 8 + 8 + 4 + 10 + 4 + 9 + 8 + 3))
    assert len(good) == 20
    (report,) = bad
    assert "attachment 'calib.yaml' CRC mismatch" in report.reason
    # a byte of a message index record (outside every chunk): only the data-section CRC sees it
    truth, chunks = _truth(data)
    index_at = chunks[0].chunk_start_offset + chunks[0].chunk_length + 12
    good, bad = _read(_flip(data, index_at))
    assert len(good) == 20
    (report,) = bad
    assert "data-section CRC mismatch" in report.reason


@pytest.mark.parametrize("head,words", [
    (b"", "empty"),
    (b"SQLite format 3\x00" + bytes(100), "SQLite"),
    (b"hello world, not a recording", "not an MCAP file"),
    (b"\x89MCA", "magic"),
])
def test_not_an_mcap_file_says_what_it_is(head: bytes, words: str) -> None:
    good, bad = _read(head)
    assert not good
    (report,) = bad
    assert words in report.reason


def test_convert_copies_every_good_message_and_lists_the_damage(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from converters.edge import cli

    data = _recording()
    truth, chunks = _truth(data)
    damaged = _flip(data, chunks[2].chunk_start_offset + chunks[2].chunk_length - 20)
    damaged = damaged[:chunks[6].chunk_start_offset + 30]  # and truncated in chunk 6
    src, dst = tmp_path / "in.mcap", tmp_path / "out.mcap"
    src.write_bytes(damaged)
    assert cli.main(["convert", str(src), str(dst), "-q"]) == 1
    err = capsys.readouterr().err
    assert f"damaged chunk at offset {chunks[2].chunk_start_offset}" in err
    assert f"offset {chunks[6].chunk_start_offset}" in err and "truncated" in err
    assert "2 BAD" in err
    lost = _in_chunk(truth, chunks[2]) + [m for m in truth
                                          if m[1] >= chunks[6].message_start_time]
    good, bad = _read(dst)
    assert not bad
    assert [_key(m) for m in good] == [m for m in truth if m not in lost]


def _fuzz_module() -> Any:
    import importlib.util
    import sys

    path = Path(__file__).resolve().parents[1] / "bench" / "fuzz.py"
    spec = importlib.util.spec_from_file_location("lidarscan_bench_fuzz", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("target,cases", [
    # 1594, 4586, 17116: a damaged uncompressed_size made zstd / lz4 allocate what it declared
    ("mcap_chunks", [1594, 4586, 17116, *range(150)]),
    ("packet_cdr", range(300)),
    # .db3 files whose sqlite error messages are not UTF-8 (raised UnicodeDecodeError once),
    # 3730: a topic row without an id (raised TypeError once)
    ("bag_db3", [152, 288, 2028, 3730, *range(40)]),
])
def test_fuzz_families_hold_their_promises(target: str, cases: Any, tmp_path: Path) -> None:
    """A slice of bench/fuzz.py's chunk-damage, packet and bag families (the long run's
    figures are in RELIABILITY.md): only LidarScanError, and the chunk family's own checks."""
    fuzz = _fuzz_module()
    fuzz.fuzz_common.ROOT = tmp_path  # scratch files of the targets go here
    runner = fuzz.TARGETS[target]()
    runner.setup()
    for index in cases:
        _, call = runner.case(fuzz.case_rng(20241122, target, index))
        try:
            call()
        except LidarScanError:
            pass


def test_schema_name_with_a_nul_byte_and_valid_crcs_is_a_bad_message() -> None:
    """The type-name check behind fuzz case mcap 4198, in a file whose CRCs are intact (so the
    chunk is read and the schema itself is refused)."""
    from mcap.writer import Writer

    buf = io.BytesIO()
    writer = Writer(buf)
    writer.start(profile="ros2", library="test")
    bad = writer.register_schema("std_msgs/msg/Strin\x00", "ros2msg", b"string data")
    good = writer.register_schema("std_msgs/msg/String", "ros2msg", b"string data")
    c_bad = writer.register_channel("/bad", "cdr", bad)
    c_good = writer.register_channel("/good", "cdr", good)
    for k, cid in enumerate((c_bad, c_good)):
        writer.add_message(cid, log_time=k, publish_time=k,
                           data=b"\x00\x01\x00\x00\x02\x00\x00\x00x\x00")
    writer.finish()
    good_items, bad_items = _read(buf.getvalue())
    assert [m.topic for m in good_items] == ["/good"]
    (report,) = bad_items
    assert report.topic == "/bad" and report.index == 0 and "type name" in report.reason
