"""Velodyne packets -> one (LidarScan, LidarInfo) per rotation (the packet decoder contract).

:class:`PacketDecoder` buffers packets, cuts rotations, measures times, rates and the scan
width, and versions the LidarInfo; the pixels come from :mod:`converters.sources.velodyne.packets`.
Conventions: see :mod:`converters.sources.velodyne`.
"""

from __future__ import annotations

import itertools
import math
import operator
from collections.abc import Iterable, Iterator, Mapping
from typing import Any

import numpy as np

from converters._kernels import select
from converters.sources.packets import payload_bytes
from converters.sources.velodyne.calibration import info_from_calibration, load_calibration
from converters.sources.velodyne.packets import (
    _AZIMUTHS,
    _RETURN_MODES,
    MODELS,
    PACKET_SIZE,
    VelodyneModel,
    _fill_views,
    _flag_names,
    _flags,
    _Layout,
    _Table,
    _Tables,
    _layout,
    _nebula_rotation,
    _tables,
    _words_at,
)
from lidarscan.errors import ConfigError, DecodeError, LidarScanError, ValidationError
from lidarscan.scan import ScanBuffer

_HOUR_NS = 3_600_000_000_000
_JUMP_CENTIDEG = 500.0      # an azimuth step this large between two firings is a gap (FOV)
_RATE_CHANGE = 0.01         # a rotation rate this much off the info's makes a new version
_RATE_COLUMNS = 100         # ... when measured over at least this many columns
_AZIMUTH_MODELS = ("nebula", "manual")
_KEY_WORD = np.array([602])   # bytes 1204 (return mode) and 1205 (product) as one u16 word


class PacketDecoder:
    """Velodyne packets -> one (LidarScan, LidarInfo) per rotation (the packet decoder contract).

    Args:
        calibration: ros-drivers style calibration YAML path or mapping; None -> the model's
            nominal public calibration (VLP-16, Puck LITE, Puck Hi-Res, HDL-32E, VLP-32C) or a
            :class:`~lidarscan.errors.ConfigError` naming the file the model needs.
        frame_id: header.frame_id of scans and infos.
        cut_angle_deg: packet azimuth (degrees, clockwise, the packets' own convention) where a
            rotation starts (Nebula's ``scan_phase``): a rotation is cut before the first firing
            sequence whose azimuth has passed it.
        time_source: "auto" (default), "sensor" or "receive". The packets' timestamp counts
            microseconds past the hour; "sensor" completes it with the hour of the recorded
            stamp (a GPS/PTP-synchronised sensor: absolute times), "receive" anchors the
            sensor's relative times at the recorded stamps (shifted so that no packet of the
            rotation is received before its own timestamp).
            "auto" uses "sensor" when the two agree within 1 s, else "receive".
        range_min, range_max: ``LidarInfo.range_min/max`` in metres (default 0 and the packet
            format's maximum, 65535 raw units: nothing is hidden).
        width_margin: relative slack of the scan width over the measured columns per
            revolution (default 0.02).
        azimuth_model: "nebula" (default): Nebula's points exactly, through the per-pixel
            ``azimuth`` channel(s) (module docstring, "Point geometry"); or "manual": no such
            channel, the manuals' firing times as per-beam offsets (physically the better
            timing on the real VLS-128 recording, ``converters.edge.evidence.velodyne_timing``).
        as_dataclass: return :mod:`lidarscan.types` dataclasses instead of rclpy messages.

    The C kernel (``converters._kernels.select("velodyne")``, switched off by
    ``LIDARSCAN_NO_KERNEL``) is chosen when the decoder is made.

    Width: W = ceil((1 + width_margin) * 2 pi / (omega * T)), omega the rotation rate and T the
    mean column period, both measured on the first rotation of an info version (a rotation
    whose rate differs by more than 1 % starts a new version). A shorter
    rotation is padded with no-return columns (their azimuths and times extrapolated at the
    measured rate); a rotation with more than W firings gets a new info version whose width
    fits it (again with the margin), so no firing is ever dropped.
    """

    def __init__(self, calibration: Any = None, *, frame_id: str = "lidar",
                 cut_angle_deg: float = 0.0, time_source: str = "auto",
                 range_min: float | None = None, range_max: float | None = None,
                 width_margin: float = 0.02, azimuth_model: str = "nebula",
                 as_dataclass: bool = False) -> None:
        if azimuth_model not in _AZIMUTH_MODELS:
            raise ConfigError("azimuth_model", azimuth_model, '"nebula" or "manual"')
        if time_source not in ("auto", "sensor", "receive"):
            raise ConfigError("time_source", time_source, '"auto", "sensor" or "receive"')
        if not (math.isfinite(float(cut_angle_deg))):
            raise ConfigError("cut_angle_deg", cut_angle_deg, "a finite angle in degrees")
        if not (0.0 <= float(width_margin) < 1.0):
            raise ConfigError("width_margin", width_margin, "a fraction in [0, 1)")
        self._calib = None if calibration is None else load_calibration(calibration)
        self._frame_id = frame_id
        self._cut = int(round(float(cut_angle_deg) * 100)) % 36000
        self._time_source = time_source
        self._range = (range_min, range_max)
        self._margin = float(width_margin)
        self._azimuth_model = azimuth_model
        self._as_dataclass = as_dataclass
        self._key: tuple[int, int] | None = None      # (product, mode) of the packets buffered
        self._model: VelodyneModel | None = None      # the stream's (its first valid packet's)
        self._layout: _Layout | None = None
        self._packets: list[Any] = []                  # payloads (bytes), (k, 1206) rows
        #                                                  or _Table (decode_packets)
        self._stamps: list[Any] = []                   # recorded stamps (ns): ints or arrays
        self._rows = 0                                  # packets buffered
        self._first_seq = 0                             # first sequence of _packets[0] to keep
        self._prev_rel = -1                             # phase-relative azimuth of the last firing
        self._info: Any = None
        self._info_key: tuple[Any, ...] | None = None
        self._omega = 0.0                               # rad/s of the current info version
        self._period = 0.0                              # ns, mean column period of the version
        self._order = np.zeros(0, np.int64)             # laser id of each row
        self._last_info_stamp: int | None = None
        self._tables: _Tables | None = None              # see _tables()
        self._offsets_key: tuple[Any, ...] | None = None
        self._rotation = np.zeros(0)                    # see _nebula_rotation
        self._rotations: dict[str, np.ndarray[Any, Any]] = {}   # ... per model name
        self._lib = select("velodyne").c                # the C kernel (LIDARSCAN_NO_KERNEL)

    # -------------------------------------------------------------------------------- public

    def push(self, stamp_ns: int, packet: Any) -> list[tuple[Any, Any]]:
        """Add one packet (1206-byte payload, never modified); return the rotations it completed.

        A packet of another return mode ends the current rotation (returned here); the info
        version changes only when the geometry does (single <-> dual, width, rotation rate).
        The stream's model is that of its first valid packet: one decoder per sensor (its
        calibration is that sensor's).

        Raises:
            DecodeError: malformed packet (size, block flags, azimuth, unknown product or
                return mode) or a packet of another model than the stream's; the packet is
                skipped (the rotation in progress goes on) and the decoder stays usable.
            ConfigError / ValidationError: the calibration does not fit the detected model.
        """
        data = packet if isinstance(packet, bytes) else payload_bytes(packet)
        key, layout = self._validate(data)
        out: list[tuple[Any, Any]] = []
        if key != self._key:                          # a valid packet of another mode
            out.extend(self.flush())
            self._key, self._layout, self._model = key, layout, layout.model
        cut = self._cut
        first, last = 2, layout.last_offset
        rel_first = ((data[first] | data[first + 1] << 8) - cut) % 36000
        rel_last = ((data[last] | data[last + 1] << 8) - cut) % 36000
        if rel_first >= self._prev_rel and rel_last >= rel_first:
            self._packets.append(data)                   # fast path: no cut in this packet
            self._stamps.append(int(stamp_ns))
            self._rows += 1
            self._prev_rel = rel_last
            return out
        out.extend(self._push_rows(np.array([int(stamp_ns)], np.int64),
                                   np.frombuffer(data, np.uint8).reshape(1, PACKET_SIZE)))
        return out

    def push_many(self, stamps_ns: Any, payloads: Any, *,
                  errors: list[tuple[int, LidarScanError]] | None = None
                  ) -> list[tuple[Any, Any]]:
        """Add N packets at once (the same as :meth:`push` of each, vectorised).

        Args:
            stamps_ns: (N,) integer recorded stamps, ns.
            payloads: (N, 1206) uint8 array, one payload per row, e.g. a zero-copy view of a
                VelodyneScan message's packet array. Read during the call, never modified; the
                packets of the unfinished rotation are copied (the caller may reuse the buffer),
                unless the array is a read-only view of ``bytes`` (then kept by reference).
            errors: None (default): if any packet is malformed, raise the DecodeError of the
                first one (the message :meth:`push` gives, with its row index) before anything
                is consumed. A list: malformed packets are skipped and ``(row, error)`` appended.

        Returns:
            The rotations completed by these packets, in order.

        Raises:
            DecodeError: payloads not an (N, 1206) uint8 array, stamps not (N,) integers, or a
                malformed packet (``errors`` None).
            ConfigError / ValidationError: the calibration does not fit a detected model.
        """
        rows = payloads if isinstance(payloads, np.ndarray) else np.asarray(payloads)
        if rows.dtype != np.uint8 or rows.ndim != 2 or rows.shape[1] != PACKET_SIZE:
            raise DecodeError("payloads", f"{rows.dtype} {rows.shape}",
                              f"an (N, {PACKET_SIZE}) uint8 array of Velodyne packets")
        stamps = np.asarray(stamps_ns)
        if stamps.shape != (rows.shape[0],) or stamps.dtype.kind not in "iu":
            raise DecodeError("stamps_ns", f"{stamps.dtype} {stamps.shape}",
                              f"({rows.shape[0]},) integer ns, one per payload")
        if rows.strides[1] != 1:                      # a row's bytes must be contiguous
            return self._push_array(stamps.astype(np.int64, copy=False),
                                    np.ascontiguousarray(rows), errors=errors, owned=True)
        return self._push_array(stamps.astype(np.int64, copy=False), rows, errors=errors,
                                owned=_immutable(rows))

    def _push_array(self, stamps: np.ndarray[Any, Any], rows: np.ndarray[Any, Any] | _Table, *,
                    errors: list[tuple[int, LidarScanError]] | None, owned: bool
                    ) -> list[tuple[Any, Any]]:
        """push_many() on checked arrays (or a :class:`_Table` of payloads: decode_packets);
        ``owned``: rows may be kept without a copy."""
        n = rows.shape[0]
        if n == 0:
            return []
        out: list[tuple[Any, Any]] = []
        good, keys, model = self._good_rows(rows, self._model)
        if not isinstance(keys, int) and not good.all():
            bad = np.flatnonzero(~good)
            if errors is None:
                err = self._row_error(rows, int(bad[0]), model)
                raise DecodeError(f"payloads[{int(bad[0])}]: {err.field}", err.value,
                                  err.expected) from err
            errors.extend((int(i), self._row_error(rows, i, model)) for i in bad.tolist())
        if isinstance(keys, int):                     # one model and mode, every packet valid
            bounds, keys = [0, n], np.full(1, keys)
        else:
            starts = np.flatnonzero((keys[1:] != keys[:-1]) | (good[1:] != good[:-1])) + 1
            bounds = [0, *starts.tolist(), n]
        for i, j in itertools.pairwise(bounds):
            if not good[i]:
                continue
            key = (int(keys[i]) >> 8, int(keys[i]) & 0xFF)
            if key != self._key:                      # another mode: end the rotation
                out.extend(self.flush())
                self._key, self._layout = key, self._check_key(key, model)
                self._model = model
            out.extend(self._push_rows(stamps[i:j], rows[i:j]))
        if not owned:
            self._own(stamps, rows)
        return out

    def _own(self, stamps: np.ndarray[Any, Any], rows: np.ndarray[Any, Any]) -> None:
        """Copy the buffered packets and stamps that view the caller's (mutable) arrays."""
        self._packets = [p.copy() if isinstance(p, np.ndarray)
                         and np.may_share_memory(p, rows) else p for p in self._packets]
        self._stamps = [s.copy() if isinstance(s, np.ndarray)
                        and np.may_share_memory(s, stamps) else s for s in self._stamps]

    def _validate(self, data: bytes, model: VelodyneModel | None = None
                  ) -> tuple[tuple[int, int], _Layout]:
        """(key, layout) of one payload, or the DecodeError saying what is wrong with it;
        ``model``: the stream's (default: the decoder's, if it has seen a valid packet)."""
        if len(data) != PACKET_SIZE:
            raise DecodeError("packet", f"{len(data)} bytes", f"{PACKET_SIZE} bytes (a Velodyne "
                              "data packet payload)")
        key = (data[1205], data[1204])
        layout = self._layout_of(key[0] << 8 | key[1], model)
        used = len(layout.flags) * 100
        if data[0:used:100] != b"\xff" * len(layout.flags) or data[1:used:100] != layout.flags:
            raise DecodeError("packet.blocks[*].flag", _flags(data, used // 100),
                              f"{_flag_names(layout.flags)} for a {layout.model.name} "
                              f"{_RETURN_MODES[key[1]]} packet")
        if max(data[3:used:100]) >= 0x8C:              # 36000 = 0x8CA0: check exactly
            worst = max(_AZIMUTHS.unpack_from(data)[: used // 100])
            if worst > 35999:
                raise DecodeError("packet.blocks[*].azimuth", worst,
                                  "0..35999 (hundredths of a degree)")
        return key, layout

    def _row_error(self, rows: np.ndarray[Any, Any] | _Table, i: int,
                   model: VelodyneModel | None) -> DecodeError:
        """The DecodeError push() gives for row i of rows (one :meth:`_good_rows` rejects) in
        a stream of ``model``."""
        try:
            self._validate(rows.row(i) if isinstance(rows, _Table) else rows[i].tobytes(),
                           model)
        except DecodeError as err:
            return err
        raise AssertionError("a row judged malformed passes the per-packet checks")

    def _good_rows(self, rows: np.ndarray[Any, Any] | _Table, model: VelodyneModel | None
                   ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any] | int,
                              VelodyneModel | None]:
        """(good, keys, the stream's model) of N packets in a stream of ``model`` (None: not
        yet known, then the model of the first (product, mode) in order of appearance with a
        valid packet). ``good`` (N,) bool: the packets push() would accept, by the same checks,
        vectorised: one C pass per (product, mode) with the kernel, else numpy; ``keys`` (N,)
        int64 product << 8 | mode of each packet, or one int when all have the same and are
        valid (the kernel's first pass, with the key of packet 0, found them so: no other
        read of the packets)."""
        n = rows.shape[0]
        good = np.zeros(n, bool)
        lib = self._lib
        if lib is not None:
            from converters._kernels.velodyne import addresses, good as check
            table = rows.addresses if isinstance(rows, _Table) else addresses(rows)
            head = rows.row(0) if isinstance(rows, _Table) else rows[0]
            first = int(head[1205]) << 8 | int(head[1204])
            try:
                layout = self._layout_of(first, model)
            except DecodeError:
                layout = None
            if layout is not None and check(lib, table, first, layout.flags, good) == n:
                return good, first, model or layout.model
        keys = _words_at(rows, _KEY_WORD)[:, 0].astype(np.int64)   # product << 8 | mode
        uniform = bool((keys == keys[0]).all())
        if uniform:
            found = [int(keys[0])]
        else:
            unique, at = np.unique(keys, return_index=True)
            found = unique[np.argsort(at)].tolist()
        for k in found:
            try:
                layout = self._layout_of(k, model)
            except DecodeError:                        # unknown product or return mode
                continue
            if lib is not None:
                some = check(lib, table, k, layout.flags, good) > 0
            else:
                assert isinstance(rows, np.ndarray)
                mine = keys == k
                sub = rows if uniform else rows[mine]
                used = len(layout.flags)
                # flag (2 bytes) and azimuth (u16) of each used block as one little-endian u32
                head = sub[:, :100 * used].reshape(-1, used, 100)[:, :, :4].view("<u4")[..., 0]
                flags = 0xFF | (np.frombuffer(layout.flags, np.uint8).astype(np.uint32) << 8)
                ok = np.all(((head & 0xFFFF) == flags) & (head < (36000 << 16)), axis=1)
                good[mine] = ok
                some = bool(ok.any())
            if model is None and some:
                model = layout.model
        return good, keys, model

    def _layout_of(self, key: int, model: VelodyneModel | None) -> _Layout:
        """:meth:`_check_key` of ``key`` (product << 8 | mode) in a stream of ``model``."""
        pair = (key >> 8, key & 0xFF)
        layout = self._layout if pair == self._key else self._check_key(pair, model)
        assert layout is not None
        return layout

    def _push_rows(self, stamps: np.ndarray[Any, Any], rows: np.ndarray[Any, Any] | _Table
                   ) -> list[tuple[Any, Any]]:
        """Add validated packets ((m, 1206) rows or a :class:`_Table`) of the current model
        and mode; cut rotations."""
        layout = self._layout
        assert layout is not None
        at = layout.azimuth_words
        rel = _words_at(rows, at).astype(np.int64).reshape(-1)     # 0..35999 (checked)
        if self._cut:                                # (rel - cut) % 36000
            rel -= self._cut
            rel += 36000 * (rel < 0)
        cuts = np.nonzero(rel < np.concatenate([[self._prev_rel], rel[:-1]]))[0]
        out: list[tuple[Any, Any]] = []
        row0 = 0
        for j in cuts.tolist():                     # sequence s of packet p starts a rotation
            p, s = divmod(j, at.size)
            s = layout.measured_seqs[s]
            self._add(stamps[row0:p + (s > 0)], rows[row0:p + (s > 0)])
            out.extend(self._emit(stop=s if s > 0 else None))
            self._packets, self._stamps, self._rows, self._first_seq = [], [], 0, s
            row0 = p
        self._add(stamps[row0:], rows[row0:])
        self._prev_rel = int(rel[-1])
        return out

    def _add(self, stamps: np.ndarray[Any, Any], rows: np.ndarray[Any, Any] | _Table) -> None:
        if rows.shape[0]:
            self._packets.append(rows)
            self._stamps.append(stamps)
            self._rows += rows.shape[0]

    def flush(self) -> list[tuple[Any, Any]]:
        """The last, partial rotation (if it has any firing); the decoder is then empty."""
        out = self._emit(stop=None, partial=True) if self._packets else []
        self._packets, self._stamps, self._rows, self._first_seq = [], [], 0, 0
        self._prev_rel = -1
        return out

    # ------------------------------------------------------------------------------ internals

    def _check_key(self, key: tuple[int, int], stream: VelodyneModel | None = None) -> _Layout:
        """The layout of packets of ``key`` (product, return mode) in a stream of model
        ``stream`` (default: the decoder's; None: any), or the error saying why it has none."""
        product, mode = key
        if product not in MODELS:
            raise DecodeError("packet.product_id", hex(product), "a known Velodyne product id "
                              "(0x21 HDL-32E, 0x22 VLP-16/Puck LITE, 0x24 Puck Hi-Res, "
                              "0x28 VLP-32C, 0xA1 VLS-128)")
        stream = stream or self._model
        if stream is not None and MODELS[product] is not stream:
            raise DecodeError("packet.product_id", f"{hex(product)} ({MODELS[product].name})",
                              f"a {stream.name} packet, the model of this decoder's stream (one "
                              "decoder per sensor: its calibration is that sensor's)")
        if mode not in _RETURN_MODES:
            raise DecodeError("packet.return_mode", hex(mode),
                              "0x37 strongest, 0x38 last or 0x39 dual")
        model = MODELS[product]
        calib = self._calib if self._calib is not None else model.nominal
        if calib is None:
            raise ConfigError("calibration", None, f"the {model.name} calibration YAML "
                              "(ros-drivers format, from the sensor's XML or the vendor); this "
                              "model has no nominal calibration")
        count = len(calib["lasers"])
        if count != model.lasers:
            raise ValidationError("calibration.lasers", f"{count} lasers",
                                  f"{model.lasers} lasers for the {model.name} that sent "
                                  "these packets")
        return _layout(product, mode)

    def _buffered(self) -> tuple[list[np.ndarray[Any, Any]], np.ndarray[Any, Any]]:
        """The buffered packets as runs of (m, 1206) uint8 rows (consecutive single payloads
        joined, array runs kept as they are: no copy) and all (n,) recorded stamps."""
        runs: list[np.ndarray[Any, Any]] = []
        for single, group in itertools.groupby(self._packets, key=lambda p: type(p) is bytes):
            if single:
                runs.append(np.frombuffer(b"".join(group), np.uint8).reshape(-1, PACKET_SIZE))
            else:
                runs.extend(group)
        stamps = self._stamps
        if len(stamps) == 1 and isinstance(stamps[0], np.ndarray):
            return runs, stamps[0]
        return runs, np.concatenate([np.atleast_1d(np.asarray(t, np.int64)) for t in stamps])

    def _emit(self, stop: int | None, partial: bool = False) -> list[tuple[Any, Any]]:
        """Decode the buffered packets' sequences [first_seq, stop of the last packet);
        ``partial``: the last, unfinished rotation (see :meth:`_assemble`)."""
        layout = self._layout
        assert layout is not None and self._key is not None
        n = self._rows
        if n == 0:
            return []
        begin = self._first_seq
        end = (n - 1) * layout.sequences + (layout.sequences if stop is None else stop)
        if end - begin <= 0:
            return []
        runs, stamps = self._buffered()
        at = layout.head_words                   # timestamp (2 words), sequence azimuths
        head = (_words_at(runs[0], at) if len(runs) == 1
                else np.concatenate([_words_at(r, at) for r in runs]))
        azimuth = head[:, 2:].astype(np.float64)
        toh = head[:, 0].astype(np.int64) | (head[:, 1].astype(np.int64) << 16)
        times, azimuth = _sequence_columns(azimuth, toh, stamps, layout, self._time_source)
        return [self._assemble(runs, begin, times[begin:end], azimuth[begin:end],
                               partial=partial)]

    def _assemble(self, runs: list[np.ndarray[Any, Any]], begin: int,
                  times: np.ndarray[Any, Any], azimuth: np.ndarray[Any, Any],
                  partial: bool = False) -> tuple[Any, Any]:
        """One rotation: sequences begin.. of the packet runs, their times (ns) and azimuths
        (clockwise 0.01 deg). ``partial``: the stream's last, unfinished rotation (flush): its
        rate is not measured over a whole turn (at a field-of-view edge it can be far off), so
        it keeps the current version when it fits in it."""
        layout = self._layout
        assert layout is not None and self._key is not None
        count = times.size
        period, omega = _rates(times, azimuth)
        key = (self._key[0], layout.dual)     # strongest <-> last keeps the geometry
        changed = (self._info is None or self._info_key != key
                   or (not partial and count >= _RATE_COLUMNS and omega > 0
                       and abs(omega - self._omega) > _RATE_CHANGE * self._omega))
        if changed or count > int(self._info.width):
            if not changed:
                period, omega = self._period, self._omega   # same sensor, only wider
            per_rev = 2.0 * math.pi / (omega * period * 1e-9) if omega > 0 else count
            width = max(count, int(math.ceil(per_rev * (1.0 + self._margin))))
            self._new_info(key, width, int(times[0]), period, omega)
        info = self._info
        width = int(info.width)
        pad = width - count
        if pad:
            step = np.arange(1, pad + 1, dtype=np.float64)
            times = np.concatenate([times, times[-1] + np.round(step * self._period)
                                    .astype(np.int64)])
            azimuth = np.concatenate([azimuth, azimuth[-1] + step * self._period * 1e-9
                                      * math.degrees(self._omega) * 100.0])
        nebula = self._azimuth_model == "nebula"
        if self._offsets_key != (layout.model.name, layout.dual):
            self._tables = _tables(layout, self._order, self._rotation if nebula else None,
                                   self._lib)
            self._offsets_key = (layout.model.name, layout.dual)
        tables = self._tables
        assert tables is not None
        returns = tables.offsets.shape[0]
        specs = {"range": np.uint16, "intensity": np.uint8}
        if returns == 2:
            specs.update(range2=np.uint16, intensity2=np.uint8)
        if nebula:
            specs.update(azimuth=np.uint16, **({"azimuth2": np.uint16} if returns == 2 else {}))
        # every pixel of the columns 0..count-1 is written (tests/test_velodyne_packets.py,
        # test_fill_writes_every_pixel): only the padding columns need zeros
        buffer = ScanBuffer(info, specs, as_dataclass=self._as_dataclass, zeroed=False)
        if pad:
            for view in buffer.views.values():
                view[:, count:] = 0
        _fill_views(runs, begin, count, layout, tables, buffer.views)
        stamp = int(times[0])
        column_azimuth = -np.deg2rad(_wrap(azimuth) / 100.0)
        scan = buffer.build(stamp, column_azimuth_angles=column_azimuth,
                            column_time_offsets=times - stamp)
        return scan, info

    def _calib_for(self, model: VelodyneModel) -> Mapping[str, Any]:
        calib = self._calib if self._calib is not None else model.nominal
        assert calib is not None
        return calib

    def _new_info(self, key: tuple[Any, ...], width: int, stamp: int, period: float,
                  omega: float) -> None:
        layout = self._layout
        assert layout is not None
        model = layout.model
        if self._last_info_stamp is not None and stamp <= self._last_info_stamp:
            stamp = self._last_info_stamp + 1               # a new version needs a new stamp
        lo, hi = self._range
        calib = self._calib_for(model)
        if self._azimuth_model == "nebula":
            if model.name not in self._rotations:         # the calibration is fixed
                self._rotations[model.name] = _nebula_rotation(calib, model.lasers)
            self._rotation = self._rotations[model.name]
            if model.nebula != "vlp32":      # Nebula's VLP-16 and VLS-128 formulas: no offsets
                calib = {**calib, "lasers": [
                    {**las, "vert_offset_correction": 0.0, "horiz_offset_correction": 0.0}
                    for las in calib["lasers"]]}
        self._info = info_from_calibration(
            calib, columns=width, stamp_ns=stamp, frame_id=self._frame_id,
            rpm=omega * 60.0 / (2.0 * math.pi),
            beam_time_offsets=np.asarray(model.laser_ns, np.int64),
            column_time_increment=int(round(period)),
            range_min=0.0 if lo is None else lo,
            range_max=65535 * model.distance_resolution if hi is None else hi,
            model=model.name, distance_resolution=model.distance_resolution,
            beam_ids="laser_id", as_dataclass=self._as_dataclass)
        self._info_key, self._period, self._omega = key, period, omega
        self._order = np.asarray(self._info.beam_ids, np.int64)    # laser id of each row
        self._offsets_key = None
        self._last_info_stamp = stamp


def _packet_times(toh_us: np.ndarray[Any, Any], stamps: np.ndarray[Any, Any],
                  source: str) -> np.ndarray[Any, Any]:
    """(n,) int64 ns of each packet's timestamp (see PacketDecoder ``time_source``), from the
    packets' (n,) int64 microseconds past the hour and their recorded stamps (ns)."""
    toh = toh_us * 1000
    delta = toh - toh[0]
    if delta.min() < 0 or delta.max() > _HOUR_NS // 2:
        delta %= _HOUR_NS                             # forward in time, across the hour wrap
        delta = np.where(delta > _HOUR_NS // 2, delta - _HOUR_NS, delta)
    # receive time of the least delayed packet, relative to the sensor clock
    anchor = int(np.min(stamps - delta))
    if source != "receive":
        cand = anchor - anchor % _HOUR_NS + int(toh[0])
        cand += _HOUR_NS * int(round((anchor - cand) / _HOUR_NS))
        if source == "sensor" or abs(cand - anchor) < 1_000_000_000:
            anchor = cand
    return anchor + delta


def _sequence_columns(seq_az: np.ndarray[Any, Any], toh_us: np.ndarray[Any, Any],
                      stamps: np.ndarray[Any, Any], layout: _Layout, source: str
                      ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
    """Time and azimuth of each firing sequence of n packets (sequence order).

    Args: seq_az (n, S) float64 azimuth (0.01 deg) of the block of each sequence (of block 0
    where ``layout.measured`` is -1; overwritten), toh_us (n,) int64 timestamps (us past the
    hour), stamps (n,) int64 recorded stamps (ns).

    Returns time (n*S,) int64 ns of each sequence's first firing and azimuth (n*S,) float64
    clockwise centidegrees (measured, or interpolated for VLP-16's second sequence of a block).
    """
    n = seq_az.shape[0]
    measured = layout.measured_seqs
    if len(measured) < layout.sequences:  # VLP-16: second sequence of a block, half-way in time
        meas = seq_az[:, 0::2]
        gap = _wrap(np.diff(meas, axis=1))
        gap = np.concatenate([gap, gap[:, -1:]], axis=1) if gap.shape[1] else np.zeros_like(meas)
        seq_az[:, 1::2] = meas + gap / 2.0
    times = _packet_times(toh_us, stamps, source)
    seq_ns = layout.seq_times
    grid = times[:, None] + seq_ns[None]
    # A sensor with a restricted field of view completes its last packet before the gap with
    # the first firings after it: sequences after an azimuth jump inside a packet are timed
    # backwards from the next packet (they directly precede it).
    if len(measured) > 1 and n > 1:
        meas = seq_az if len(measured) == layout.sequences else seq_az[:, list(measured)]
        jump = _wrap(np.diff(meas, axis=1)) > _JUMP_CENTIDEG
        rows = np.nonzero(jump[:-1].any(axis=1))[0]
        if rows.size:
            for p in rows.tolist():
                first = measured[int(np.argmax(jump[p])) + 1]
                grid[p, first:] = (times[p + 1] + seq_ns[0] - int(round(layout.model.sequence_ns))
                                   - (seq_ns[-1] - seq_ns[first:]))
    return grid.reshape(-1), seq_az.reshape(-1)


def _rates(times: np.ndarray[Any, Any], azimuth: np.ndarray[Any, Any]) -> tuple[float, float]:
    """(mean column period in ns, rotation rate in rad/s) measured on decoded columns."""
    if times.size < 2:
        return 0.0, 0.0
    dt = np.diff(times.astype(np.float64))
    da = _wrap(np.diff(azimuth))
    half = dt.size // 2                               # np.median(dt), without its overhead
    if dt.size % 2:
        median = float(np.partition(dt, half)[half])
    else:
        low, high = np.partition(dt, (half - 1, half))[half - 1:half + 1]
        median = float((low + high) / 2.0)
    regular = (dt > 0) & (dt < 1.5 * median)          # consecutive firings, not gaps
    if not regular.all():
        if not regular.any():
            return 0.0, 0.0
        dt, da = dt[regular], da[regular]
    total = dt.sum()                                  # (dt.mean() is total / size)
    return float(total / dt.size), float(np.radians(da.sum() / 100.0) / (total * 1e-9))


def _wrap(values: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """``np.mod(values, 36000.0)`` bit for bit (float64), without its cost where every value is
    in (-36000, 72000): there one exact addition or subtraction of 36000 (+0.0 makes -0.0 the
    +0.0 that np.mod gives)."""
    if values.size:
        low, high = values.min(), values.max()        # (NaN: both comparisons fail)
        if low >= 0.0 and high < 36000.0:
            return values + 0.0
        if low >= 0.0 and high < 72000.0:
            return values - 36000.0 * (values >= 36000.0) + 0.0
        if low > -36000.0 and high < 36000.0:
            return values + 36000.0 * (values < 0.0)
    return np.mod(values, 36000.0)


def _immutable(rows: np.ndarray[Any, Any]) -> bool:
    """True if ``rows`` views memory nobody can change: its base chain ends at a ``bytes``
    object (directly or through a read-only memoryview of one), as ``np.frombuffer`` of message
    bytes gives. Such rows may be kept by reference; anything else is copied."""
    base: Any = rows
    while isinstance(base, np.ndarray):
        if base.flags.writeable:
            return False
        base = base.base
    if isinstance(base, memoryview):
        return base.readonly and type(base.obj) is bytes
    return type(base) is bytes


#: packets decode_packets() pushes at once (one join, one C header pass, one stamps array)
_CHUNK = 4096
_stamp_of, _payload_of = operator.itemgetter(0), operator.itemgetter(1)


def decode_packets(packets: Iterable[tuple[int, Any]], calibration: Any = None,
                   **kw: Any) -> Iterator[tuple[Any, Any]]:
    """Decode (stamp_ns, payload) pairs: :meth:`PacketDecoder.push` each, then ``flush``.

    Chunks of up to 4096 pairs go through :meth:`PacketDecoder.push_many` when every payload
    of the chunk is a valid packet (same results): with the C kernel, a chunk of (int,
    1206-byte ``bytes``) tuples is read where it is, through a table of the payloads' addresses
    (:func:`converters._kernels.velodyne.table`), other chunks are joined into one buffer.
    Keyword arguments go to :class:`PacketDecoder`. A malformed packet raises its DecodeError
    after the rotations before it (use :class:`PacketDecoder` directly to report and continue).
    """
    decoder = PacketDecoder(calibration, **kw)
    lib = decoder._lib
    source = iter(packets)
    while chunk := list(itertools.islice(source, _CHUNK)):
        batch = _as_table(chunk, lib) if lib is not None else None
        if batch is None:
            batch = _as_rows(chunk)
        done = None
        if batch is not None:
            try:
                done = decoder._push_array(*batch, errors=None, owned=True)
            except LidarScanError:               # raised before anything was consumed
                done = None
        if done is None:                         # odd inputs or a bad packet: one by one
            for stamp, payload in chunk:
                yield from decoder.push(stamp, payload)
        else:
            yield from done
    yield from decoder.flush()


def _as_table(chunk: list[Any], lib: Any) -> tuple[np.ndarray[Any, Any], _Table] | None:
    """(stamps (n,) int64 ns, the payloads as a :class:`_Table`) of n (stamp, payload) pairs
    when each is a tuple of an int and a 1206-byte ``bytes`` (one C pass, no copy); else None
    (then :func:`_as_rows`)."""
    from converters._kernels.velodyne import table
    found = table(chunk)
    if found is None:
        return None
    addresses, stamps = found
    return stamps, _Table(addresses, chunk, 0, lib)


def _as_rows(chunk: list[Any]) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]] | None:
    """(stamps (n,) int64 ns, rows (n, 1206) uint8 over one new ``bytes``) of n (stamp,
    payload) pairs, the payloads taken as :meth:`PacketDecoder.push` takes them; None when a
    pair, stamp or payload is odd (then push() one by one says what is wrong)."""
    n = len(chunk)
    try:
        payloads = list(map(_payload_of, chunk))
        stamps = np.fromiter(map(_stamp_of, chunk), np.int64, n)
    except (TypeError, ValueError, IndexError, KeyError, OverflowError):
        return None
    if set(map(type, payloads)) != {bytes}:      # bytearray, memoryview, ndarray payloads
        try:
            payloads = list(map(payload_bytes, payloads))
        except LidarScanError:
            return None
    if set(map(len, payloads)) != {PACKET_SIZE}:
        return None
    return stamps, np.frombuffer(b"".join(payloads), np.uint8).reshape(n, PACKET_SIZE)
