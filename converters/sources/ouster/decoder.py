"""Ouster lidar packets -> one LidarScan + LidarInfo per frame (exact, vectorised).

The packet layouts are in :mod:`converters.sources.ouster.packet_format`. The scan is the one
:func:`converters.ouster.scan_from_frame` makes from ouster-sdk's ``LidarFrame`` of the same
packets (channels, dtypes, ``column_time_offsets``, stamp; the LidarInfo of
:func:`converters.ouster.info_from_metadata`): the decoder fills that frame itself.

Conventions
-----------
* Frames: packets are gathered by frame id. A frame is emitted when every column of the column
  window has arrived, when a packet of another frame id arrives, or at :meth:`PacketDecoder.
  flush`. A packet of one of the last 8 frames emitted (late, reordered) is dropped and
  counted, never opens a second frame of that id; frames are never merged or shifted.
* Columns: measurement id = column. A column whose status bit 0 is clear (invalid), or that
  never arrived (missing packet), is left as ouster-sdk leaves it: every field 0, timestamp 0,
  status 0, so the scan has no return there and its time is interpolated
  (:func:`converters.ouster.scan_from_frame`). Both are counted (``stats``).
* Sensor: a packet whose init_id or serial number differs from the metadata's (when the
  metadata gives them) raises :class:`~lidarscan.errors.InfoMismatchError` naming both: it is
  another sensor's, or the sensor was re-initialised with another configuration.
* Time: int64 ns on the sensor clock (the column timestamps); the scan's stamp is the time of
  column 0. The stamps given to push() (receive times) are not used.
"""

from __future__ import annotations

import collections
from collections.abc import Iterable, Iterator
from typing import Any

import numpy as np

import converters.sources.ouster.metadata as _meta
from converters.sources.ouster.packet_format import PacketLayout, layout_from_metadata
from converters.sources.packets import payload_bytes
from lidarscan.errors import DecodeError, InfoMismatchError, LidarScanError, ValidationError

__all__ = ["PacketDecoder", "decode_packets"]

#: frame ids remembered as emitted: a late packet of one of them is dropped
_RECENT = 8

_WORD = {1: "u1", 2: "<u2", 4: "<u4", 8: "<u8"}


class PacketDecoder:
    """Raw Ouster lidar packets (UDP payloads) -> (LidarScan, LidarInfo) per frame.

    Args:
        metadata: the sensor's metadata JSON (path, text or dict; flat firmware-2.x or nested
            layout). Required: it holds the packet profile, sizes and the geometry.
        frame_id: header.frame_id of scans and info; default "os_sensor" ("os_lidar" with
            ``use_lidar_to_sensor`` false), as :func:`converters.ouster.info_from_metadata`.
        use_lidar_to_sensor, range_encoding, destagger, as_dataclass: as in
            :func:`converters.ouster.info_from_metadata` / :func:`converters.ouster.
            scan_from_frame` (range float32 metres by default; "uint32_mm" keeps millimetres).

    Attributes:
        info: the LidarInfo (one version for the whole stream).
        layout: the :class:`~converters.sources.ouster.packet_format.PacketLayout`.
        stats: counters: ``packets``, ``frames``, ``late_packets`` (dropped), ``missing_columns``
            (window columns that never arrived), ``invalid_columns`` (status not valid).
    """

    def __init__(self, metadata: Any = None, *, frame_id: str | None = None,
                 use_lidar_to_sensor: bool = True, range_encoding: str = "float32",
                 destagger: bool = False, as_dataclass: bool = False) -> None:
        if metadata is None:
            from lidarscan.errors import ConfigError
            raise ConfigError("metadata", None, "the sensor's metadata JSON (ouster-ros "
                              "/ouster/metadata, or the .json saved next to a pcap)")
        data, text = _meta.load_metadata(metadata)
        self.layout: PacketLayout = layout_from_metadata(data)
        self.info = _meta.info_from_metadata(text, frame_id=frame_id,
                                             use_lidar_to_sensor=use_lidar_to_sensor,
                                             as_dataclass=as_dataclass)
        if range_encoding not in ("float32", "uint32_mm"):
            raise ValidationError("range_encoding", range_encoding, '"float32" or "uint32_mm"')
        self.range_encoding = range_encoding
        self.destagger = destagger
        self.as_dataclass = as_dataclass
        lay = self.layout
        self._size = lay.packet_bytes
        self._window = lay.window_mask()
        self._expected = int(self._window.sum())
        # packets of a complete frame: those holding a window column (whole packets)
        self._full = -(-self._expected // lay.columns_per_packet)
        self._buf = np.empty((0, self._size), np.uint8)     # packets of the frame gathered
        self._mids = self._buf[:, :0]
        self._n = 0
        self._frame: int | None = None
        self._done: collections.deque[int] = collections.deque(maxlen=_RECENT)
        self.stats = {"packets": 0, "frames": 0, "late_packets": 0, "missing_columns": 0,
                      "invalid_columns": 0}
        self._scratch: dict[str, np.ndarray[Any, Any]] = {}    # reused by _scan per frame

    # ------------------------------------------------------------------------ packet intake
    def push(self, stamp_ns: int, packet: Any) -> list[tuple[Any, Any]]:
        """Add one lidar packet (UDP payload); returns the frames it completed (0, 1 or 2).

        Raises:
            DecodeError: a payload that is not this sensor's lidar packet size (the decoder
                stays usable).
            InfoMismatchError: a packet of another sensor (init_id / serial number).
        """
        # a view of the caller's buffer, only read: copied once, into the frame
        if isinstance(packet, np.ndarray) and packet.ndim == 1 and packet.dtype == np.uint8:
            row = packet
        elif isinstance(packet, (bytes, bytearray, memoryview)):
            row = np.frombuffer(packet, np.uint8)
        else:
            row = np.frombuffer(payload_bytes(packet), np.uint8)    # DecodeError: bad type
        if row.size != self._size:
            raise DecodeError("ouster lidar packet size", row.size,
                              f"{self._size} bytes ({self.layout.profile}, "
                              f"{self.layout.columns_per_packet} columns of "
                              f"{self.layout.height} pixels)")
        frame, init_id, serial = self.layout.header(row)
        self._check_sensor(init_id, serial)
        return self._accept(frame, row[None])

    def push_many(self, stamps_ns: Any, payloads: Any,
                  errors: list[tuple[int, LidarScanError]] | None = None
                  ) -> list[tuple[Any, Any]]:
        """Add N lidar packets at once: the results of push() one by one.

        Args:
            stamps_ns: (N,) integer ns (not used: the packets carry their times).
            payloads: (N, packet size) uint8, one packet per row. Never modified.
            errors: with a list, rows of another size or of another sensor are recorded as
                (row, error) and skipped instead of raising (the contract of the other packet
                decoders).

        Raises:
            DecodeError: wrong array shape/dtype.
            InfoMismatchError: a packet of another sensor (without ``errors``; the frames
                completed before it are lost to the caller: use ``errors`` to keep them).
        """
        rows = payloads
        if not isinstance(rows, np.ndarray) or rows.dtype != np.uint8 or rows.ndim != 2:
            raise DecodeError("payloads", f"{getattr(rows, 'dtype', type(rows).__name__)} "
                              f"{getattr(rows, 'shape', '')}", "an (N, size) uint8 ndarray")
        if rows.shape[1] != self._size:
            err = DecodeError("ouster lidar packet size", rows.shape[1],
                              f"{self._size} bytes ({self.layout.profile})")
            if errors is None:
                raise err
            errors.extend((i, err) for i in range(rows.shape[0]))
            return []
        frames, inits, serials = self.layout.headers(rows)
        foreign = _foreign(self.layout, inits, serials)
        # runs of consecutive packets of one frame id (and one sensor) go in together
        cuts = np.flatnonzero((np.diff(frames) != 0) | foreign[1:] | foreign[:-1]) + 1
        out: list[tuple[Any, Any]] = []
        for start, stop in zip([0, *cuts.tolist()], [*cuts.tolist(), rows.shape[0]]):
            if foreign[start]:
                try:
                    self._check_sensor(int(inits[start]), int(serials[start]))
                except InfoMismatchError as mismatch:
                    if errors is None:
                        raise
                    errors.append((start, mismatch))
                continue
            out += self._accept(int(frames[start]), rows[start:stop])
        return out

    def flush(self) -> list[tuple[Any, Any]]:
        """The frame being gathered (complete or not), if any; the decoder is then empty."""
        out = self._emit() if self._n else []
        self._done.clear()
        return out

    # ------------------------------------------------------------------------------ frames
    def _check_sensor(self, init_id: int, serial: int) -> None:
        lay = self.layout
        if lay.legacy:                  # no sensor ids in LEGACY packets (per packet: no array)
            return
        if _foreign(lay, init_id, serial):
            raise InfoMismatchError(
                "ouster packet sensor", f"init_id {init_id}, serial {serial}",
                f"init_id {lay.init_id}, serial {lay.serial} of the metadata (a packet of "
                "another sensor, or of a re-initialised sensor: use its metadata)")

    def _accept(self, frame: int, rows: np.ndarray[Any, Any]) -> list[tuple[Any, Any]]:
        """Packets ``rows`` (k, size), all of frame id ``frame``, in arrival order: the same as
        one by one (a frame completed by one of them is emitted there, the rest of the run is
        then late)."""
        self.stats["packets"] += rows.shape[0]
        out: list[tuple[Any, Any]] = []
        if frame != self._frame:
            if self._n:
                out = self._emit()
            if frame in self._done:                   # late packets of a frame already out
                self.stats["late_packets"] += rows.shape[0]
                return out
            self._frame = frame
        at = 0
        while at < rows.shape[0]:
            take = min(max(self._full - self._n, 1), rows.shape[0] - at)
            if self._n + take > self._buf.shape[0]:
                self._grow(self._n + take)
            self._buf[self._n:self._n + take] = rows[at:at + take]
            self._n += take
            at += take
            if self._n >= self._full and self._complete():
                out += self._emit()
                self.stats["late_packets"] += rows.shape[0] - at
                break
        return out

    def _grow(self, need: int) -> None:
        lay = self.layout
        cap = max(2 * self._buf.shape[0], self._full + 2, need)
        buf = np.empty((cap, self._size), np.uint8)
        buf[:self._n] = self._buf[:self._n]
        self._buf = buf
        self._mids = np.ndarray((cap, lay.columns_per_packet), "<u2", buf,
                                lay.header_bytes + 8, (self._size, lay.column_bytes))

    def _complete(self) -> bool:
        """Whether every column of the window has arrived."""
        mids = self._mids[:self._n].reshape(-1)
        seen = np.zeros(self.layout.width + 1, bool)
        seen[np.minimum(mids, self.layout.width)] = True
        return bool(seen[:-1][self._window].all())

    def _emit(self) -> list[tuple[Any, Any]]:
        rows = self._buf[:self._n]
        self._done.append(self._frame)
        self._frame, self._n = None, 0
        self.stats["frames"] += 1
        cols = _Columns(self.layout, rows)
        self.stats["invalid_columns"] += cols.invalid
        self.stats["missing_columns"] += int(np.count_nonzero(self._window & ~cols.received))
        if not (cols.times[cols.valid] != 0).any():
            return []                       # no valid, timed column: nothing to make a scan of
        if self.destagger:
            scan = _meta.scan_from_frame(frame_arrays(self.layout, rows, cols), self.info,
                                         range_encoding=self.range_encoding, destagger=True,
                                         as_dataclass=self.as_dataclass)
        else:
            scan = _scan(self.layout, cols, self.info, self.range_encoding, self.as_dataclass,
                         self._scratch)
        return [(scan, self.info)]


def _foreign(layout: PacketLayout, init_ids: Any, serials: Any) -> Any:
    """Whether packets are another sensor's: an init_id or serial number (ints, or (N,) int
    arrays: then an (N,) bool array) other than the metadata's, where the metadata gives one
    (non-zero). LEGACY packets carry neither: never foreign."""
    if layout.legacy:
        return np.zeros(np.shape(init_ids), bool)
    return (((init_ids != layout.init_id) & (layout.init_id != 0))
            | ((serials != layout.serial) & (layout.serial != 0)))


#: frame key -> LidarScan channel name, in the order of converters.ouster.scan_from_frame
_CHANNEL_OF = {"range_mm": "range", "signal": "intensity", "reflectivity": "reflectivity",
               "near_ir": "ambient", "flags": "flags", "range2_mm": "range2",
               "signal2": "intensity2", "reflectivity2": "reflectivity2", "flags2": "flags2"}


class _Columns:
    """The measurement columns of N packets of one frame, put in column order.

    Attributes:
        data: (P, C, column bytes) uint8 with P * C = W: column c's bytes at [c // C, c % C]
            (a strided view of the packets, P packets of C columns, when they hold columns
            0..W-1 in order; else the columns gathered, P = W, C = 1; the rows of columns not
            received valid hold arbitrary bytes).
        valid: (W,) bool, the columns received with a valid status.
        times: (W,) uint64 ns, their column timestamps (0 elsewhere).
        received: (W,) bool, the columns in some packet.
        invalid: columns received whose status is not valid (or measurement id >= W).
    """

    def __init__(self, layout: PacketLayout, rows: np.ndarray[Any, Any]) -> None:
        w, cpp, csize = layout.width, layout.columns_per_packet, layout.column_bytes
        cols = np.lib.stride_tricks.as_strided(
            rows[:, layout.header_bytes:], (rows.shape[0], cpp, csize),
            (rows.strides[0], csize, 1), writeable=False)
        mids = _word(cols, 8, 2)
        status = _word(cols, layout.status_offset, 4 if layout.legacy else 2)
        inside = mids < w
        ok = ((status & 1) != 0) & inside
        self.invalid = int(np.count_nonzero(~ok))
        self.received = np.zeros(w, bool)
        self.received[mids[inside]] = True
        self.valid = np.zeros(w, bool)
        self.valid[mids[ok]] = True
        self.times = np.zeros(w, np.uint64)
        self.times[mids[ok]] = _word(cols, 0, 8)[ok]
        if mids.size == w and bool(ok.all()) and bool((mids == np.arange(w)).all()):
            self.data = cols
        else:
            source = np.zeros(w, np.int64)
            source[mids[ok]] = np.flatnonzero(ok)      # the last valid copy of each column
            self.data = cols.reshape(-1, csize)[source][:, None, :]


def _word(cols: np.ndarray[Any, Any], at: int, size: int) -> np.ndarray[Any, Any]:
    """The little-endian unsigned word of ``size`` bytes at byte ``at`` of every column of
    ``cols`` ((..., column bytes) uint8), flattened to (columns,)."""
    return np.ascontiguousarray(cols[..., at:at + size]).view(_WORD[size]).reshape(-1)


def _scan(layout: PacketLayout, cols: _Columns, info: Any, range_encoding: str,
          as_dataclass: bool, scratch: dict[str, np.ndarray[Any, Any]]) -> Any:
    """The LidarScan of :func:`converters.ouster.scan_from_frame` (staggered) written straight
    into the scan's data block: per field one pass that reads the packet bytes and writes the
    (H, W) image (the tests check both give the same scan). ``scratch``: the caller's reused
    (H, W) integer images of the ranges converted to float32 metres."""
    from lidarscan.scan import ScanBuffer

    h, w = layout.height, layout.width
    hdr, pix = layout.column_header_bytes, layout.pixel_bytes
    packets, per = cols.data.shape[:2]
    pixels = cols.data[:, :, hdr:hdr + h * pix].reshape(packets, per, h, pix)
    floats = range_encoding == "float32"
    specs = {_CHANNEL_OF[f.key]: (np.float32 if floats and f.key.startswith("range")
                                  else np.dtype(f.dtype)) for f in layout.fields}
    order = [name for name in _CHANNEL_OF.values() if name in specs]
    buffer = ScanBuffer(info, {name: specs[name] for name in order}, as_dataclass=as_dataclass,
                        zeroed=False)
    gaps = ~cols.valid
    for f in layout.fields:
        name = _CHANNEL_OF[f.key]
        # (H, P, C) word view of the packet bytes -> the (H, W) image seen as (H, P, C)
        source = pixels[..., f.offset:f.offset + f.src].view(_WORD[f.src])[..., 0]
        source = source.transpose(2, 0, 1)
        view = buffer.views[name]
        target = view
        if view.dtype != np.dtype(f.dtype):                 # range in float32 metres
            if f.dtype not in scratch:
                scratch[f.dtype] = np.empty((h, w), f.dtype)
            target = scratch[f.dtype]
        shaped = target.reshape(h, packets, per)
        if f.mask:
            np.bitwise_and(source, f.mask, out=shaped, casting="unsafe")
        else:
            np.copyto(shaped, source, casting="unsafe")
        if f.shift > 0:
            np.right_shift(target, f.shift, out=target)
        elif f.shift < 0:
            np.left_shift(target, -f.shift, out=target)
        if gaps.any():
            target[:, gaps] = 0
        if target is not view:
            np.multiply(target, _meta._RANGE_MULTIPLIER, out=view, dtype=np.float64,
                        casting="unsafe")
            np.copyto(view, np.inf, where=view == 0)
    full = _meta._column_times({"timestamps_ns": cols.times}, w, cols.valid,
                               int(info.column_time_increment))
    if full is None:                                   # the caller checks there is one
        raise ValidationError("stamp_ns", None, "a valid column with a timestamp")
    return buffer.build(int(full[0]), column_time_offsets=full - full[0])


def frame_arrays(layout: PacketLayout, rows: np.ndarray[Any, Any],
                 cols: _Columns | None = None) -> dict[str, Any]:
    """The ouster-sdk style frame of N packets of one frame (rows (N, packet size) uint8): the
    readable numpy reference of the decoder (:func:`converters.ouster.scan_from_frame` of it
    is the scan the decoder makes). ``cols``: the rows' columns when the caller has them.

    Returns:
        dict: the profile's staggered images (H, W) (``range_mm`` uint32 mm, ``signal``,
        ``reflectivity``, ...; :data:`~converters.sources.ouster.packet_format.FIELDS`),
        ``timestamps_ns`` (W,) uint64, ``measurement_id`` (W,) uint16, ``status`` (W,)
        uint32 and ``frame_id``. Columns not received valid are 0 everywhere, as ouster-sdk
        leaves them.
    """
    h, w = layout.height, layout.width
    cols = _Columns(layout, rows) if cols is None else cols
    data = cols.data.reshape(w, -1)
    hdr, pix = layout.column_header_bytes, layout.pixel_bytes
    pixels = data[:, hdr:hdr + h * pix].reshape(w, h, pix)
    out: dict[str, Any] = {}
    for f in layout.fields:
        raw = np.ascontiguousarray(pixels[:, :, f.offset:f.offset + f.src])
        value = raw.view(_WORD[f.src])[:, :, 0].astype(np.uint64)
        if f.mask:
            value &= np.uint64(f.mask)
        value = value >> np.uint64(f.shift) if f.shift >= 0 else value << np.uint64(-f.shift)
        value[~cols.valid] = 0
        out[f.key] = value.T.astype(f.dtype)
    valid = cols.valid
    out["timestamps_ns"] = cols.times
    out["measurement_id"] = np.where(valid, np.arange(w), 0).astype(np.uint16)
    status = _word(cols.data, layout.status_offset, 4 if layout.legacy else 2)
    out["status"] = np.where(valid, status, 0).astype(np.uint32)
    out["frame_id"] = layout.header(rows[0])[0]
    return out


#: packets handed to push_many at once by decode_packets
_RUN = 256


def decode_packets(packets: Iterable[tuple[int, Any]], metadata: Any = None, **kw: Any
                   ) -> Iterator[tuple[Any, Any]]:
    """Decode an iterable of (stamp_ns, lidar packet), then flush(): (LidarScan, LidarInfo)
    per frame, as :class:`PacketDecoder` with ``metadata`` and ``kw`` (the results of push()
    one by one; runs of up to 256 packets go through push_many).

    Raises:
        DecodeError: a packet of another size (after the frames completed before it).
        InfoMismatchError: a packet of another sensor (likewise: a run is pushed up to it).
    """
    decoder = PacketDecoder(metadata, **kw)
    size = decoder.layout.packet_bytes
    run: list[Any] = []
    for _, packet in packets:
        if len(packet) != size:
            if run:
                yield from _push_run(decoder, run)
            yield from decoder.push(0, packet)         # raises the size error
        run.append(packet)
        if len(run) == _RUN:
            yield from _push_run(decoder, run)
    if run:
        yield from _push_run(decoder, run)
    yield from decoder.flush()


def _push_run(decoder: PacketDecoder, run: list[Any]) -> Iterator[tuple[Any, Any]]:
    """push_many of the packets ``run`` (emptied) up to the first of another sensor, whose
    push() then raises: the frames completed before it are yielded, as one by one."""
    rows = np.frombuffer(b"".join(run), np.uint8).reshape(len(run), -1)
    del run[:]
    _, inits, serials = decoder.layout.headers(rows)
    foreign = np.flatnonzero(_foreign(decoder.layout, inits, serials))
    stop = int(foreign[0]) if foreign.size else rows.shape[0]
    yield from decoder.push_many(np.zeros(stop, np.int64), rows[:stop])
    if stop < rows.shape[0]:
        decoder.push(0, rows[stop])                   # raises InfoMismatchError
