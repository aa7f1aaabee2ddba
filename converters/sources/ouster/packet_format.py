"""Ouster lidar UDP packet layouts (firmware 2.x/3.x "lidar data format"), read from metadata.

A lidar packet is (all little-endian, offsets in bytes):

* packet header, 32 bytes (none for LEGACY). Standard header: packet type u16 at 0 (1 = lidar),
  frame id u16 at 2, init_id u24 at 4, serial number u40 at 7 (then shot-limiting / thermal
  countdowns and status bytes). FuSa header (FUSA_RNG15_RFL8_NIR8_DUAL): packet type u8 at 0,
  init_id u24 at 1, frame id u32 at 4, serial number u40 at 11.
* ``columns_per_packet`` measurement columns, each: a column header (12 bytes: timestamp u64 ns
  at 0, measurement id u16 at 8, status u16 at 10, bit 0 = valid; LEGACY: 16 bytes with the frame
  id u16 at 10 and the encoder count u32 at 12), then ``pixels_per_column`` pixels of the
  profile's size, then (LEGACY only) a u32 column status (0xFFFFFFFF = valid; bit 0 tested).
* packet footer, 32 bytes (none for LEGACY).

Pixel fields per profile: a little-endian word of ``src`` bytes read at ``offset``, and-ed with
``mask`` (0: none), shifted right by ``shift`` (negative: left), stored as ``dtype``, exactly
as ouster-sdk fills its ``LidarFrame`` fields (``FIELDS``; keys are the frame keys
:func:`converters.ouster.scan_from_frame` reads). Ranges are millimetres; the low-data-rate
ranges (RNG15) come in units of 8 mm and their near-IR in units of 16.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

import converters.sources.ouster.metadata as _meta
from lidarscan.errors import DecodeError, ValidationError

__all__ = ["FIELDS", "PIXEL_BYTES", "PROFILES", "Field", "PacketLayout", "layout_from_metadata"]


@dataclass(frozen=True)
class Field:
    """One pixel field: frame key, source word size (bytes), byte offset in the pixel, mask,
    right shift (negative = left) and output dtype."""

    key: str
    src: int
    offset: int
    mask: int
    shift: int
    dtype: str


_RNG19 = 0x0007FFFF
_RNG15 = 0x7FFF

#: profile -> pixel fields (documented lidar data formats; dtypes as ouster-sdk's LidarFrame)
FIELDS: dict[str, tuple[Field, ...]] = {
    "LEGACY": (
        Field("range_mm", 4, 0, 0x000FFFFF, 0, "uint32"),
        Field("signal", 2, 6, 0, 0, "uint16"),
        Field("reflectivity", 1, 4, 0, 0, "uint8"),    # low byte of the u16 at 4
        Field("near_ir", 2, 8, 0, 0, "uint16"),
        Field("flags", 1, 3, 0, 4, "uint8"),
    ),
    "RNG19_RFL8_SIG16_NIR16": (
        Field("range_mm", 4, 0, _RNG19, 0, "uint32"),
        Field("signal", 2, 6, 0, 0, "uint16"),
        Field("reflectivity", 1, 4, 0, 0, "uint8"),
        Field("near_ir", 2, 8, 0, 0, "uint16"),
        Field("flags", 1, 2, 0xF8, 3, "uint8"),
    ),
    "RNG19_RFL8_SIG16_NIR16_DUAL": (
        Field("range_mm", 4, 0, _RNG19, 0, "uint32"),
        Field("signal", 2, 8, 0, 0, "uint16"),
        Field("reflectivity", 1, 3, 0, 0, "uint8"),
        Field("near_ir", 2, 12, 0, 0, "uint16"),
        Field("flags", 1, 2, 0xF8, 3, "uint8"),
        Field("range2_mm", 4, 4, _RNG19, 0, "uint32"),
        Field("signal2", 2, 10, 0, 0, "uint16"),
        Field("reflectivity2", 1, 7, 0, 0, "uint8"),
        Field("flags2", 1, 6, 0xF8, 3, "uint8"),
    ),
    "RNG15_RFL8_NIR8": (
        Field("range_mm", 2, 0, _RNG15, -3, "uint32"),
        Field("reflectivity", 1, 2, 0, 0, "uint8"),
        Field("near_ir", 1, 3, 0, -4, "uint16"),
        Field("flags", 1, 1, 0x80, 7, "uint8"),
    ),
    "FUSA_RNG15_RFL8_NIR8_DUAL": (
        Field("range_mm", 2, 0, _RNG15, -3, "uint32"),
        Field("reflectivity", 1, 2, 0, 0, "uint8"),
        Field("near_ir", 1, 3, 0, -4, "uint16"),
        Field("flags", 1, 1, 0x80, 7, "uint8"),
        Field("range2_mm", 2, 4, _RNG15, -3, "uint32"),
        Field("reflectivity2", 1, 6, 0, 0, "uint8"),
        Field("flags2", 1, 5, 0x80, 7, "uint8"),
    ),
}

#: profile -> bytes per pixel
PIXEL_BYTES = {"LEGACY": 12, "RNG19_RFL8_SIG16_NIR16": 12, "RNG19_RFL8_SIG16_NIR16_DUAL": 16,
               "RNG15_RFL8_NIR8": 4, "FUSA_RNG15_RFL8_NIR8_DUAL": 8}
PROFILES = tuple(FIELDS)

#: (byte offset, size) of the little-endian frame id, init_id and serial number in a lidar
#: packet, per header kind (the module header's layouts; LEGACY: the first column's frame id,
#: no init_id or serial number)
_HEADER_WORDS: dict[str, tuple[tuple[int, int] | None, ...]] = {
    "standard": ((2, 2), (4, 3), (7, 5)),
    "fusa": ((4, 4), (1, 3), (11, 5)),
    "legacy": ((10, 2), None, None),
}

#: UDP payload size of an Ouster IMU packet (LEGACY IMU profile): never a lidar packet
IMU_PACKET_BYTES = 48


@dataclass(frozen=True)
class PacketLayout:
    """Where everything is in one sensor's lidar packets (from its metadata).

    Attributes:
        profile: ``udp_profile_lidar`` (one of :data:`PROFILES`).
        height: pixels per column (beams).
        width: columns per frame.
        columns_per_packet: measurement columns per packet.
        column_window: (first, last) measurement id the sensor sends, inclusive (may wrap).
        init_id: the metadata's initialization id (0: not given, not checked).
        serial: the metadata's serial number (0: not given or not a number, not checked).
        udp_port: the metadata's lidar UDP port (0: not given).
        fusa: the FuSa packet header (FUSA profile or ``header_type`` "FUSA").
    """

    profile: str
    height: int
    width: int
    columns_per_packet: int
    column_window: tuple[int, int]
    init_id: int
    serial: int
    udp_port: int
    fusa: bool

    @property
    def legacy(self) -> bool:
        return self.profile == "LEGACY"

    @property
    def header_bytes(self) -> int:
        return 0 if self.legacy else 32

    @property
    def column_header_bytes(self) -> int:
        return 16 if self.legacy else 12

    @property
    def pixel_bytes(self) -> int:
        return PIXEL_BYTES[self.profile]

    @property
    def column_bytes(self) -> int:
        return (self.column_header_bytes + self.height * self.pixel_bytes
                + (4 if self.legacy else 0))

    @property
    def packet_bytes(self) -> int:
        """UDP payload size of one lidar packet (header + columns + footer)."""
        return 2 * self.header_bytes + self.columns_per_packet * self.column_bytes

    @property
    def status_offset(self) -> int:
        """Byte offset of the column status inside a column (u16, LEGACY u32)."""
        return self.column_bytes - 4 if self.legacy else 10

    @property
    def fields(self) -> tuple[Field, ...]:
        return FIELDS[self.profile]

    def window_mask(self) -> np.ndarray[Any, Any]:
        """(W,) bool: the measurement ids inside the column window."""
        first, last = self.column_window
        ids = np.arange(self.width)
        if first <= last:
            return (ids >= first) & (ids <= last)
        return (ids >= first) | (ids <= last)           # a window across column 0

    @property
    def _header_words(self) -> tuple[tuple[int, int] | None, ...]:
        """(byte offset, size) of the frame id, init_id and serial number in a packet
        (``_HEADER_WORDS`` of this header kind; None: the packet has no such field)."""
        return _HEADER_WORDS["legacy" if self.legacy else "fusa" if self.fusa else "standard"]

    def header(self, packet: Any) -> tuple[int, int, int]:
        """(frame id, init_id, serial) of one packet (bytes-like of ``packet_bytes``); LEGACY:
        the first column's frame id and 0, 0."""
        head = bytes(packet[:16])
        frame, init_id, serial = (0 if word is None else
                                  int.from_bytes(head[word[0]:word[0] + word[1]], "little")
                                  for word in self._header_words)
        return frame, init_id, serial

    def headers(self, rows: np.ndarray[Any, Any]) -> tuple[np.ndarray[Any, Any], ...]:
        """:meth:`header` of every row of an (N, packet_bytes) uint8 array: three (N,) int64."""
        def word(at: int, size: int) -> np.ndarray[Any, Any]:
            out = np.zeros(rows.shape[0], np.int64)
            for k in range(size):
                out |= rows[:, at + k].astype(np.int64) << (8 * k)
            return out

        return tuple(np.zeros(rows.shape[0], np.int64) if at is None else word(*at)
                     for at in self._header_words)


def _window(value: Any, width: int) -> tuple[int, int]:
    if value is None:
        return 0, width - 1
    try:
        first, last = (int(v) for v in value)
    except (TypeError, ValueError) as err:
        raise DecodeError("metadata.column_window", value, "[first, last] measurement ids") \
            from err
    if not (0 <= first < width and 0 <= last < width):
        raise ValidationError("metadata.column_window", [first, last],
                              f"measurement ids in 0..{width - 1}")
    return first, last


def layout_from_metadata(src: Any) -> PacketLayout:
    """:class:`PacketLayout` from Ouster metadata (path, JSON text or dict; flat firmware-2.x
    or nested layout, as :func:`converters.ouster.info_from_metadata` reads it).

    ``udp_profile_lidar`` absent means LEGACY (firmware < 2.2); ``columns_per_packet`` absent
    means 16 (both read from ``lidar_data_format``, else ``config_params``).

    Raises:
        DecodeError: unreadable metadata, unknown profile, missing size keys.
        ValidationError: a column window outside the frame or a packet above 65535 bytes.
    """
    data, _ = _meta.load_metadata(src)
    meta = _meta._Lookup(data)
    fmt = ("lidar_data_format",)
    ident = ("sensor_info",)
    height = _meta._int(meta.get("pixels_per_column", fmt) or
                        len(meta.require("beam_altitude_angles", ("beam_intrinsics",))),
                        "pixels_per_column")
    columns = meta.get("columns_per_frame", fmt)
    if columns is None:
        columns = _meta._parse_mode(meta.require("lidar_mode", ("config_params",)))[0]
    width = _meta._int(columns, "columns_per_frame")
    if not 0 < width <= _meta.MAX_COLUMNS or not 0 < height <= 1024:
        raise ValidationError("metadata", f"{height} x {width}",
                              f"1..1024 pixels per column, 1..{_meta.MAX_COLUMNS} columns")
    # the sensor's own /api/v1/sensor/metadata also states these in config_params
    fmt_or_config = ("lidar_data_format", "config_params")
    per_packet = _meta._int(meta.get("columns_per_packet", fmt_or_config, 16),
                            "columns_per_packet")
    if not 0 < per_packet <= width:
        raise ValidationError("metadata.columns_per_packet", per_packet, f"1..{width}")
    profile = str(meta.get("udp_profile_lidar", fmt_or_config) or "LEGACY")
    profile = profile.removeprefix("PROFILE_")
    if profile == "LIDAR_LEGACY":
        profile = "LEGACY"
    if profile not in FIELDS:
        raise DecodeError("metadata.udp_profile_lidar", profile,
                          f"one of the lidar packet profiles {', '.join(PROFILES)}")
    init_id = meta.get("initialization_id", ident, 0) or 0
    serial = meta.get("prod_sn", ident, 0) or 0
    port = meta.get("udp_port_lidar", ("config_params",), 0) or 0
    header_type = str(meta.get("header_type", fmt, "") or "")
    layout = PacketLayout(
        profile=profile, height=height, width=width, columns_per_packet=per_packet,
        column_window=_window(meta.get("column_window", fmt), width),
        init_id=_meta._int(init_id, "initialization_id"),
        serial=int(str(serial).strip()) if str(serial).strip().isdigit() else 0,
        udp_port=_meta._int(port, "udp_port_lidar"),
        fusa=profile.startswith("FUSA") or header_type.upper() == "FUSA")
    if layout.packet_bytes > 65535:
        raise ValidationError("lidar packet size", layout.packet_bytes,
                              f"at most 65535 bytes ({height} pixels x {per_packet} columns "
                              f"of {profile})")
    return layout

