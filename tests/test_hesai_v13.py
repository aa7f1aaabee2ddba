"""converters.sources.hesai.decoder: the Pandar128's older firmware (protocol 1.3), synthetic packets built field
by field from the Pandar128 user manual's layout (3.2.2 "UDP Data", Appendix II.1) against a
plain loop oracle written here.

Layout: pre-header 0xEE 0xFF, protocol 1, 3, 2 reserved; header laser num 128, block num 2, echo
count, dis unit, echo num, UDP sequence on/off; body 2 blocks of azimuth u16 + 128 x (distance
u16, reflectivity u8) = 772 bytes; tail 24 bytes: 6 reserved, high-temperature flag, 3 reserved,
motor speed u16, timestamp u32 (us), return mode, factory information, date-time (6); then the
UDP sequence (4) when on. Time: t0 = date-time + timestamp is the trigger of block 2's firing
(dual return: of both blocks, block 1 last, block 2 strongest); block 1 (single return) fires
one firing period earlier, 55.556 us (the module's stated assumption, as the 128E3X's standard
mode); channel delays are not applied.
"""

from __future__ import annotations

import calendar
import math
import struct

import numpy as np
import pytest

from converters.sources.hesai import decoder as hesai
from lidarscan.errors import ConfigError, DecodeError
from test_hesai import _calibration_csv, _compare, _decoded, _rows, _same

DATE = (124, 11, 25, 12, 30, 15)
US = 250_000
PERIOD_NS = 55556


def build(mode: int, azimuths: list[int], dist: np.ndarray, refl: np.ndarray, *,
          udp_seq: bool = True, us: int = US, rpm: int = 600, dis_mm: int = 4) -> bytes:
    dual = mode == 0x39
    out = bytearray([0xEE, 0xFF, 1, 3, 0, 0])
    out += bytes([128, 2, 1 if dual else 0, dis_mm, 2 if dual else 1, int(udp_seq)])
    for b in range(2):
        out += struct.pack("<H", azimuths[b])
        for ch in range(128):
            out += struct.pack("<HB", int(dist[b, ch]), int(refl[b, ch]))
    out += bytes(6) + bytes([0]) + bytes(3)                  # reserved, temperature, reserved
    out += struct.pack("<HI", rpm, us) + bytes([mode, 0x42]) + bytes(DATE)
    if udp_seq:
        out += struct.pack("<I", 1234)
    return bytes(out)


def loop_oracle(packets: list[bytes], csv: str) -> list[tuple[int, int, str, float, float, float]]:
    cal = hesai.load_calibration(csv)
    out = []
    for pk in packets:
        dis_m = pk[9] * 1e-3
        tail = 12 + 772
        rpm, us = struct.unpack_from("<HI", pk, tail + 10)
        mode = pk[tail + 16]
        y, mo, d, h, mi, s = pk[tail + 18:tail + 24]
        t0 = calendar.timegm((1900 + y, mo, d, h, mi, s, 0, 0, 0)) * 10**9 + us * 1000
        for b in range(2):
            if mode == 0x39:
                t, name = t0, ("range2" if b == 0 else "range")     # block 1 last, 2 strongest
            else:
                t, name = t0 - (PERIOD_NS if b == 0 else 0), "range"
            at = 12 + b * 386
            az = struct.unpack_from("<H", pk, at)[0] / 100.0
            for ch in range(128):
                raw = struct.unpack_from("<H", pk, at + 2 + 3 * ch)[0]
                if raw == 0:
                    continue
                r = raw * dis_m
                a = math.radians(az + cal.azimuth_deg[ch])
                e = math.radians(cal.elevation_deg[ch])
                out.append((t, ch + 1, name, r * math.cos(e) * math.sin(a),
                            r * math.cos(e) * math.cos(a), r * math.sin(e)))
    return out


def _stream(mode: int, packets: int = 40, udp_seq: bool = True, seed: int = 2
            ) -> list[tuple[int, bytes]]:
    rng = np.random.default_rng(seed)
    firings = 1 if mode == 0x39 else 2
    out = []
    for p in range(packets):
        az = [(35600 + (p * firings + k) * 20) % 36000 for k in range(firings)]
        az = az * 2 if firings == 1 else az
        dist = rng.integers(1, 65536, (2, 128))
        dist[rng.random(dist.shape) < 0.2] = 0
        us = US + 111 * p
        out.append((us * 1000, build(mode, az, dist, rng.integers(0, 256, (2, 128)),
                                     udp_seq=udp_seq, us=us)))
    return out


@pytest.mark.parametrize("udp_seq", [True, False])
@pytest.mark.parametrize("mode", [0x37, 0x38, 0x39])
def test_protocol_13_against_the_loop_oracle(mode: int, udp_seq: bool) -> None:
    csv = _calibration_csv(128, seed=4)
    packets = _stream(mode, udp_seq=udp_seq)
    assert len(packets[0][1]) == (812 if udp_seq else 808)
    results = list(hesai.decode_packets(packets, csv, as_dataclass=True))
    assert len(results) == 2
    _compare(loop_oracle([p for _, p in packets], csv), _decoded(results))
    scan, info = results[0]
    assert info.model == "Pandar128" and info.column_time_increment == PERIOD_NS
    assert info.width == math.ceil(1.02 * 60e9 / (600 * PERIOD_NS))
    dec = hesai.PacketDecoder(csv, as_dataclass=True)
    _same(results, [r for t, p in packets for r in dec.push(t, p)] + dec.flush())
    stamps, rows = _rows(packets)
    dec = hesai.PacketDecoder(csv, as_dataclass=True)
    _same(results, dec.push_many(stamps, rows) + dec.flush())


def test_protocol_13_bad_packets_raise() -> None:
    good = _stream(0x37, packets=1)[0][1]
    with pytest.raises(DecodeError, match="808 or 812 bytes for a Pandar128 packet"):
        hesai.detect_format(good + bytes(3))
    bad = bytearray(good)
    bad[12 + 772 + 16] = 0x3B                       # a dual mode whose block order is unknown
    with pytest.raises(DecodeError, match="0x3b"):
        list(hesai.decode_packets([(0, bytes(bad))], _calibration_csv(128)))
    with pytest.raises(ConfigError, match="one time per channel"):
        list(hesai.decode_packets([(0, good)], _calibration_csv(128), firetimes=(
            "Operational State,2\nAzimuth State,0\n" + "".join(f"{k},1\n"
                                                             for k in range(1, 129)))))
