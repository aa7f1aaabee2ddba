"""Shared parts of the ``lidarscan`` commands: exit codes, progress, messages, inputs."""

from __future__ import annotations

import functools
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any


EXIT_OK, EXIT_BAD, EXIT_FATAL, EXIT_INTERRUPTED = 0, 1, 2, 130


@functools.cache
def codec_coder() -> Any:
    """The compiled residual coder of :mod:`lidarscan.codec` (same bytes as its numpy
    reference, faster), or None when numba is missing or switched off; loaded on first use."""
    from converters._kernels import select
    return select("codec").numba


def decode_item(item: Any) -> Any:
    """Decode one recorded message (an :class:`lidarscan.mcap.McapMessage`); a LidarScan
    stored as a :mod:`lidarscan.codec` buffer is decompressed with :func:`codec_coder`."""
    from lidarscan.mcap import CODEC_ENCODING
    if getattr(item, "encoding", "cdr") == CODEC_ENCODING:
        return item.decode(codec_coder())
    return item.decode()


class Progress:
    """Progress on stderr: a one-line bar at most 10 Hz on a terminal; when enabled on a
    stream that is not a terminal (``--progress``), one line per 10 %."""

    def __init__(self, total: int, label: str, *, stream: IO[str] | None = None,
                 enabled: bool | None = None) -> None:
        self.total = max(int(total), 1)
        self.label = label
        self.stream = stream or sys.stderr
        tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.enabled = tty if enabled is None else enabled
        self.lines = self.enabled and not tty
        self._last = 0.0
        self._step = -1
        self._shown = False

    def update(self, done: int, extra: str = "", *, force: bool = False) -> None:
        if not self.enabled:
            return
        fraction = min(max(done / self.total, 0.0), 1.0)
        if self.lines:
            step = int(fraction * 10)
            if step != self._step:
                self._step = step
                self.stream.write(f"{self.label}: {100 * fraction:3.0f}% {extra}\n")
                self.stream.flush()
            return
        now = time.monotonic()
        if not force and now - self._last < 0.1:
            return
        self._last = now
        bar = "#" * int(fraction * 30)
        self.stream.write(f"\r{self.label} [{bar:<30}] {100 * fraction:5.1f}% {extra}\x1b[K")
        self.stream.flush()
        self._shown = True

    def close(self) -> None:
        if self._shown:
            self.stream.write("\n")
            self.stream.flush()
            self._shown = False


def _err(*parts: Any) -> None:
    print(*parts, file=sys.stderr)


def _fmt_stamp(ns: int) -> str:
    return f"{ns // 1_000_000_000}.{ns % 1_000_000_000:09d}"


def _namespace(topic: str) -> str:
    """'/lidar/scan' -> '/lidar'; '/scan' or 'scan' -> ''."""
    head, _, _ = topic.rstrip("/").rpartition("/")
    return head


@dataclass
class _Input:
    """A recording named on the command line: an MCAP file, a rosbag2 bag or an Ouster file.

    Attributes:
        path: as given.
        kind: :class:`converters.sources.bags.InputKind` (``kind.kind`` is ``"ouster"`` for .pcap/.osf).
        bag: the :class:`converters.sources.bags.Bag` of a rosbag2 directory or .db3 file.
        ahead: :meth:`items` reads in a background thread (False: in the caller's).
    """

    path: Path
    kind: Any
    bag: Any = None
    ahead: bool = True

    def topics(self) -> dict[str, str]:
        """topic -> message type."""
        if self.bag is not None:
            return {t.name: t.msgtype for t in self.bag.topics.values()}
        return _file_topics(self.path)

    def items(self, progress: Progress | None = None,
              prepare: Callable[[Any], Any] | None = None) -> Iterator[Any]:
        """Every message (McapMessage) and damaged part (BadMessage), updating ``progress``;
        read (and decompressed) by a background thread a few messages ahead of the caller
        (:func:`_read_ahead`; in the caller's thread when ``ahead`` is False). With ``prepare`` (a function of a McapMessage, e.g. a packet
        parser), ``(item, prepare(item))`` pairs, ``prepare`` run in that thread too (a
        LidarScanError it raises is given in place of its value; None for a BadMessage)."""
        if self.bag is not None and progress is not None:
            progress.total = max(self.bag.message_count, 1)
        source = self.bag.messages if self.bag is not None else \
            functools.partial(_mcap_items, self.path)
        entries = functools.partial(_prepared, source, prepare, self.bag is None)
        count = 0
        for item, position, value in _read_ahead(entries) if self.ahead else entries():
            count += 1
            if progress is not None:
                progress.update(position if self.bag is None else count, f"{count} msgs")
            yield item if prepare is None else (item, value)
        if progress is not None:
            progress.update(progress.total, "done", force=True)


def _mcap_items(path: Path) -> Iterator[tuple[Any, int]]:
    """(message or damaged part, file position after it) of an MCAP file."""
    from lidarscan.mcap import read_messages

    with open(path, "rb") as stream:
        for item in read_messages(stream):
            yield item, stream.tell()


def _prepared(source: Callable[[], Iterator[Any]], prepare: Callable[[Any], Any] | None,
              positioned: bool) -> Iterator[tuple[Any, int, Any]]:
    """(item, file position (``positioned``: the source gives (item, position) pairs) or 0,
    ``prepare(item)`` or the LidarScanError it raised or None)."""
    from lidarscan.errors import LidarScanError
    from lidarscan.mcap import McapMessage

    for entry in source():
        item, position = entry if positioned else (entry, 0)
        value = None
        if prepare is not None and isinstance(item, McapMessage):
            try:
                value = prepare(item)
            except LidarScanError as err:
                value = err
        yield item, position, value


#: messages read ahead of the one being converted (a few MB: bounded memory)
READ_AHEAD = 4


def _read_ahead(make: Callable[[], Iterator[Any]], depth: int = READ_AHEAD) -> Iterator[Any]:
    """The items of the iterator ``make()``, made by a background thread at most ``depth``
    ahead of the caller: the reading (sqlite3 steps, zstd decompression: they release the GIL)
    overlaps the caller's work. The iterator is made, run and closed in that thread (an sqlite3
    connection stays in the thread that opened it); an error it raises is raised here, after
    the items before it. Leaving early (an error, Ctrl-C, ``close()``) stops the thread and
    waits for it (its iterator is closed there)."""
    import queue
    import threading

    items: queue.Queue[tuple[Any, BaseException | None]] = queue.Queue(maxsize=depth)
    stop = threading.Event()
    end = object()

    def put(entry: tuple[Any, BaseException | None]) -> bool:
        while not stop.is_set():
            try:
                items.put(entry, timeout=0.05)
                return True
            except queue.Full:
                continue
        return False

    def run() -> None:
        try:
            source = make()
            try:
                for item in source:
                    if not put((item, None)):
                        return
            finally:
                close = getattr(source, "close", None)
                if close is not None:
                    close()
        except BaseException as err:  # noqa: BLE001 - raised in the caller's thread
            put((end, err))
            return
        put((end, None))

    thread = threading.Thread(target=run, name="read-ahead", daemon=True)
    thread.start()
    try:
        while True:
            item, err = items.get()
            if err is not None:
                raise err
            if item is end:
                return
            yield item
    finally:
        stop.set()
        thread.join()


def _open_input(name: str, role: str, *, ouster: bool = False) -> _Input:
    """Check what ``name`` is before anything is written (exit 2 with the reason otherwise)."""
    from converters.sources.bags import InputKind, detect_input, open_bag
    from lidarscan.errors import McapFormatError

    path = Path(name)
    if ouster and path.suffix.lower() in (".pcap", ".osf") and path.is_file():
        return _Input(path, InputKind("ouster", "an Ouster recording"))
    kind = detect_input(path)
    if kind.kind == "missing":
        raise FileNotFoundError(f"{role} {path}: no such file or directory")
    if kind.kind == "mcap":
        return _Input(path, kind)
    if kind.is_bag:
        return _Input(path, kind, open_bag(path))
    raise McapFormatError(f"{role} {path}", kind.description,
                          "an MCAP file, a rosbag2 directory or a rosbag2 .db3 file"
                          + (" (or an Ouster .pcap/.osf)" if ouster else ""))


def _describe_bad(item: Any) -> str:
    """One line for a BadMessage: a message, or a damaged part of the input."""
    if item.index < 0:
        return f"damaged input: {item.reason}"
    return (f"bad message #{item.index} topic '{item.topic}' stamp "
            f"{_fmt_stamp(item.log_time_ns)}: {item.reason}")


def _file_topics(path: Path) -> dict[str, str]:
    """topic -> type from the file's summary, or from a quick pass when it has none."""
    from lidarscan.mcap import BadMessage, read_messages

    try:
        from mcap.reader import make_reader

        with open(path, "rb") as stream:
            summary = make_reader(stream).get_summary()
        if summary is not None and summary.channels:
            return {c.topic: summary.schemas[c.schema_id].name
                    for c in summary.channels.values() if c.schema_id in summary.schemas}
    except Exception:  # noqa: BLE001, S110 - damaged summary: fall back to streaming
        pass
    out: dict[str, str] = {}
    for item in read_messages(path):
        if not isinstance(item, BadMessage):
            out.setdefault(item.topic, item.msgtype)
    return out
