"""The low-level MCAP writer (lidarscan._mcapfile) against the reference readers: the ``mcap``
package's stream reader (every record, CRCs checked) and its indexed reader (summary, chunk and
message indexes), for every chunk compression and a few zstd levels."""

from __future__ import annotations

import io
import struct
import zlib
from typing import Any

import pytest

from lidarscan.mcap._file import ChunkedMcapWriter
from lidarscan.errors import ConfigError
from lidarscan.mcap import McapWriter, read_messages

CASES = [("zstd", None), ("zstd", 3), ("zstd", -5), ("lz4", None), ("none", None)]


def _messages(n: int = 40) -> list[tuple[int, int, bytes]]:
    """(channel, log time, payload): two channels, times not sorted, sizes from 0 to ~3 kB."""
    out = []
    for i in range(n):
        payload = bytes((i * 7 + k) % 251 for k in range((i * 97) % 3000))
        out.append((1 + i % 2, 1_000 + ((i * 37) % n) * 10, payload))
    return out


def _write(compression: str, level: int | None, messages: list[tuple[int, int, bytes]],
           chunk_size: int = 4096, **options: Any) -> bytes:
    buf = io.BytesIO()
    writer = ChunkedMcapWriter(buf, chunk_size=chunk_size, compression=compression, level=level,
                               **options)
    writer.start("ros2", "test")
    schema = writer.register_schema("pkg/msg/A", "ros2msg", b"int32 a")
    for topic in ("/a", "/b"):
        writer.register_channel(topic, "cdr", schema, {"k": topic})
    for seq, (channel, log_time, payload) in enumerate(messages):
        writer.add_message(channel_id=channel, log_time=log_time, data=payload,
                           publish_time=log_time + 1, sequence=seq)
    writer.add_metadata("rosbag2", {"serialized_metadata": "x: 1"})
    writer.finish()
    return buf.getvalue()


@pytest.mark.parametrize(("compression", "level"), CASES)
def test_every_record_reads_back_with_crcs_checked(compression: str, level: int | None) -> None:
    from mcap.records import Chunk, DataEnd, Footer, Message, MessageIndex
    from mcap.stream_reader import StreamReader

    messages = _messages()
    data = _write(compression, level, messages)
    records = list(StreamReader(io.BytesIO(data), validate_crcs=True).records)
    got = [(r.channel_id, r.log_time, r.data, r.sequence, r.publish_time)
           for r in records if isinstance(r, Message)]
    assert got == [(c, t, p, s, t + 1) for s, (c, t, p) in enumerate(messages)]
    chunks = [r for r in StreamReader(io.BytesIO(data), emit_chunks=True).records
              if isinstance(r, Chunk)]
    assert len(chunks) > 3  # the 4 kB chunks closed many times
    assert {c.compression for c in chunks} == {"" if compression == "none" else compression}
    assert sum(isinstance(r, MessageIndex) for r in records) >= len(chunks)
    assert isinstance(records[-1], Footer) and any(isinstance(r, DataEnd) for r in records)


@pytest.mark.parametrize(("compression", "level"), CASES)
def test_the_indexed_reader_finds_every_message_through_the_summary(
        compression: str, level: int | None) -> None:
    from mcap.reader import make_reader

    messages = _messages()
    data = _write(compression, level, messages)
    reader = make_reader(io.BytesIO(data), validate_crcs=True)
    summary = reader.get_summary()
    assert summary is not None
    stats = summary.statistics
    assert stats.message_count == len(messages) and stats.channel_count == 2
    assert stats.message_start_time == min(t for _, t, _ in messages)
    assert stats.message_end_time == max(t for _, t, _ in messages)
    assert stats.channel_message_counts == {1: 20, 2: 20}
    assert stats.chunk_count == len(summary.chunk_indexes) and stats.metadata_count == 1
    assert {c.topic: c.metadata for c in summary.channels.values()} == {
        "/a": {"k": "/a"}, "/b": {"k": "/b"}}
    # the indexed path reads through chunk indexes and message indexes, in log-time order
    got = [(c.id, m.log_time, m.data) for _, c, m in reader.iter_messages(log_time_order=True)]
    assert got == sorted(((c, t, p) for c, t, p in messages), key=lambda m: m[1])
    only_b = [m.data for _, _, m in reader.iter_messages(topics=["/b"], log_time_order=False)]
    assert sorted(only_b) == sorted(p for c, _, p in messages if c == 2)
    assert [m.name for m in reader.iter_metadata()] == ["rosbag2"]


def test_message_indexes_point_at_their_messages() -> None:
    """Each MessageIndex entry's offset, inside its chunk's uncompressed records, is the start of
    a Message record of that channel with that log time."""
    from mcap.records import Chunk, MessageIndex
    from mcap.stream_reader import StreamReader

    data = _write("none", None, _messages())
    records = list(StreamReader(io.BytesIO(data), emit_chunks=True).records)
    checked = 0
    chunk: Any = None
    for record in records:
        if isinstance(record, Chunk):
            chunk = record
            assert zlib.crc32(chunk.data) == chunk.uncompressed_crc
        elif isinstance(record, MessageIndex):
            for log_time, offset in record.records:
                opcode, _, channel, _, stamp = struct.unpack_from("<BQHIQ", chunk.data, offset)
                assert (opcode, channel, stamp) == (0x05, record.channel_id, log_time)
                checked += 1
    assert checked == 40


def test_a_payload_view_of_any_item_size_is_written_as_its_bytes() -> None:
    import numpy as np
    from mcap.reader import make_reader

    buf = io.BytesIO()
    writer = ChunkedMcapWriter(buf, chunk_size=1 << 20, compression="zstd")
    writer.start("", "test")
    writer.register_channel("/v", "raw", 0, {})
    values = np.arange(10, dtype=np.float64)
    writer.add_message(channel_id=1, log_time=5, data=memoryview(values), publish_time=5)
    writer.finish()
    got = [m.data for _, _, m in make_reader(io.BytesIO(buf.getvalue()),
                                             validate_crcs=True).iter_messages()]
    assert got == [values.tobytes()]


@pytest.mark.parametrize("level", [None, 1, 19, -3])
def test_mcap_writer_levels_read_back_with_ours_and_theirs(tmp_path: Any,
                                                           level: int | None) -> None:
    from mcap.reader import make_reader

    path = tmp_path / "x.mcap"
    with McapWriter(path, level=level, chunk_size=2048) as writer:
        for i in range(30):
            writer.write("/raw", bytes(range(i, i + 200)), msgtype="std_msgs/msg/String",
                         log_time_ns=i)
    ours = [m.payload for m in read_messages(path)]
    with open(path, "rb") as stream:
        theirs = [m.data for _, _, m in make_reader(stream, validate_crcs=True).iter_messages()]
    assert ours == theirs == [bytes(range(i, i + 200)) for i in range(30)]


@pytest.mark.parametrize("level", [23, 1.5, "3"])
def test_mcap_writer_refuses_a_level_zstd_does_not_have(tmp_path: Any, level: Any) -> None:
    with pytest.raises(ConfigError, match="level"):
        McapWriter(tmp_path / "x.mcap", level=level)


# ------------------------------------------------------------------- threads, CRC, payloads

@pytest.mark.parametrize(("compression", "level"), CASES)
@pytest.mark.parametrize("threads", [2, 3, 5])
def test_the_writer_threads_write_the_same_bytes(compression: str, level: int | None,
                                                 threads: int) -> None:
    messages = _messages(120)
    alone = _write(compression, level, messages)
    assert _write(compression, level, messages, threads=threads, queue_chunks=1) == alone
    # a payload given as pieces is the same message as their join
    pieces = [(c, t, [p[:7], memoryview(p)[7:]]) for c, t, p in messages]
    assert _write(compression, level, pieces, threads=threads) == alone  # type: ignore[arg-type]


class _FailingStream(io.BytesIO):
    """A stream whose writes fail once ``limit`` bytes were written (a full disk)."""

    def __init__(self, limit: int) -> None:
        super().__init__()
        self.limit = limit

    def write(self, data: Any) -> int:
        if self.tell() + memoryview(data).nbytes > self.limit:
            raise OSError(28, "No space left on device")
        return super().write(data)


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_an_error_of_the_writer_thread_is_raised_in_the_caller(threads: int) -> None:
    import threading

    before = threading.active_count()
    stream = _FailingStream(20_000)
    writer = ChunkedMcapWriter(stream, chunk_size=4096, compression="none", threads=threads)
    writer.start("ros2", "test")
    schema = writer.register_schema("pkg/msg/A", "ros2msg", b"int32 a")
    writer.register_channel("/a", "cdr", schema, {})
    with pytest.raises(OSError, match="No space left"):
        for seq in range(1000):   # 3 MB: fails long before the end
            writer.add_message(channel_id=1, log_time=seq, data=bytes(3000), publish_time=seq,
                               sequence=seq)
        writer.finish()
    assert seq < 1000
    writer.finish()     # after the error: the threads stop, nothing more is written, no raise
    assert stream.tell() <= 20_000
    assert threading.active_count() == before


def test_the_queue_of_closed_chunks_is_bounded() -> None:
    """A stream that does not take the bytes (a slow disk): the caller waits once a few
    closed chunks are queued, and goes on when the stream does."""
    import threading

    class Stalled(io.BytesIO):
        def __init__(self) -> None:
            super().__init__()
            self.go = threading.Event()

        def write(self, data: Any) -> int:
            if threading.current_thread().name == "mcap-chunk-writer":   # the chunks wait
                self.go.wait(30)
            return super().write(data)

    stream = Stalled()
    writer = ChunkedMcapWriter(stream, chunk_size=1000, compression="zstd", threads=2,
                               queue_chunks=3)
    writer.start("ros2", "test")
    writer.register_channel("/a", "cdr", 0, {})
    added: list[int] = []

    def produce() -> None:
        for seq in range(50):           # one chunk per message
            writer.add_message(channel_id=1, log_time=seq, data=bytes(1500), publish_time=seq)
            added.append(seq)

    producer = threading.Thread(target=produce)
    producer.start()
    producer.join(1.0)
    assert producer.is_alive() and len(added) <= 3 + 2  # queued + the thread's + the caller's
    stream.go.set()
    producer.join(30)
    assert not producer.is_alive() and len(added) == 50
    writer.finish()
    assert len(list(read_messages(io.BytesIO(stream.getvalue())))) == 50


def test_chunks_without_crc_read_with_crc_checks_on() -> None:
    from mcap.reader import make_reader
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader

    messages = _messages()
    data = _write("zstd", None, messages, crc=False)
    chunks = [r for r in StreamReader(io.BytesIO(data), emit_chunks=True).records
              if isinstance(r, Chunk)]
    assert chunks and {c.uncompressed_crc for c in chunks} == {0}  # 0: not computed
    got = [m.data for _, _, m in make_reader(io.BytesIO(data), validate_crcs=True)
           .iter_messages(log_time_order=False)]
    assert got == [p for _, _, p in messages]


def test_mcap_writer_keeps_read_only_arrays_and_copies_writable_ones(tmp_path: Any) -> None:
    """A read-only array is written as it is when its chunk closes; a writable one as it was
    when write() was called (the caller may reuse it)."""
    import numpy as np

    from lidarscan import types
    from lidarscan.mcap import McapWriter as Writer

    def scan(data: Any) -> Any:
        return types.LidarScan(header=types.Header(types.Time(1, 0), "lidar"),
                               lidar_info_time=types.Time(1, 0), height=1,
                               width=data.size // 4, channels=(types.LidarChannel(
                                   "range", 0, 7, 1),), data=data)

    writable = np.arange(1 << 17, dtype=np.uint8)
    frozen = np.arange(1 << 17, dtype=np.uint8)[::-1].copy()
    frozen.flags.writeable = False
    path = tmp_path / "x.mcap"
    with Writer(path, threads=2) as writer:
        writer.write("/a", scan(writable), log_time_ns=1)
        writer.write("/b", scan(frozen), log_time_ns=2)
        expected = writable.copy()
        writable[:] = 0                      # changed before its chunk was written
    got = {m.topic: m.decode().data for m in read_messages(path)}
    assert bytes(got["/a"]) == expected.tobytes() and bytes(got["/b"]) == frozen.tobytes()


@pytest.mark.parametrize("threads", [0, 65, 1.5])
def test_mcap_writer_refuses_a_thread_count_it_cannot_use(tmp_path: Any, threads: Any) -> None:
    with pytest.raises(ConfigError, match="threads"):
        McapWriter(tmp_path / "x.mcap", threads=threads)


# ------------------------------------------------- zstd parameters chosen from the messages

def _grid_scan(names: tuple[str, ...], stamp: int, rows: int = 32, cols: int = 512) -> Any:
    """A LidarScan dataclass: one uint16 grid per name, second returns equal to the first
    where a pixel has no second return (as a dual-return sensor's)."""
    import numpy as np

    from lidarscan import types

    rng = np.random.default_rng(stamp)
    first = rng.integers(0, 4000, (rows, cols), dtype=np.uint16)
    grids = []
    for name in names:
        grid = first.copy() if name[-1:].isdigit() else \
            rng.integers(0, 4000, (rows, cols), dtype=np.uint16)
        if name[-1:].isdigit():
            grid[:, ::7] = 0
        grids.append(grid)
    data = np.concatenate([g.ravel() for g in grids]).view(np.uint8)
    data.flags.writeable = False
    plane = rows * cols * 2
    return types.LidarScan(
        header=types.Header(types.Time(stamp, 0), "lidar"), lidar_info_time=types.Time(1, 0),
        height=rows, width=cols, data=data,
        channels=tuple(types.LidarChannel(n, k * plane, 4, 1) for k, n in enumerate(names)))


def test_local_messages_are_lidar_infos_and_scans_without_a_second_return() -> None:
    from lidarscan.mcap._writer import _local
    from lidarscan.mcap import INFO_TYPE, SCAN_TYPE

    assert _local(_grid_scan(("range", "intensity"), 1), SCAN_TYPE)
    assert not _local(_grid_scan(("range", "intensity", "range2"), 1), SCAN_TYPE)
    assert not _local(b"\x00\x01\x00\x00", SCAN_TYPE)          # encoded: unknown
    assert _local(object(), INFO_TYPE)
    assert not _local(object(), "sensor_msgs/msg/PointCloud2")


@pytest.mark.parametrize("level", [None, 2])
def test_each_chunk_is_compressed_with_the_parameters_its_messages_call_for(
        tmp_path: Any, level: int | None) -> None:
    """Default level: a chunk of single-return scans only gets the small hash table, a chunk
    with a second return (or any other message) level 2's own; a chosen level is used as it
    is. Every chunk reads back (CRCs checked) and the bytes do not depend on the threads."""
    import zstandard
    from mcap.reader import make_reader
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader

    from lidarscan.mcap._file import _compressor

    single, dual = ("range", "intensity"), ("range", "intensity", "range2", "intensity2")
    plan = [("/s", single), ("/s", single), ("/d", dual), ("/s", single), ("/d", dual)]
    outputs = []
    for threads in (1, 3):
        path = tmp_path / f"t{threads}.mcap"
        with McapWriter(path, level=level, chunk_size=1, threads=threads,
                        file_name="x.mcap") as writer:
            for k, (topic, names) in enumerate(plan):    # chunk_size 1: a chunk per message
                writer.write(topic, _grid_scan(names, 10 + k), log_time_ns=k)
        outputs.append(path.read_bytes())
    assert outputs[0] == outputs[1]
    chunks = [r for r in StreamReader(io.BytesIO(outputs[0]), emit_chunks=True).records
              if isinstance(r, Chunk)]
    assert len(chunks) == len(plan)
    small, default = _compressor("zstd", None, True)[1], _compressor("zstd", level)[1]
    differ = 0
    for chunk, (_, names) in zip(chunks, plan):
        records = zstandard.ZstdDecompressor().decompress(chunk.data)
        want = small if level is None and names == single else default
        assert chunk.data == want(records)
        differ += small(records) != default(records)
    assert differ == len(plan)          # the two parameter sets do give different frames
    with open(tmp_path / "t1.mcap", "rb") as stream:
        got = [(c.topic, m.log_time) for _, c, m in
               make_reader(stream, validate_crcs=True).iter_messages()]
    assert got == [(topic, k) for k, (topic, _) in enumerate(plan)]
