"""converters.sources.hesai.decoder on models, modes and packet options no recording covers.

For every format of the decoder's table (Pandar40P, Pandar64, PandarXT16/XT32/XT32M,
PandarQT64, PandarQT128, Pandar128E3X/E4X in standard and high resolution mode) and every
return-mode byte it accepts, a synthetic stream is built from the manuals' layouts (the
field-by-field packet writers of ``test_hesai`` and ``test_hesai_models``) with the header
flags on and off and both distance units, at 300, 600 and 1200 rpm, with the azimuth and the
tail's timestamp advancing as the manual's firing period says. Checked: it decodes, every
scan has the width ``ceil(1.02 * 60 s / (rpm * firing period))`` (the period from the
manuals' firing-time appendices, written here again), no unit is lost (the sums of every
distance and reflectivity of the packets are those of the scans), column times increase
within a scan and scan stamps across scans, and a packet of another model (or not a Hesai
packet) in the middle of the stream raises a DecodeError that names it, after which the
decoder goes on as if it had never seen it. Also: a limited azimuth FOV (one scan per turn),
the tail's motor speed wandering, a year byte counted from 2000, and the angle-correction CSV
as vendors ship it (header line variants, extra columns, CRLF, byte-order mark, quoted cells,
bytes) and its mismatch with the packets' laser count.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pytest

import lidarscan
from converters.sources.hesai import decoder as hesai
from lidarscan.errors import ConfigError, DecodeError
import test_hesai as old
import test_hesai_models as new

# ------------------------------------------------------------------- formats (manuals)
#: firing period (ns) from the manuals' "Absolute Time and Laser Firing Time" appendices
PERIOD_NS = {"Pandar40P": 55560.0, "Pandar64": 55560.0, "PandarXT32": 50000.0,
             "PandarQT64": 500000.0 / 3, "PandarXT16": 50000.0, "PandarXT32M": 50000.0,
             "PandarQT128": 111110.0, "Pandar128E3X/E4X": 55556.0,
             "Pandar128E3X/E4X/hires": 27778.0}
LASERS = {"Pandar40P": 40, "Pandar64": 64, "PandarXT32": 32, "PandarQT64": 64, "PandarXT16": 16,
          "PandarXT32M": 32, "PandarQT128": 128, "Pandar128E3X/E4X": 128,
          "Pandar128E3X/E4X/hires": 128}
BLOCKS = {"Pandar40P": 10, "Pandar64": 6, "PandarXT32": 8, "PandarQT64": 4, "PandarXT16": 8,
          "PandarXT32M": 6, "PandarQT128": 2, "Pandar128E3X/E4X": 2,
          "Pandar128E3X/E4X/hires": 2}
#: header flag variants: the UDP-sequence option (the old formats: appended or not); the
#: 12-byte-header models: the Flags byte (bit 0 UDP sequence, 1 IMU, 2 functional safety,
#: 3 signature, 4 confidence; PandarXT: bit 0 only)
FLAGS = {"Pandar40P": (0, 1), "Pandar64": (0, 1), "PandarXT32": (0, 1), "PandarQT64": (0, 1),
         "PandarXT16": (0, 1), "PandarXT32M": (0, 1),
         "PandarQT128": (0x00, 0x01, 0x02, 0x04, 0x08, 0x10, 0x1F),
         "Pandar128E3X/E4X": (0x00, 0x01, 0x02, 0x04, 0x08, 0x10, 0x1F),
         "Pandar128E3X/E4X/hires": (0x01, 0x1F)}
#: distance units (mm) to try: the Pandar40P has no Dis Unit byte (4 mm)
DIS_MM = {m: ((4,) if m == "Pandar40P" else (4, 5)) for m in LASERS}


def _modes(model: str) -> list[int]:
    if model in old.LAYOUT:
        return [*old.SINGLE, old.DUAL[model][0]]
    return list(new._modes(model.removesuffix("/hires")))


def _returns(model: str, mode: int) -> int:
    if model in old.LAYOUT:
        return 1 if mode in old.SINGLE else 2
    return len(new._modes(model.removesuffix("/hires"))[mode])


def _builder(model: str, mode: int, flags: int, dis_mm: int, rpm: int
             ) -> Callable[..., bytes]:
    """(azimuths, dist, refl, us, mode_flag) -> one payload of ``model`` (manual layouts)."""
    if model in old.LAYOUT:
        def build(az: list[int], dist: Any, refl: Any, us: int, mode_flag: int = 0) -> bytes:
            return old._packet(model, mode, az, dist, refl, us, seq=7 if flags else None,
                               rpm=rpm, dis_mm=dis_mm)
        return build
    name = model.removesuffix("/hires")
    extra = {"op_state": 0} if model.endswith("/hires") else {}

    def build(az: list[int], dist: Any, refl: Any, us: int, mode_flag: int = 0) -> bytes:
        packet = new.build_packet(name, mode, az, dist, refl, flags=flags or 0x00,
                                  dis_mm=dis_mm, rpm=rpm, us=us, mode_flag=mode_flag, **extra)
        if new.MODELS[name]["family"] == "xt" and not flags:   # PandarXT without UDP seq
            packet = packet[:11] + b"\x00" + packet[12:-4]
        return packet
    return build


def _offset(a: bytes, b: bytes) -> int:
    """First byte where two payloads differ."""
    return int(np.flatnonzero(np.frombuffer(a, np.uint8) != np.frombuffer(b, np.uint8))[0])


def _stream(model: str, mode: int, *, flags: int = 1, dis_mm: int = 4, rpm: int = 600,
            rotations: float = 1.3, start: int = 30000, pool: int = 6, seed: int = 5
            ) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """(stamps (N,), payload rows (N, size), the units' distances/reflectivities sent) of a
    sensor turning at ``rpm`` from azimuth ``start`` (0.01 deg), its timestamp advancing by
    the firing period. Bodies come from ``pool`` packets written by the manual-layout
    builders; each packet's block azimuths and timestamp are then set where the builder puts
    them (found by writing packets that differ in that field only)."""
    build = _builder(model, mode, flags, dis_mm, rpm)
    blocks, lasers = BLOCKS[model], LASERS[model]
    returns = _returns(model, mode)
    firings = blocks // returns
    rng = np.random.default_rng(seed)
    zero_az, zeros = [0] * blocks, np.zeros((blocks, lasers), np.int64)
    base = build(zero_az, zeros, zeros, 0)
    az_at = [_offset(base, build([0x0101 if i == b else 0 for i in range(blocks)], zeros,
                                 zeros, 0)) for b in range(blocks)]
    us_at = _offset(base, build(zero_az, zeros, zeros, 0x01010101))
    dists, refls, bodies = [], [], []
    for i in range(pool):
        dist = rng.integers(1, 65536, (blocks, lasers))
        dist[rng.random(dist.shape) < 0.2] = 0
        refl = rng.integers(0, 256, dist.shape)
        dists.append(dist)
        refls.append(refl)
        bodies.append(np.frombuffer(build(zero_az, dist, refl, 0, mode_flag=i % 2), np.uint8))
    period = PERIOD_NS[model]
    step = 36000.0 * rpm * period / 60e9                       # 0.01 deg per firing
    n = int(rotations * 60e9 / (rpm * period)) // firings
    which = np.arange(n) % pool
    rows = np.stack(bodies)[which]
    k = np.arange(n)[:, None] * firings + np.arange(firings)[None, :]
    az = (np.rint(start + k * step).astype(np.int64) % 36000).repeat(returns, axis=1)
    for b in range(blocks):
        rows[:, az_at[b]:az_at[b] + 2] = az[:, b].astype("<u2").view(np.uint8).reshape(n, 2)
    us = 100_000 + np.rint(np.arange(n) * firings * period / 1000).astype(np.int64)
    rows[:, us_at:us_at + 4] = us.astype("<u4").view(np.uint8).reshape(n, 4)
    sent = {"dist": np.stack(dists)[which], "refl": np.stack(refls)[which]}
    return us * 1000, rows, sent


def _width(model: str, rpm: int) -> int:
    return math.ceil(1.02 * 60e9 / (rpm * PERIOD_NS[model]))


def _check(model: str, mode: int, rpm: int, results: list[tuple[Any, Any]],
           sent: dict[str, np.ndarray], dis_mm: int = 4) -> None:
    """Width, nothing lost, times increasing (see the module docstring)."""
    assert results
    returns = _returns(model, mode)
    stamps = []
    dist_sum = refl_sum = 0
    for scan, info in results:
        assert scan.width == info.width == _width(model, rpm)
        assert info.column_time_increment == round(PERIOD_NS[model])
        assert math.isclose(info.range_multiplier, dis_mm * 1e-3)
        assert json.loads(info.vendor_metadata)["rpm"] == rpm
        times = np.asarray(scan.column_time_offsets)
        assert times[0] == 0 and np.all(np.diff(times) > 0)
        stamps.append(lidarscan.stamps.to_ns(scan.header.stamp))
        names = lidarscan.scan.channel_names(scan)
        assert len([c for c in names if c.startswith("range")]) == returns
        for name in names:
            values = lidarscan.scan.channel(scan, name).astype(np.int64)
            if name.startswith("range"):
                dist_sum += int(values.sum())
            elif name.startswith("intensity"):
                refl_sum += int(values.sum())
    assert np.all(np.diff(stamps) > 0)
    assert dist_sum == int(sent["dist"].sum()) and refl_sum == int(sent["refl"].sum())


def _decode(stamps: np.ndarray, rows: np.ndarray, csv: str, batch: int = 500
            ) -> list[tuple[Any, Any]]:
    dec = hesai.PacketDecoder(csv, as_dataclass=True)
    out = []
    for i in range(0, len(rows), batch):
        out += dec.push_many(stamps[i:i + batch], rows[i:i + batch])
    return out + dec.flush()


MODELS = list(PERIOD_NS)
MODES = [(m, mode) for m in MODELS for mode in _modes(m)]


@pytest.mark.parametrize("rpm", [300, 600, 1200])
@pytest.mark.parametrize(("model", "mode"), MODES)
def test_every_model_mode_and_speed_decodes_whole(model: str, mode: int, rpm: int) -> None:
    csv = old._calibration_csv(LASERS[model], seed=2)
    stamps, rows, sent = _stream(model, mode, rpm=rpm)
    results = _decode(stamps, rows, csv)
    assert len(results) == 3                    # 300 deg -> 360, one turn, 0 -> 48 deg
    _check(model, mode, rpm, results, sent)


FLAG_CASES = [(m, mode, f, dis) for m in MODELS for mode in (_modes(m)[1], _modes(m)[-1])
              for f in FLAGS[m] for dis in DIS_MM[m]]


@pytest.mark.parametrize(("model", "mode", "flags", "dis_mm"), FLAG_CASES)
def test_header_flags_and_distance_units(model: str, mode: int, flags: int, dis_mm: int
                                         ) -> None:
    csv = old._calibration_csv(LASERS[model], seed=3)
    stamps, rows, sent = _stream(model, mode, flags=flags, dis_mm=dis_mm, rpm=1200,
                                 rotations=1.1)
    _check(model, mode, 1200, _decode(stamps, rows, csv), sent, dis_mm)


def _foreign() -> dict[str, bytes]:
    """One packet of every model (600 rpm), and payloads that are no Hesai packet at all."""
    out = {}
    for model in MODELS:
        _, rows, _ = _stream(model, _modes(model)[1], rotations=0.01, pool=1)
        out[model] = rows[0].tobytes()
    out["GPS-sized"] = bytes(512)
    out["Velodyne-sized"] = bytes(1206)
    return out


FOREIGN = _foreign()


@pytest.mark.parametrize("model", MODELS)
def test_a_packet_of_another_model_mid_stream_raises_and_is_dropped(model: str) -> None:
    csv = old._calibration_csv(LASERS[model], seed=4)
    stamps, rows, _ = _stream(model, _modes(model)[-1], rpm=1200, rotations=1.2)
    packets = [(int(t), r.tobytes()) for t, r in zip(stamps, rows)]
    ref = _decode(stamps, rows, csv)
    mid = len(packets) // 2
    others = {k: v for k, v in FOREIGN.items() if k.removesuffix("/hires")
              != model.removesuffix("/hires")}
    # push(): each foreign payload raises, naming what it is; the stream goes on untouched
    dec = hesai.PacketDecoder(csv, as_dataclass=True)
    out = [r for t, p in packets[:mid] for r in dec.push(t, p)]
    for name, payload in others.items():
        with pytest.raises(DecodeError) as err:
            dec.push(packets[mid][0], payload)
        if name in LASERS:                       # names the intruder and the stream's model
            assert str(err.value).startswith(f"hesai model='{name.removesuffix('/hires')}'")
            assert model.removesuffix("/hires") in str(err.value)
        else:
            assert str(err.value).startswith(("hesai packet size", "hesai pre-header"))
    out += [r for t, p in packets[mid:] for r in dec.push(t, p)] + dec.flush()
    old._same(out, ref)
    # decode_packets: the error names the index, the rotations before it were yielded
    for name, payload in others.items():
        seq = packets[:mid] + [(packets[mid][0], payload)] + packets[mid:]
        got = []
        with pytest.raises(DecodeError) as err:
            for r in hesai.decode_packets(seq, csv, as_dataclass=True):
                got.append(r)
        assert err.value.index == mid            # type: ignore[attr-defined]
        assert str(err.value).startswith(f"packets[{mid}]")
    # push_many: a batch of the foreign payload raises with index 0; the next batches go on
    dec = hesai.PacketDecoder(csv, as_dataclass=True)
    out = dec.push_many(stamps[:mid], rows[:mid])
    for name, payload in others.items():
        with pytest.raises(DecodeError) as err:
            dec.push_many(stamps[mid:mid + 1], np.frombuffer(payload, np.uint8)[None])
        assert err.value.index == 0 and err.value.results == []   # type: ignore[attr-defined]
    old._same(out + dec.push_many(stamps[mid:], rows[mid:]) + dec.flush(), ref)


def test_motor_speed_jitter_keeps_one_width_and_version() -> None:
    """The tail's motor speed of a real sensor wanders (598, 601, ...): the width follows the
    stream's first packet rounded to a multiple of 60 rpm; no new version per packet."""
    csv = old._calibration_csv(64, seed=7)
    stamps, rows, sent = _stream("Pandar64", 0x39, rpm=600, rotations=2.2)
    at = _offset(old._packet("Pandar64", 0x39, [0] * 6, np.zeros((6, 64)), np.zeros((6, 64)),
                             0, rpm=600),
                 old._packet("Pandar64", 0x39, [0] * 6, np.zeros((6, 64)), np.zeros((6, 64)),
                             0, rpm=0x0101))
    jitter = 600 + np.random.default_rng(8).integers(-5, 6, len(rows))
    rows[:, at:at + 2] = jitter.astype("<u2").view(np.uint8).reshape(-1, 2)
    results = _decode(stamps, rows, csv)
    assert len({info.header.stamp for _, info in results}) == 1
    _check("Pandar64", 0x39, 600, results, sent)


# ------------------------------------------------------------------- angle-correction CSV
ROWS = [(1, 14.882, -1.042), (2, 11.032, -1.042), (3, 8.059, -1.042), (4, 5.057, -1.042)]


def _csv(header: str = "Laser id,Elevation,Azimuth", end: str = "\n", extra: str = "",
         quote: str = "") -> str:
    lines = [header] if header else []
    lines += [",".join(f"{quote}{v}{quote}" for v in row) + extra for row in ROWS]
    return end.join(lines) + end


VARIANTS = {
    "plain": _csv(),
    "channel header": _csv("Channel,Elevation,Azimuth"),
    "no header": _csv(""),
    "crlf": _csv(end="\r\n"),
    "bom": "\ufeff" + _csv(),
    "bom, no header": "\ufeff" + _csv(""),
    "extra columns": _csv("Laser id,Elevation,Azimuth,Azimuth Offset,Distance", extra=",0.1,0"),
    "spaces and blank lines": "Laser id, Elevation, Azimuth\n\n" + "".join(
        f" {a} , {b} , {c} \n\n" for a, b, c in ROWS),
    "quoted cells": _csv('"Laser id","Elevation","Azimuth"', quote='"'),
    "trailing comment": _csv() + "# end of table\n",
}


@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_calibration_csv_variants_parse_alike(variant: str, tmp_path: Path) -> None:
    text = VARIANTS[variant]
    path = tmp_path / "angles.csv"
    path.write_bytes(text.encode("utf-8"))
    for source in (text, path, str(path), text.encode("utf-8")):
        cal = hesai.load_calibration(source)
        assert cal.laser_ids.tolist() == [r[0] for r in ROWS], (variant, source)
        assert cal.elevation_deg.tolist() == [r[1] for r in ROWS]
        assert cal.azimuth_deg.tolist() == [r[2] for r in ROWS]


def test_calibration_with_the_wrong_channel_count_names_both() -> None:
    stamps, rows, _ = _stream("PandarXT32", 0x37, rotations=0.05)
    for lasers in (16, 64):
        dec = hesai.PacketDecoder(old._calibration_csv(lasers), as_dataclass=True)
        with pytest.raises(ConfigError, match=f"calibration lasers.*{lasers}.*32"):
            dec.push(int(stamps[0]), rows[0].tobytes())
    for bad in ("Laser id,Elevation,Azimuth\n1,2,3\n3,4,5\n",          # id 2 missing
                "Laser id,Elevation,Azimuth\n1,2,3\n1,4,5\n",          # id 1 twice
                "Laser id,Elevation,Azimuth\n1,2,x\n2,4,5\n",          # not a number
                "Laser id,Elevation,Azimuth\n", b"\xff\xfe1,2,3\n",      # empty, UTF-16
                bytearray(b"/nonexistent.csv"), 5, None, 1.5):           # no file, no CSV
        with pytest.raises(DecodeError):
            hesai.load_calibration(bad)


@pytest.mark.parametrize("fov", [(0, 18000), (9000, 27000), (3000, 12000), (30000, 6000)])
@pytest.mark.parametrize("model", ["Pandar64", "PandarXT32", "Pandar128E3X/E4X"])
def test_a_limited_azimuth_fov_gives_one_scan_per_turn(model: str, fov: tuple[int, int]
                                                       ) -> None:
    """The sensor sends only the packets inside its azimuth FOV [lo, hi) (0.01 deg): each
    turn's packets are one scan of the full-turn width (the rest padded), whether the FOV
    contains azimuth 0 or not; nothing is lost."""
    mode = _modes(model)[1]
    returns = _returns(model, mode)
    csv = old._calibration_csv(LASERS[model], seed=6)
    start = 100
    stamps, rows, sent = _stream(model, mode, rpm=1200, rotations=3.0, start=start)
    firings = BLOCKS[model] // returns
    step = 36000.0 * 1200 * PERIOD_NS[model] / 60e9
    k = np.arange(len(rows))[:, None] * firings + np.arange(firings)[None, :]
    unwrapped = np.rint(start + k * step).astype(np.int64)      # as _stream wrote them
    az = unwrapped % 36000
    lo, hi = fov
    inside = (az >= lo) & (az < hi) if lo < hi else (az >= lo) | (az < hi)
    keep = inside.all(1)
    turns = np.unique((unwrapped[keep] - (lo if lo < hi else 0)) // 36000)
    results = _decode(stamps[keep], rows[keep], csv)
    assert len(results) == len(turns)
    _check(model, mode, 1200, results,
           {"dist": sent["dist"][keep], "refl": sent["refl"][keep]})


@pytest.mark.parametrize("model", ["Pandar64", "PandarXT32", "Pandar128E3X/E4X"])
def test_a_year_byte_counted_from_2000_gives_the_same_times(model: str) -> None:
    """The Pandar64 manual's tail counts the year from 2000, the others (and its recording)
    from 1900: a year byte below 70 is read from 2000, so 24 and 124 both mean 2024."""
    csv = old._calibration_csv(LASERS[model], seed=9)
    stamps, rows, _ = _stream(model, _modes(model)[0], rpm=1200, rotations=1.2)
    dec = hesai.PacketDecoder(csv, as_dataclass=True)
    first = dec.push(int(stamps[0]), rows[0].tobytes())
    at = hesai.detect_format(rows[0].tobytes()).datetime_at
    assert first == [] and rows[0, at] in (123, 124)
    short = rows.copy()
    short[:, at] -= 100
    results = _decode(stamps, short, csv)
    old._same(results, _decode(stamps, rows, csv))
    year = lidarscan.stamps.to_ns(results[0][0].header.stamp) // 10**9 // 31_556_952 + 1970
    assert year == 1900 + int(rows[0, at])
