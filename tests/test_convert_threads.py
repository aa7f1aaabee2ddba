"""``lidarscan convert`` writes the same messages whatever its threads: every message's topic,
type, times and bytes of the real raw-packet recordings (tests/data/nebula, see their NOTICE
files) converted with ``--threads 1`` (everything in one thread), 2 and 3 (the default: reading
ahead, compressing and writing in other threads) are equal, and equal to the digests of the
converter before the pipeline's threads were reworked (main at fde7d8b; chunking and chunk
compression may differ, the messages may not)."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest

from converters.edge import cli
from lidarscan.mcap import BadMessage, read_messages

DATA = Path(__file__).parent / "data" / "nebula"

#: recording -> (calibration, sha256 of its messages converted by main at fde7d8b, count)
RECORDINGS = {
    "velodyne_vls128": ("VLS128.yaml",
                        "196eca02934da073a254f41d7055a57a073bc07af4feec7b6476726058bcc037", 6),
    "velodyne_vlp32": ("VLP32.yaml",
                       "3f4991ef85ee5bdd8a849cf36b03f032d067c00970ec503398f83a5556e61a2d", 7),
    "hesai_pandar64": ("Pandar64.csv",
                       "5154d4f95a4974bff76e2713cc39b7f3b5872ec02b5af3d9603a99ee3d2ff749", 6),
}


def message_digest(path: Path) -> tuple[str, int]:
    """(sha256 over every message in file order: topic, type, encoding, log and publish time,
    payload; the number of messages) of an MCAP file."""
    digest = hashlib.sha256()
    count = 0
    for item in read_messages(path):
        assert not isinstance(item, BadMessage), item
        for part in (item.topic, item.msgtype, item.encoding):
            digest.update(part.encode() + b"\0")
        digest.update(item.log_time_ns.to_bytes(8, "little", signed=True))
        digest.update(item.publish_time_ns.to_bytes(8, "little", signed=True))
        digest.update(len(item.payload).to_bytes(8, "little"))
        digest.update(item.payload)
        count += 1
    return digest.hexdigest(), count


def _convert(name: str, out: Path, *options: str) -> Path:
    calibration = RECORDINGS[name][0]
    status = cli.main(["convert", str(DATA / name / "bag"), str(out), "--calibration",
                       str(DATA / name / calibration), "-q", *options])
    assert status == 0
    return out


@pytest.mark.parametrize("name", sorted(RECORDINGS))
def test_same_messages_for_every_thread_count(name: str, tmp_path: Path) -> None:
    digests = {threads: message_digest(_convert(name, tmp_path / f"{threads}.mcap",
                                                "--threads", str(threads)))
               for threads in (1, 2, 3)}
    assert digests[1] == digests[2] == digests[3]
    _, golden, count = RECORDINGS[name]
    assert digests[1] == (golden, count)


def test_same_messages_with_a_reading_thread_that_waits(tmp_path: Path,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """A read-ahead of one message (the reader blocks on every put) changes nothing."""
    from converters.edge.cli import _common

    monkeypatch.setattr(_common, "READ_AHEAD", 1)
    monkeypatch.setattr(_common._read_ahead, "__defaults__", (1,))
    name = "velodyne_vls128"
    assert message_digest(_convert(name, tmp_path / "1.mcap", "--threads", "3")) == \
        RECORDINGS[name][1:]


def test_switch_interval_restored(tmp_path: Path) -> None:
    """``convert`` with threads shortens the GIL switch interval only while it runs."""
    import sys

    before = sys.getswitchinterval()
    _convert("velodyne_vls128", tmp_path / "o.mcap")
    assert sys.getswitchinterval() == before


def test_second_compressing_thread_takes_only_the_backlog() -> None:
    """The chunk compressors' pool keeps its first thread busy (one chunk running, one
    waiting) before a second thread gets a chunk; results come back per job."""
    import threading

    from lidarscan._mcapfile import _SpillPool

    release = threading.Event()
    pool = _SpillPool(2)
    try:
        def job(k: int) -> tuple[int, str]:
            release.wait(10)
            return k, threading.current_thread().name.rsplit("_", 1)[0]

        jobs = [pool.submit(job, k) for k in range(4)]
        release.set()
        got = [j.result(10) for j in jobs]
    finally:
        pool.shutdown()
    assert got == [(0, "mcap-compress-0"), (1, "mcap-compress-0"), (2, "mcap-compress-1"),
                   (3, "mcap-compress-1")]
