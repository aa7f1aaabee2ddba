"""Ouster lidar packets -> one LidarScan + LidarInfo per frame (exact, vectorised).

The packet layouts are in :mod:`converters.sources.ouster.packet_format`. The scan is the one
:func:`converters.ouster.scan_from_frame` makes from ouster-sdk's ``LidarFrame`` of the same
packets (channels, dtypes, ``column_time_offsets``, stamp; the LidarInfo of
:func:`converters.ouster.info_from_metadata`): the decoder fills that frame itself.

Conventions
-----------
* Frames: packets are gathered by frame id. A frame is emitted when every column of the column
  window has arrived, when a packet of another frame id arrives, or at :meth:`PacketDecoder.
  flush`. A packet of the frame just emitted (late, reordered) is dropped and counted, never
  opens a second frame of that id; frames are never merged or shifted.
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

from collections.abc import Iterable, Iterator
from typing import Any

import numpy as np

import converters.ouster as _meta
from converters._packets import payload_bytes
from converters.sources.ouster.packet_format import PacketLayout, layout_from_metadata
from lidarscan.errors import DecodeError, InfoMismatchError, LidarScanError

__all__ = ["PacketDecoder", "decode_packets"]

_WORD = {1: "u1", 2: "<u2", 4: "<u4"}


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
        self.range_encoding = range_encoding
        self.destagger = destagger
        self.as_dataclass = as_dataclass
        lay = self.layout
        self._size = lay.packet_bytes
        self._window = lay.window_mask()
        self._expected = int(self._window.sum())
        self._mid_at = lay.header_bytes + 8 + np.arange(lay.columns_per_packet) * lay.column_bytes
        self._rows: list[np.ndarray[Any, Any]] = []    # packets of the frame being gathered
        self._frame: int | None = None
        self._last: int | None = None                  # frame id last emitted
        self._seen = np.zeros(lay.width, bool)
        self._count = 0
        self.stats = {"packets": 0, "frames": 0, "late_packets": 0, "missing_columns": 0,
                      "invalid_columns": 0}

    # ------------------------------------------------------------------------ packet intake
    def push(self, stamp_ns: int, packet: Any) -> list[tuple[Any, Any]]:
        """Add one lidar packet (UDP payload); returns the frames it completed (0, 1 or 2).

        Raises:
            DecodeError: a payload that is not this sensor's lidar packet size (the decoder
                stays usable).
            InfoMismatchError: a packet of another sensor (init_id / serial number).
        """
        data = packet if type(packet) is bytes else payload_bytes(packet)
        if len(data) != self._size:
            raise DecodeError("ouster lidar packet size", len(data),
                              f"{self._size} bytes ({self.layout.profile}, "
                              f"{self.layout.columns_per_packet} columns of "
                              f"{self.layout.height} pixels)")
        frame, init_id, serial = self.layout.header(data)
        self._check_sensor(init_id, serial)
        return self._accept(frame, np.frombuffer(data, np.uint8))

    def push_many(self, stamps_ns: Any, payloads: Any,
                  errors: list[tuple[int, LidarScanError]] | None = None
                  ) -> list[tuple[Any, Any]]:
        """Add N lidar packets at once: the results of push() one by one.

        Args:
            stamps_ns: (N,) integer ns (not used: the packets carry their times).
            payloads: (N, packet size) uint8, one packet per row. Never modified.
            errors: with a list, a row of another size is recorded as (row, DecodeError) and
                skipped instead of raising (the contract of the other packet decoders).

        Raises:
            DecodeError: wrong array shape/dtype.
            InfoMismatchError: a packet of another sensor (after the frames before it).
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
        out: list[tuple[Any, Any]] = []
        for i in range(rows.shape[0]):
            self._check_sensor(int(inits[i]), int(serials[i]))
            out += self._accept(int(frames[i]), rows[i])
        return out

    def flush(self) -> list[tuple[Any, Any]]:
        """The frame being gathered (complete or not), if any; the decoder is then empty."""
        out = self._emit() if self._rows else []
        self._last = None
        return out

    # ------------------------------------------------------------------------------ frames
    def _check_sensor(self, init_id: int, serial: int) -> None:
        lay = self.layout
        if lay.legacy:
            return
        if (lay.init_id and init_id != lay.init_id) or (lay.serial and serial != lay.serial):
            raise InfoMismatchError(
                "ouster packet sensor", f"init_id {init_id}, serial {serial}",
                f"init_id {lay.init_id}, serial {lay.serial} of the metadata (a packet of "
                "another sensor, or of a re-initialised sensor: use its metadata)")

    def _accept(self, frame: int, row: np.ndarray[Any, Any]) -> list[tuple[Any, Any]]:
        self.stats["packets"] += 1
        out: list[tuple[Any, Any]] = []
        if frame != self._frame:
            if frame == self._last and not self._rows:
                self.stats["late_packets"] += 1
                return out
            if self._rows:
                out = self._emit()
                if frame == self._last:                   # late packet of the frame just out
                    self.stats["late_packets"] += 1
                    return out
            self._frame = frame
        self._rows.append(row)
        mids = row[self._mid_at].astype(np.int64) | (row[self._mid_at + 1].astype(np.int64) << 8)
        mids = mids[mids < self.layout.width]
        new = mids[~self._seen[mids]]
        self._seen[new] = True
        self._count += int(np.count_nonzero(self._window[new]))
        if self._count >= self._expected:
            out += self._emit()
        return out

    def _emit(self) -> list[tuple[Any, Any]]:
        rows = self._rows
        self._rows, self._last, self._frame = [], self._frame, None
        self._seen[:] = False
        self._count = 0
        frame = frame_arrays(self.layout, np.stack(rows) if len(rows) > 1 else rows[0][None])
        self.stats["frames"] += 1
        self.stats["invalid_columns"] += frame.pop("invalid_columns")
        received = frame.pop("received")
        self.stats["missing_columns"] += int(np.count_nonzero(self._window & ~received))
        if not (frame["status"] & 1).any():
            return []                       # no valid column: nothing to make a scan of
        scan = _meta.scan_from_frame(frame, self.info, range_encoding=self.range_encoding,
                                     destagger=self.destagger, as_dataclass=self.as_dataclass)
        return [(scan, self.info)]


def frame_arrays(layout: PacketLayout, rows: np.ndarray[Any, Any]) -> dict[str, Any]:
    """The ouster-sdk style frame of N packets of one frame (rows (N, packet size) uint8).

    Returns:
        dict: the profile's staggered images (H, W) (``range_mm`` uint32 mm, ``signal``,
        ``reflectivity``, ...; :data:`~converters.sources.ouster.packet_format.FIELDS`),
        ``timestamps_ns`` (W,) uint64, ``measurement_id`` (W,) uint16, ``status`` (W,)
        uint32, ``frame_id``, ``invalid_columns`` (columns received with status not valid or
        a measurement id >= W) and ``received`` (W,) bool (columns in some packet). Columns
        not received valid are 0 everywhere.
    """
    h, w, cpp, csize = layout.height, layout.width, layout.columns_per_packet, layout.column_bytes
    n = rows.shape[0]
    body = rows[:, layout.header_bytes:layout.header_bytes + cpp * csize]
    cols = body.reshape(n * cpp, csize)
    mids = cols[:, 8:10].view("<u2")[:, 0]
    st = layout.status_offset
    status = cols[:, st:st + 4].view("<u4")[:, 0] if layout.legacy else \
        cols[:, st:st + 2].view("<u2")[:, 0]
    inside = mids < w
    ok = ((status & 1) != 0) & inside
    invalid = int(np.count_nonzero(~ok))
    received = np.zeros(w, bool)
    received[mids[inside]] = True
    times = cols[:, 0:8].view("<u8")[:, 0]
    out: dict[str, Any] = {}
    hdr = layout.column_header_bytes
    pix = cols[:, hdr:hdr + h * layout.pixel_bytes].reshape(n * cpp, h, layout.pixel_bytes)
    everything = bool(ok.all()) and n * cpp == w and bool((mids == np.arange(w)).all())
    if not everything:
        pix = pix[ok]
        where = mids[ok]
    for f in layout.fields:
        raw = pix[:, :, f.offset:f.offset + f.src].view(_WORD[f.src])[:, :, 0]
        if f.mask:
            raw = raw & f.mask
        if f.shift > 0:
            raw = raw >> f.shift
        values = raw.astype(f.dtype)
        if f.shift < 0:
            values <<= -f.shift
        if everything:
            out[f.key] = np.ascontiguousarray(values.T)
        else:
            image = np.zeros((h, w), f.dtype)
            image[:, where] = values.T
            out[f.key] = image
    if everything:
        out["timestamps_ns"] = times.astype(np.uint64)
        out["measurement_id"] = mids.astype(np.uint16)
        out["status"] = status.astype(np.uint32)
    else:
        for key, values, dtype in (("timestamps_ns", times, np.uint64),
                                   ("measurement_id", mids, np.uint16),
                                   ("status", status, np.uint32)):
            column = np.zeros(w, dtype)
            column[where] = values[ok]
            out[key] = column
    out["frame_id"] = layout.header(rows[0])[0]
    out["invalid_columns"] = invalid
    out["received"] = received
    return out


def decode_packets(packets: Iterable[tuple[int, Any]], metadata: Any = None, **kw: Any
                   ) -> Iterator[tuple[Any, Any]]:
    """Decode an iterable of (stamp_ns, lidar packet), then flush(): (LidarScan, LidarInfo)
    per frame, as :class:`PacketDecoder` with ``metadata`` and ``kw``."""
    decoder = PacketDecoder(metadata, **kw)
    for stamp, packet in packets:
        yield from decoder.push(stamp, packet)
    yield from decoder.flush()
