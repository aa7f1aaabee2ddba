"""Test helpers for Ouster lidar packets: metadata variants, a packet writer and two oracles
that are not the decoder under test (a per-pixel loop over the documented bit layout, and
ouster-sdk's own FrameBatcher when it is installed)."""

from __future__ import annotations

import copy
import json
import struct
from pathlib import Path
from typing import Any

import numpy as np

DATA = Path(__file__).parent / "data" / "ouster"
OS2 = "OS-2-128-U1_v2.3.0_1024x10"
OS0 = "OS-0-32-U1_v2.2.0_1024x10"
WINDOWED = "2_0_0_os1-992008000494-128_col_win_legacy"

#: profile -> (bytes per pixel, {frame key: function of the pixel's bytes}), written from the
#: firmware user manual's "lidar data format" tables (bit ranges of each little-endian word)
DOCUMENTED: dict[str, tuple[int, dict[str, Any]]] = {
    "LEGACY": (12, {
        "range_mm": lambda p: struct.unpack_from("<I", p, 0)[0] & ((1 << 20) - 1),
        "flags": lambda p: p[3] >> 4,
        "reflectivity": lambda p: struct.unpack_from("<H", p, 4)[0] & 0xFF,
        "signal": lambda p: struct.unpack_from("<H", p, 6)[0],
        "near_ir": lambda p: struct.unpack_from("<H", p, 8)[0],
    }),
    "RNG19_RFL8_SIG16_NIR16": (12, {
        "range_mm": lambda p: struct.unpack_from("<I", p, 0)[0] % (1 << 19),
        "flags": lambda p: (struct.unpack_from("<I", p, 0)[0] >> 19) & 0x1F,
        "reflectivity": lambda p: p[4],
        "signal": lambda p: struct.unpack_from("<H", p, 6)[0],
        "near_ir": lambda p: struct.unpack_from("<H", p, 8)[0],
    }),
    "RNG19_RFL8_SIG16_NIR16_DUAL": (16, {
        "range_mm": lambda p: struct.unpack_from("<I", p, 0)[0] % (1 << 19),
        "flags": lambda p: (struct.unpack_from("<I", p, 0)[0] >> 19) & 0x1F,
        "reflectivity": lambda p: p[3],
        "range2_mm": lambda p: struct.unpack_from("<I", p, 4)[0] % (1 << 19),
        "flags2": lambda p: (struct.unpack_from("<I", p, 4)[0] >> 19) & 0x1F,
        "reflectivity2": lambda p: p[7],
        "signal": lambda p: struct.unpack_from("<H", p, 8)[0],
        "signal2": lambda p: struct.unpack_from("<H", p, 10)[0],
        "near_ir": lambda p: struct.unpack_from("<H", p, 12)[0],
    }),
    "RNG15_RFL8_NIR8": (4, {
        "range_mm": lambda p: (struct.unpack_from("<H", p, 0)[0] % (1 << 15)) * 8,
        "flags": lambda p: p[1] >> 7,
        "reflectivity": lambda p: p[2],
        "near_ir": lambda p: p[3] * 16,
    }),
    "FUSA_RNG15_RFL8_NIR8_DUAL": (8, {
        "range_mm": lambda p: (struct.unpack_from("<H", p, 0)[0] % (1 << 15)) * 8,
        "flags": lambda p: p[1] >> 7,
        "reflectivity": lambda p: p[2],
        "near_ir": lambda p: p[3] * 16,
        "range2_mm": lambda p: (struct.unpack_from("<H", p, 4)[0] % (1 << 15)) * 8,
        "flags2": lambda p: p[5] >> 7,
        "reflectivity2": lambda p: p[6],
    }),
}
DTYPES = {"range_mm": np.uint32, "range2_mm": np.uint32, "signal": np.uint16,
          "signal2": np.uint16, "near_ir": np.uint16, "reflectivity": np.uint8,
          "reflectivity2": np.uint8, "flags": np.uint8, "flags2": np.uint8}


def load(name: str) -> dict[str, Any]:
    return json.loads((DATA / f"{name}.json").read_text())


def metadata(profile: str, height: int = 16, width: int = 512, per_packet: int = 16,
             window: tuple[int, int] | None = None, init_id: int = 4242,
             serial: str = "992210000957") -> dict[str, Any]:
    """A flat firmware-2.x metadata dict (from the OS-2-128 file) for any profile / size."""
    meta = copy.deepcopy(load(OS2))
    alt = np.linspace(21.0, -21.0, height)
    meta["beam_altitude_angles"] = alt.tolist()
    meta["beam_azimuth_angles"] = np.resize([4.2, 1.4, -1.4, -4.2], height).tolist()
    meta["lidar_mode"] = f"{width}x10"
    meta["initialization_id"] = init_id
    meta["prod_sn"] = serial
    fmt = meta["data_format"]
    fmt.update(pixels_per_column=height, columns_per_frame=width, columns_per_packet=per_packet,
               column_window=list(window or (0, width - 1)), udp_profile_lidar=profile,
               pixel_shift_by_row=np.resize([12, 8, 4, 0], height).tolist())
    return meta


class Writer:
    """Lidar packets of the documented layout (headers written field by field)."""

    def __init__(self, meta: dict[str, Any], seed: int = 0) -> None:
        fmt = meta.get("data_format") or meta["lidar_data_format"]
        self.profile = fmt.get("udp_profile_lidar", "LEGACY")
        self.h, self.w = fmt["pixels_per_column"], fmt["columns_per_frame"]
        self.cpp = fmt["columns_per_packet"]
        self.window = fmt.get("column_window", [0, self.w - 1])
        self.init_id = int(meta.get("initialization_id", 0))
        self.serial = int(meta.get("prod_sn", 0))
        self.pixel = DOCUMENTED[self.profile][0]
        legacy = self.profile == "LEGACY"
        self.head = 0 if legacy else 32
        self.col = (16 if legacy else 12) + self.h * self.pixel + (4 if legacy else 0)
        self.size = 2 * self.head + self.cpp * self.col
        self.rng = np.random.default_rng(seed)

    def in_window(self, m: int) -> bool:
        first, last = self.window
        return first <= m <= last if first <= last else (m >= first or m <= last)

    def packet(self, frame: int, first: int, t0: int = 10**12, *, invalid: set[int] = frozenset(),
               init_id: int | None = None, serial: int | None = None) -> bytes:
        """Packet of frame ``frame`` holding columns first..first+cpp-1 (random pixels);
        columns outside the window or in ``invalid`` get status 0."""
        buf = bytearray(self.rng.integers(0, 256, self.size, dtype=np.uint8).tobytes())
        init = self.init_id if init_id is None else init_id
        sn = self.serial if serial is None else serial
        if self.profile.startswith("FUSA"):
            buf[0] = 1
            buf[1:4] = init.to_bytes(3, "little")
            buf[4:8] = frame.to_bytes(4, "little")
            buf[11:16] = sn.to_bytes(5, "little")
        elif self.profile != "LEGACY":
            buf[0:2] = (1).to_bytes(2, "little")
            buf[2:4] = frame.to_bytes(2, "little")
            buf[4:7] = init.to_bytes(3, "little")
            buf[7:12] = sn.to_bytes(5, "little")
        for k in range(self.cpp):
            m = first + k
            at = self.head + k * self.col
            ok = self.in_window(m) and m not in invalid and m < self.w
            struct.pack_into("<QH", buf, at, t0 + m * 97_656 + int(self.rng.integers(0, 50)), m)
            if self.profile == "LEGACY":
                struct.pack_into("<HI", buf, at + 10, frame, 0)
                struct.pack_into("<I", buf, at + self.col - 4, 0xFFFFFFFF if ok else 0)
            else:
                struct.pack_into("<H", buf, at + 10, (1 if ok else 0) | 0xF0)
        return bytes(buf)

    def frame(self, frame: int, t0: int = 10**12, **kw: Any) -> list[bytes]:
        """The packets a sensor sends for one frame: those holding a window column."""
        return [self.packet(frame, first, t0, **kw) for first in range(0, self.w, self.cpp)
                if any(self.in_window(m) for m in range(first, min(first + self.cpp, self.w)))]


def loop_frame(meta: dict[str, Any], packets: list[bytes]) -> dict[str, np.ndarray]:
    """The ouster-sdk style frame of ``packets`` by a per-pixel loop over DOCUMENTED."""
    wr = Writer(meta)
    size, fields = DOCUMENTED[wr.profile]
    out = {k: np.zeros((wr.h, wr.w), DTYPES[k]) for k in fields}
    times = np.zeros(wr.w, np.uint64)
    status = np.zeros(wr.w, np.uint32)
    mids = np.zeros(wr.w, np.uint16)
    legacy = wr.profile == "LEGACY"
    for pkt in packets:
        for k in range(wr.cpp):
            at = wr.head + k * wr.col
            ts, m = struct.unpack_from("<QH", pkt, at)
            st = struct.unpack_from("<I", pkt, at + wr.col - 4)[0] if legacy else \
                struct.unpack_from("<H", pkt, at + 10)[0]
            if not st & 1 or m >= wr.w:
                continue
            times[m], status[m], mids[m] = ts, st, m
            for u in range(wr.h):
                start = at + (16 if legacy else 12) + u * size
                pixel = pkt[start:start + size]
                for key, read in fields.items():
                    out[key][u, m] = read(pixel)
    return {**out, "timestamps_ns": times, "status": status, "measurement_id": mids}


def sdk_frames(meta: dict[str, Any] | str, packets: list[bytes], count: int,
               later: list[bytes]) -> list[dict[str, Any]]:
    """ouster-sdk's decoding of ``packets`` (its FrameBatcher): ``count`` frame dicts. The
    SDK holds the last frames back: ``later`` (packets of later frame ids) push them out.
    Needs ouster-sdk."""
    import warnings

    from ouster.sdk import core

    text = meta if isinstance(meta, str) else json.dumps(meta)
    info = core.SensorInfo(text)
    fmt = core.PacketFormat(info)
    batcher = core.FrameBatcher(info)
    names = {"RANGE": "range_mm", "RANGE2": "range2_mm", "SIGNAL": "signal",
             "SIGNAL2": "signal2", "REFLECTIVITY": "reflectivity",
             "REFLECTIVITY2": "reflectivity2", "NEAR_IR": "near_ir", "FLAGS": "flags",
             "FLAGS2": "flags2"}
    frames: list[dict[str, Any]] = []
    frame = core.LidarFrame(info)
    for data in [*packets, *later]:
        if len(frames) >= count:
            break
        packet = core.LidarPacket(fmt)
        packet.buf[:] = np.frombuffer(data, np.uint8)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ready = batcher.batch(packet, frame)
        if ready:
            arrays = {names[f]: np.array(frame.field(f)) for f in frame.fields if f in names}
            arrays.update(timestamps_ns=np.array(frame.timestamp),
                          status=np.array(frame.status),
                          measurement_id=np.array(frame.measurement_id),
                          frame_id=frame.frame_id)
            frames.append(arrays)
            frame = core.LidarFrame(info)
    return frames
