"""Low-level MCAP writer: records, chunks, indexes and summary of one MCAP file (spec v0).

:class:`lidarscan.mcap.McapWriter` writes through this; it exists instead of ``mcap.writer`` so
the chunk compression level can be chosen (``mcap.writer`` compresses zstd at the library's
default level, the largest cost of ``lidarscan convert``) and so message payloads reach the file
without Python-side copies: a chunk's records are kept as a list of byte pieces (record headers
and the callers' payloads), joined once for the compressor (or written as they are without
compression), the compressed chunk goes to the stream as it is. At the default zstd level a
chunk's parameters follow from what its messages are (a smaller hash table when every message
repeats its bytes only nearby: :data:`LOCAL_HASH_LOG`). Closed chunks can be compressed
and written by background threads (``threads``): the file's bytes do not depend on it.

The file layout is what ``mcap.writer.Writer`` writes with its defaults (so every MCAP reader,
``mcap``'s Python reader, the Go ``mcap`` CLI and Foxglove, reads it): magic, Header; Schema and
Channel records inside the chunks where they are first used; per chunk a Chunk record (CRC-32 of
its uncompressed records; 0, "not computed", with ``crc=False``) followed by one MessageIndex per
channel; DataEnd (no data-section CRC); a summary of every Schema, Channel, Statistics,
ChunkIndex and MetadataIndex with their SummaryOffsets; the Footer (CRC-32 of the summary) and
the magic. The zstd and lz4 frames state their content size. All integers are little-endian.
"""

from __future__ import annotations

import struct
import threading
import zlib
from collections.abc import Callable
from typing import IO, Any

try:  # ISA-L's CRC-32 (the "fast" extra): the same values, about 4x zlib's speed here
    from isal.isal_zlib import crc32 as _crc32
except ImportError:
    from zlib import crc32 as _crc32

__all__ = ["ChunkedMcapWriter", "COMPRESSIONS", "DEFAULT_ZSTD_LEVEL"]

MAGIC = b"\x89MCAP0\r\n"
#: zstd level of the chunks unless a caller chooses one (see bench/README.md, bench_convert:
#: on lidar scans level 2 costs a third to a half of level 3's CPU for 5 % more bytes; level 1
#: is hardly faster and misses the repeats of dual-return scans: 40 % more bytes)
DEFAULT_ZSTD_LEVEL = 2
#: log2 of the zstd hash table of a chunk whose messages all repeat their bytes only nearby
#: (``add_message(local=True)``: a single-return LidarScan, a LidarInfo) at the default level:
#: 2^13 four-byte entries (32 KiB) stay in a core's L2 cache beside the chunk streaming
#: through, level 2's own 2^16 (256 KiB) do not; repeats between neighbouring pixels and
#: no-return runs are found all the same (bench/README.md, bench_convert: VLS-128 chunks
#: 0.55-0.7x level 2's CPU for +0.9 % bytes; VLP32 +2 % over 2^14). Repeats a whole grid back
#: (a second return repeating the first where there is none, 100-400 KB back) need level 2's
#: own table: chunks with them keep it.
LOCAL_HASH_LOG = 13
COMPRESSIONS = ("zstd", "lz4", "none")

_HEADER, _FOOTER, _SCHEMA, _CHANNEL, _MESSAGE, _CHUNK = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06
_MESSAGE_INDEX, _CHUNK_INDEX, _DATA_END = 0x07, 0x08, 0x0F
_METADATA, _METADATA_INDEX, _STATISTICS, _SUMMARY_OFFSET = 0x0C, 0x0D, 0x0B, 0x0E
_MESSAGE_HEAD = struct.Struct("<BQHIQQ")  # opcode, length, channel, sequence, log, publish


def _string(text: str) -> bytes:
    raw = text.encode()
    return struct.pack("<I", len(raw)) + raw


def _string_map(values: dict[str, str]) -> bytes:
    body = b"".join(_string(k) + _string(v) for k, v in sorted(values.items()))
    return struct.pack("<I", len(body)) + body


def _record(opcode: int, body: bytes) -> bytes:
    return struct.pack("<BQ", opcode, len(body)) + body


class _Background:
    """One daemon thread running jobs in submission order from a bounded queue.

    The first error of a job is kept and raised in the caller (by :meth:`submit`, :meth:`drain`
    or :meth:`close`, once); the jobs after it are skipped.
    """

    def __init__(self, depth: int) -> None:
        import queue

        self._queue: queue.Queue[Callable[[], None] | None] = queue.Queue(maxsize=depth)
        self._error: BaseException | None = None
        self._raised = False
        self._thread = threading.Thread(target=self._run, name="mcap-chunk-writer",
                                        daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            job = self._queue.get()
            try:
                if job is None:
                    return
                if self._error is None:
                    job()
            except BaseException as err:  # noqa: BLE001 - handed to the caller's thread
                self._error = err
            finally:
                self._queue.task_done()

    def _check(self) -> None:
        if self._error is not None and not self._raised:
            self._raised = True
            raise self._error

    def submit(self, job: Callable[[], None]) -> None:
        self._check()
        if self._error is None:
            self._queue.put(job)

    def drain(self) -> None:
        self._queue.join()
        self._check()

    def close(self) -> None:
        """Run every job left, stop the thread, raise its error if not raised yet."""
        self._queue.put(None)
        self._thread.join()
        self._check()

    @property
    def failed(self) -> bool:
        return self._error is not None


class _SpillPool:
    """``workers`` compressing threads, the first kept busy before the others are given work:
    a job goes to the first thread with fewer than 2 jobs in hand (one running, one waiting),
    else to the one with fewest. Each thread that joins in costs CPU in every thread (caches
    shared with the converting thread: bench/README.md, bench_convert), so a second one only
    takes the chunks the first cannot keep up with."""

    def __init__(self, workers: int) -> None:
        from concurrent.futures import ThreadPoolExecutor

        self._pools = [ThreadPoolExecutor(1, thread_name_prefix=f"mcap-compress-{k}")
                       for k in range(workers)]
        self._jobs: list[list[Any]] = [[] for _ in self._pools]

    def submit(self, fn: Callable[..., Any], *args: Any) -> Any:
        for jobs in self._jobs:
            jobs[:] = [job for job in jobs if not job.done()]
        k = next((k for k, jobs in enumerate(self._jobs) if len(jobs) < 2),
                 min(range(len(self._jobs)), key=lambda k: len(self._jobs[k])))
        job = self._pools[k].submit(fn, *args)
        self._jobs[k].append(job)
        return job

    def shutdown(self) -> None:
        for pool in self._pools:
            pool.shutdown()


def _compressor(compression: str, level: int | None, local: bool = False
                ) -> tuple[str, Callable[[bytes], bytes]]:
    """(the Chunk record's compression name, compress(records) -> frame); ``local``: the
    records repeat their bytes only nearby (used at the default level only: its parameters with
    a hash table of :data:`LOCAL_HASH_LOG`)."""
    if compression == "zstd":
        import zstandard

        if local and level is None:
            base = zstandard.ZstdCompressionParameters.from_level(DEFAULT_ZSTD_LEVEL)
            params = zstandard.ZstdCompressionParameters(
                window_log=base.window_log, chain_log=base.chain_log,
                hash_log=min(base.hash_log, LOCAL_HASH_LOG), search_log=base.search_log,
                min_match=base.min_match, target_length=base.target_length,
                strategy=base.strategy, write_content_size=1)
            return "zstd", zstandard.ZstdCompressor(compression_params=params).compress
        cctx = zstandard.ZstdCompressor(
            level=DEFAULT_ZSTD_LEVEL if level is None else level, write_content_size=True)
        return "zstd", cctx.compress
    if compression == "lz4":
        import lz4.frame

        def lz4_compress(data: bytes) -> bytes:
            return lz4.frame.compress(data, store_size=True)  # type: ignore[no-any-return]
        return "lz4", lz4_compress
    return "", bytes


class ChunkedMcapWriter:
    """One MCAP file written to ``stream`` (binary; offsets are the stream's positions).

    Args:
        stream: binary stream; left open by :meth:`finish`.
        chunk_size: a chunk is closed once its uncompressed records pass this many bytes.
        compression: "zstd", "lz4" or "none" (the caller checks the name).
        level: zstd level (default :data:`DEFAULT_ZSTD_LEVEL`, with a hash table of
            :data:`LOCAL_HASH_LOG` for chunks of local messages, see :meth:`add_message`;
            negative levels are zstd's fast ones); ignored for the others.
        threads: 1: everything in the caller's thread; 2: the chunks are compressed and
            written by one writer thread (zstd, lz4, CRC-32 and file writes release the GIL:
            they overlap the caller's work on another core); N > 2: N - 1 threads compress
            chunks side by side (the first kept busy before the next is given chunks:
            :class:`_SpillPool`) and the writer thread writes them in order. The file's bytes
            are the same for every N. At most ``queue_chunks`` closed chunks (at least 2 per
            compressing thread) wait for the threads, then :meth:`add_message` blocks (memory
            stays bounded); an error of a thread is raised by the next call here (at the
            latest by :meth:`finish`).
        queue_chunks: see ``threads``.
        crc: compute the chunks' CRC-32 of their uncompressed records (False: write 0, which
            MCAP defines as "not computed"; readers then skip the check).
    """

    def __init__(self, stream: IO[bytes], *, chunk_size: int, compression: str,
                 level: int | None = None, threads: int = 1, queue_chunks: int = 4,
                 crc: bool = True) -> None:
        self._stream = stream
        try:
            self._offset = stream.tell()   # file offsets count from the stream's start
        except (AttributeError, OSError):
            self._offset = 0               # a pipe: we are at its start
        self._chunk_size = max(int(chunk_size), 1)
        self._name = _compressor(compression, level)[0]
        self._codec = (compression, level)
        self._local = threading.local()     # per-thread compressors
        self._schemas: list[bytes] = []      # Schema record bodies, for the summary
        self._channels: list[bytes] = []     # Channel record bodies, for the summary
        self._pieces: list[Any] = []         # records of the open chunk
        self._chunk_bytes = 0
        self._index: dict[int, list[int]] = {}   # channel -> [log time, offset, ...]
        self._chunk_times: list[int] = []        # [first, last] log time of the open chunk
        self._chunk_local = True                 # every message of the open chunk is local
        self._chunk_indexes: list[bytes] = []
        self._metadata_indexes: list[bytes] = []
        self._counts: dict[int, int] = {}
        self._messages = 0
        self._times: list[int] = []
        self._chunks = 0
        self._metadata = 0
        self._check = bool(crc)
        threads = max(int(threads), 1)
        self._background = _Background(max(int(queue_chunks), 2 * (threads - 1))) \
            if threads > 1 else None
        self._pool: Any = None
        if threads > 2:
            self._pool = _SpillPool(threads - 1)

    def _write(self, data: Any) -> None:
        self._stream.write(data)
        self._offset += len(data) if isinstance(data, bytes) else memoryview(data).nbytes

    def start(self, profile: str, library: str) -> None:
        self._write(MAGIC)
        self._write(_record(_HEADER, _string(profile) + _string(library)))

    def _add_to_chunk(self, record: bytes) -> None:
        self._pieces.append(record)
        self._chunk_bytes += len(record)

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        schema_id = len(self._schemas) + 1
        body = struct.pack("<H", schema_id) + _string(name) + _string(encoding) + \
            struct.pack("<I", len(data)) + bytes(data)
        self._schemas.append(body)
        self._add_to_chunk(_record(_SCHEMA, body))
        return schema_id

    def register_channel(self, topic: str, message_encoding: str, schema_id: int,
                         metadata: dict[str, str]) -> int:
        channel_id = len(self._channels) + 1
        body = struct.pack("<HH", channel_id, schema_id) + _string(topic) + \
            _string(message_encoding) + _string_map(metadata)
        self._channels.append(body)
        self._counts[channel_id] = 0
        self._add_to_chunk(_record(_CHANNEL, body))
        return channel_id

    def add_message(self, *, channel_id: int, log_time: int, data: Any, publish_time: int,
                    sequence: int = 0, local: bool = False) -> None:
        """One Message record; ``data`` (bytes-like, or a list of bytes-like pieces that make
        the payload together) is kept by reference until its chunk is written: the caller must
        not change it. ``local``: the payload repeats its bytes only nearby (a few KiB back,
        not an earlier message's): a chunk of only such messages is compressed with a smaller
        zstd hash table at the default level (:data:`LOCAL_HASH_LOG`)."""
        if not local:
            self._chunk_local = False
        parts = data if isinstance(data, list) else [data]
        size = sum(len(p) if isinstance(p, bytes) else memoryview(p).nbytes for p in parts)
        self._index.setdefault(channel_id, []).extend((log_time, self._chunk_bytes))
        self._pieces.append(_MESSAGE_HEAD.pack(_MESSAGE, 22 + size, channel_id, sequence,
                                               log_time, publish_time))
        self._pieces.extend(parts)
        self._chunk_bytes += 31 + size
        if self._chunk_times:
            if log_time < self._chunk_times[0]:
                self._chunk_times[0] = log_time
            if log_time > self._chunk_times[1]:
                self._chunk_times[1] = log_time
        else:
            self._chunk_times = [log_time, log_time]
        self._counts[channel_id] += 1
        self._messages += 1
        if self._chunk_bytes > self._chunk_size:
            self._finish_chunk()

    def _finish_chunk(self) -> None:
        """Close the open chunk: it is packed and written in this thread, or handed to the
        writer threads (``threads`` > 1; same bytes, same order)."""
        if not self._chunk_times:
            return  # no message yet: its Schema/Channel records wait for the next chunk
        start, end = self._chunk_times
        self._times = [min(self._times[0], start), max(self._times[1], end)] if self._times \
            else [start, end]
        pieces, size, index, local = self._pieces, self._chunk_bytes, self._index, \
            self._chunk_local
        self._pieces, self._chunk_bytes, self._index, self._chunk_times = [], 0, {}, []
        self._chunk_local = True
        if self._background is None:
            self._write_chunk(self._pack(pieces, local), size, index, start, end)
        elif self._pool is None:    # the writer thread compresses and writes
            self._background.submit(
                lambda: self._write_chunk(self._pack(pieces, local), size, index, start, end))
        else:                       # the pool compresses, the writer thread writes in order
            packed = self._pool.submit(self._pack, pieces, local)
            self._background.submit(
                lambda: self._write_chunk(packed.result(), size, index, start, end))

    def _pack(self, pieces: list[Any], local: bool = False) -> tuple[int, list[Any]]:
        """(CRC-32 of the records, the frames that hold them in the file: one compressed
        frame, or the pieces themselves without compression); ``local``: every message of the
        chunk is local (see :meth:`add_message`). Thread-safe."""
        if self._name:
            records = b"".join(pieces)
            compressors = getattr(self._local, "compressors", None)
            if compressors is None:     # a zstd compressor is used by one thread at a time
                compressors = self._local.compressors = {}
            compress = compressors.get(local)
            if compress is None:
                compress = compressors[local] = _compressor(*self._codec, local)[1]
            return (_crc32(records) if self._check else 0), [compress(records)]
        crc = 0
        if self._check:
            for piece in pieces:
                crc = _crc32(piece, crc)
        return crc, pieces

    def _write_chunk(self, packed: tuple[int, list[Any]], size: int,
                     index: dict[int, list[int]], start: int, end: int) -> None:
        """Write one chunk (``packed`` by :meth:`_pack` from its records, ``size`` bytes), then
        one MessageIndex per channel; its ChunkIndex is kept for the summary. Runs in one
        thread at a time (the writer thread, or the caller's without one), in chunk order."""
        crc, frames = packed
        compressed = sum(len(f) for f in frames) if self._name else size
        head = struct.pack("<QQQI", start, end, size, crc) + _string(self._name) + \
            struct.pack("<Q", compressed)
        chunk_start = self._offset
        self._write(struct.pack("<BQ", _CHUNK, len(head) + compressed) + head)
        for frame in frames:
            self._write(frame)
        chunk_length = self._offset - chunk_start
        index_start = self._offset
        offsets = []
        for channel_id, entries in sorted(index.items()):
            offsets.append(struct.pack("<HQ", channel_id, self._offset))
            body = struct.pack(f"<HI{len(entries)}Q", channel_id, 8 * len(entries), *entries)
            self._write(_record(_MESSAGE_INDEX, body))
        offset_map = b"".join(offsets)
        self._chunk_indexes.append(_record(_CHUNK_INDEX, struct.pack(
            "<QQQQI", start, end, chunk_start, chunk_length, len(offset_map)) + offset_map +
            struct.pack("<Q", self._offset - index_start) + _string(self._name) +
            struct.pack("<QQ", compressed, size)))
        self._chunks += 1

    def _drain(self) -> None:
        """Wait until the writer thread has written every chunk handed to it (re-raises its
        error); a no-op without one."""
        if self._background is not None:
            self._background.drain()

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        self._finish_chunk()   # a Metadata record stands between chunks
        self._drain()
        offset = self._offset
        record = _record(_METADATA, _string(name) + _string_map(data))
        self._write(record)
        self._metadata += 1
        self._metadata_indexes.append(_record(_METADATA_INDEX, struct.pack(
            "<QQ", offset, len(record)) + _string(name)))

    def finish(self) -> None:
        """Close the open chunk, write DataEnd, the summary, the Footer and the magic (Schema
        and Channel records of a channel without messages after the last chunk are only in the
        summary)."""
        background = self._background
        try:
            self._finish_chunk()
        finally:
            self._background = None
            if background is not None:
                try:
                    background.close()  # every chunk written; raises the thread's error
                finally:
                    if self._pool is not None:
                        self._pool.shutdown()
                        self._pool = None
        if background is not None and background.failed:
            return  # a chunk was not written: no summary over it (the error was raised)
        self._write(_record(_DATA_END, struct.pack("<I", 0)))
        summary_start = self._offset
        groups: list[tuple[int, list[bytes]]] = [
            (_SCHEMA, [_record(_SCHEMA, b) for b in self._schemas]),
            (_CHANNEL, [_record(_CHANNEL, b) for b in self._channels]),
            (_STATISTICS, [self._statistics()]),
            (_CHUNK_INDEX, self._chunk_indexes),
            (_METADATA_INDEX, self._metadata_indexes),
        ]
        parts: list[bytes] = []
        offsets: list[bytes] = []
        at = summary_start
        for opcode, records in groups:
            if not records:
                continue
            block = b"".join(records)
            offsets.append(_record(_SUMMARY_OFFSET, struct.pack("<BQQ", opcode, at, len(block))))
            parts.append(block)
            at += len(block)
        summary_offset_start = at
        summary = b"".join(parts + offsets)
        footer_head = struct.pack("<BQQQ", _FOOTER, 20, summary_start, summary_offset_start)
        crc = zlib.crc32(footer_head, zlib.crc32(summary))
        self._write(summary)
        self._write(footer_head + struct.pack("<I", crc))
        self._write(MAGIC)

    def _statistics(self) -> bytes:
        start, end = self._times or (0, 0)
        counts = b"".join(struct.pack("<HQ", c, n) for c, n in sorted(self._counts.items()))
        return _record(_STATISTICS, struct.pack(
            "<QHIIIIQQI", self._messages, len(self._schemas), len(self._channels), 0,
            self._metadata, self._chunks, start, end, len(counts)) + counts)
