"""converters.sources.hesai.decoder with a vendor "Firetime Correction File": parser, built-in tables, pixel times.

The vendor files in ``tests/data/hesai_firetimes`` are copies from Hesai's SDK (provenance and
licence: ``HESAI_SDK_NOTICE.md`` there). The loop oracle of the 128 series' per-pixel times
reads those CSVs with the csv module, independently of the module under test: a pixel fires at
t0 + its block's start (the manual's "Start Time of Each Block") + the file's time of its
channel in the packet's operational state, the block's azimuth state (tail bits 15:14 block 1,
13:12 block 2) and near (distance < the file's section distance) or far field.
"""

from __future__ import annotations

import calendar
import csv
import io
import json
import struct
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import lidarscan
from converters.sources.hesai import decoder as hesai
from lidarscan.errors import ConfigError, DecodeError, LidarScanError
from test_hesai import (DATA as NEBULA, RECORDINGS, _calibration_csv, _compare, _decoded,
                        _packets, _rows, _same)
from test_hesai_models import MODELS, US, _firing_ns, _modes, build_packet, oracle

FIRETIMES = Path(__file__).parent / "data" / "hesai_firetimes"
P128 = "Pandar128E3X/E4X"


def _file(name: str) -> Path:
    return FIRETIMES / f"{name}_firetimes.csv"


# --------------------------------------------------------------------------------- parser
def test_vendor_files_parse() -> None:
    e3x = hesai.load_firetimes(_file("Pandar128E3X"))
    assert (e3x.kind, e3x.lasers, e3x.near_m) == ("state", 128, 2.85)
    assert e3x.states == ((0, 0), (0, 1), (0, 2), (0, 3), (2, 0), (2, 1), (3, 0), (3, 1))
    assert e3x.table is not None
    # channel 47 (row "47,10381,10381,10731,27406,...,38509,55184,..."): [state, far/near, ch]
    assert e3x.table[1, :, 46].tolist() == [10731, 27406]
    assert e3x.table[4, :, 46].tolist() == [38509, 55184]
    ot = hesai.load_firetimes(_file("OT128"))
    assert (ot.kind, ot.lasers, ot.states) == ("state", 128, ((0, 0), (0, 1), (0, 2), (0, 3),
                                                              (2, 0), (2, 1)))
    assert ot.table is not None   # channel 1: "1,-,18.867,-,18.867,46.645,46.645"
    assert ot.table[:, 0, 0].tolist() == [0, 18867, 0, 18867, 46645, 46645]
    assert (ot.table[:, 0] == ot.table[:, 1]).all()          # no near/far distinction
    qt = hesai.load_firetimes(_file("PandarQT"))
    assert (qt.kind, qt.lasers) == ("channel", 64)
    assert qt.channel_ns is not None and qt.channel_ns[0] == pytest.approx(2310.0)
    # every input form gives the same tables
    text = _file("OT128").read_text()
    for form in (text, text.encode(), "\ufeff" + text.replace("\n", "\r\n"), str(_file("OT128")),
                 ot):
        again = hesai.load_firetimes(form)
        assert again.table is not None and (again.table == ot.table).all()


#: model -> (firetime file, our reference minus the file's: each file has its own zero)
BUILT_IN = {"Pandar40P": ("Pandar40P", 0.0), "Pandar64": ("Pandar64", 0.0),
            "PandarXT16": ("PandarXT-16", -5632.0), "PandarXT32": ("PandarXT-32", -5632.0),
            "PandarXT32M": ("PandarXT-32M2X", -5632.0), "PandarQT64": ("PandarQT", 10000.0)}


@pytest.mark.parametrize("model", sorted(BUILT_IN))
def test_vendor_file_agrees_with_the_built_in_table(model: str) -> None:
    name, shift = BUILT_IN[model]
    ft = hesai.load_firetimes(_file(name))
    built_in = np.asarray(hesai.FORMATS[model].channel_ns)
    assert ft.kind == "channel" and ft.channel_ns is not None
    assert np.abs(ft.channel_ns + shift - built_in).max() < 0.5      # ns


@pytest.mark.parametrize("name", ["hesai_pandar64", "hesai_xt32", "hesai_qt64"])
def test_a_per_channel_file_that_agrees_changes_nothing(name: str) -> None:
    file = {"hesai_pandar64": "Pandar64", "hesai_xt32": "PandarXT-32",
            "hesai_qt64": "PandarQT"}[name]
    packets = _packets(name)[:400]
    csv_path = NEBULA / name / RECORDINGS[name][0]
    plain = list(hesai.decode_packets(packets, csv_path, as_dataclass=True))
    timed = list(hesai.decode_packets(packets, csv_path, as_dataclass=True,
                                      firetimes=_file(file)))
    _same(plain, timed)
    meta = json.loads(timed[0][1].vendor_metadata)
    assert meta.pop("firetimes") == "per channel"
    assert meta == json.loads(plain[0][1].vendor_metadata)


def test_a_per_channel_file_replaces_the_built_in_offsets() -> None:
    text = "Channel,fire time(us)\n" + "".join(f"{k + 1},{2.5 * k}\n" for k in range(32))
    packets = _packets("hesai_xt32")[:100]
    csv_path = NEBULA / "hesai_xt32" / RECORDINGS["hesai_xt32"][0]
    scan, info = next(hesai.decode_packets(packets, csv_path, as_dataclass=True,
                                           firetimes=text))
    ids = np.asarray(info.beam_ids)
    assert np.asarray(info.beam_time_offsets).tolist() == [2500 * (int(i) - 1) for i in ids]


GOOD_128 = _file("Pandar128E3X").read_text(encoding="utf-8-sig").splitlines()
GOOD_OT = _file("OT128").read_text().splitlines()
GOOD_CH = _file("PandarXT-16").read_text(encoding="utf-8-sig").splitlines()


def _edit(lines: list[str], row: int, text: str) -> str:
    return "\n".join(lines[:row] + [text] + lines[row + 1:]) + "\n"


MALFORMED = {
    "empty": ("\n\n", "firetimes"),
    "unknown header": (_edit(GOOD_CH, 0, "Laser,Elevation,Azimuth"), "firetimes line 1"),
    "unit not us": (_edit(GOOD_CH, 0, "Channel,fire time(ms)"), "line 1 column 2"),
    "channel not a number": (_edit(GOOD_CH, 3, "x,9.0"), "line 4 column 1"),
    "time not a number": (_edit(GOOD_CH, 3, "3,abc"), "line 4 column 2"),
    "time not finite": (_edit(GOOD_CH, 3, "3,nan"), "line 4 column 2"),
    "extra cell": (_edit(GOOD_CH, 3, "3,9.0,1"), "line 4"),
    "repeated channel": (_edit(GOOD_CH, 3, "2,9.0"), "repeated \\[2\\]"),
    "128: mode row": (_edit(GOOD_128, 1, GOOD_128[1].replace("operation mode", "mode")),
                      "line 2 column 1"),
    "128: state row short": (_edit(GOOD_128, 2, GOOD_128[2].rsplit(",", 1)[0]), "line 3"),
    "128: unknown state": (_edit(GOOD_128, 1, GOOD_128[1].replace(",3,3,3,3", ",9,3,3,3")),
                           "column 14"),
    "128: far/near label": (_edit(GOOD_128, 0, GOOD_128[0].replace("distance<A1", "d", 1)),
                            "line 1 column 3"),
    "128: two far columns": (_edit(GOOD_128, 0, GOOD_128[0].replace("distance<A1",
                                                                     "distance>=A1", 1)),
                             "operational state 0, azimuth state 0"),
    "128: negative time": (_edit(GOOD_128, 3, GOOD_128[3].replace(",", ",-", 1)),
                           "line 4 column 2"),
    "128: short row": (_edit(GOOD_128, 10, GOOD_128[10].rsplit(",", 1)[0]), "line 11"),
    "128: missing channel": ("\n".join(GOOD_128[:7] + GOOD_128[8:]) + "\n",
                             "firetimes channels"),
    "OT: state row": (_edit(GOOD_OT, 1, "Azimuth,0,1,2,3,0,1"), "line 2 column 1"),
    "OT: time": (_edit(GOOD_OT, 5, "4,6.289,x,6.289,-,6.289,6.289"), "line 6 column 3"),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_files_name_the_line_and_column(case: str) -> None:
    text, where = MALFORMED[case]
    with pytest.raises(LidarScanError, match=where):
        hesai.load_firetimes(text)


def test_unreadable_sources_raise() -> None:
    with pytest.raises(DecodeError, match="firetimes"):
        hesai.load_firetimes(FIRETIMES / "missing.csv")
    with pytest.raises(DecodeError, match="firetimes"):
        hesai.load_firetimes(3.5)
    with pytest.raises(DecodeError, match="UTF-8"):
        hesai.load_firetimes(b"\xff\xfe\n")


# --------------------------------------------------------------- 128 series: pixel times
def _vendor_table(path: Path) -> tuple[dict[tuple[int, int, int], list[int]], float]:
    """(op state, azimuth state, 0 far / 1 near) -> ns per channel index; near/far distance."""
    rows = list(csv.reader(io.StringIO(path.read_text(encoding="utf-8-sig"))))
    if rows[0][0] == "Operational State":      # OT128: us, '-' = not fired, no near/far
        ops, azs, body, near = rows[0][1:], rows[1][1:], rows[2:], 0.0
        sides = [0] * len(ops)
    else:                                      # Pandar128E3X: ns, far and near columns
        near = float(rows[0][0])
        sides = [1 if c == "distance<A1" else 0 for c in rows[0][1:]]
        ops, azs, body = rows[1][1:], rows[2][1:], rows[3:]
    out: dict[tuple[int, int, int], list[int]] = {}
    for j, (op, az, side) in enumerate(zip(ops, azs, sides)):
        values = [0 if r[j + 1] == "-" else round(float(r[j + 1]) * (1000 if not near else 1))
                  for r in sorted(body, key=lambda r: int(r[0]))]
        for s in ((0, 1) if rows[0][0] == "Operational State" else (side,)):
            out[(int(op), int(az), s)] = values
    return out, near


def _pixel_oracle(packets: list[bytes], calib: str, path: Path
                  ) -> list[tuple[int, int, str, float, float, float]]:
    """test_hesai_models.oracle's points with each pixel's time from the vendor file."""
    table, near_m = _vendor_table(path)
    out = []
    for pk in packets:
        points = oracle([pk], calib)
        blocks, dis_mm, flags = pk[7], pk[9], pk[11]
        unit = 4 if flags & 0x10 else 3
        tail = 12 + blocks * (2 + unit * 128) + 4 + (17 if flags & 0x04 else 0)
        az_state = struct.unpack_from("<H", pk, tail + 9)[0]
        op = pk[tail + 11]
        mode = pk[tail + 12]
        op_t = op if any(k[0] == op for k in table) else 2     # energy saving: standard's
        kinds = _modes(P128)[mode]
        returns = len(kinds)
        primary = (0 if returns == 1 else kinds.index("strongest") if "strongest" in kinds
                   else kinds.index("last"))
        y, mo, d, h, mi, s = pk[tail + 15:tail + 21]
        t0 = (calendar.timegm((1900 + y, mo, d, h, mi, s, 0, 0, 0)) * 10**9
              + struct.unpack_from("<I", pk, tail + 21)[0] * 1000)
        firings = blocks // returns
        times = {}
        for k in range(firings):
            b = k * returns + primary                 # the block of the 'range' return
            flag = (az_state >> (14 - 2 * b)) & 3
            for ch in range(128):
                raw = struct.unpack_from("<H", pk, 12 + b * (2 + unit * 128) + 2 + ch * unit)[0]
                side = 1 if raw * dis_mm * 1e-3 < near_m else 0
                dt = table.get((op_t, flag, side), [0] * 128)[ch]
                times[(k, ch)] = t0 + _firing_ns(P128, k, firings, ch, state=op) + dt
        # map oracle points (in packet order: block, channel) to their firing
        i = 0
        for b in range(blocks):
            k = b // returns
            for ch in range(128):
                raw = struct.unpack_from("<H", pk, 12 + b * (2 + unit * 128) + 2 + ch * unit)[0]
                if raw:
                    t, lid, name, *xyz = points[i]
                    assert lid == ch + 1
                    out.append((times[(k, ch)], lid, name, *xyz))
                    i += 1
    return out


def _stream128(mode: int, op_state: int, packets: int = 24, seed: int = 5, flags: int = 0x01,
               start: int = 35700) -> list[tuple[int, bytes]]:
    """128-series packets whose azimuth states change from packet to packet (0..3 in high
    performance mode, 0..1 otherwise) and a third of whose distances are near field."""
    m = MODELS[P128]
    returns = len(_modes(P128)[mode])
    firings = m["blocks"] // returns
    rng = np.random.default_rng(seed)
    out = []
    for p in range(packets):
        az = [(start + (p * firings + k) * 20) % 36000 for k in range(firings)
              for _ in range(returns)]
        dist = rng.integers(1, 65536, (m["blocks"], 128))
        near = rng.random(dist.shape) < 0.35
        dist[near] = rng.integers(1, 713, int(near.sum()))          # < 2.85 m at 4 mm
        dist[rng.random(dist.shape) < 0.15] = 0
        refl = rng.integers(0, 256, dist.shape)
        states = rng.integers(0, 4 if op_state == 0 else 2, 2)
        az_state = (int(states[0]) << 14) | (int(states[1]) << 12)
        us = US + p * 200
        out.append((us * 1000, build_packet(P128, mode, az, dist, refl, us=us, flags=flags,
                                            azimuth_state=az_state, op_state=op_state)))
    return out


@pytest.mark.parametrize("name", ["Pandar128E3X", "OT128"])
@pytest.mark.parametrize("mode", [0x37, 0x39, 0x3C])
@pytest.mark.parametrize("op_state", [0, 2, 3])
def test_128_pixel_times_against_the_loop_oracle(name: str, mode: int, op_state: int) -> None:
    calib = _calibration_csv(128, seed=9)
    packets = _stream128(mode, op_state, flags=0x11 if mode == 0x3C else 0x01)
    results = list(hesai.decode_packets(packets, calib, as_dataclass=True,
                                        firetimes=_file(name)))
    assert results
    _compare(_pixel_oracle([p for _, p in packets], calib, _file(name)), _decoded(results))
    scan, info = results[0]
    meta = json.loads(info.vendor_metadata)
    assert meta["firetimes"] == "per pixel (state table)"
    assert meta["channel_timing"].startswith("per pixel: channel 't'")
    assert np.asarray(info.beam_time_offsets).tolist() == [0] * 128
    # push() and push_many() give the same
    dec = hesai.PacketDecoder(calib, as_dataclass=True, firetimes=_file(name))
    one = [r for t, p in packets for r in dec.push(t, p)] + dec.flush()
    _same(results, one)
    stamps, rows = _rows(packets)
    dec = hesai.PacketDecoder(calib, as_dataclass=True, firetimes=_file(name))
    _same(results, dec.push_many(stamps, rows) + dec.flush())


def test_128_near_field_and_not_fired_channels() -> None:
    """One hand-checked pixel per case, from the Pandar128E3X file's rows 47 and 1."""
    calib = {i + 1: (10.0 - 0.1 * i, 0.0) for i in range(128)}        # row u = channel u + 1
    dist = np.full((2, 128), 2000)                                  # 8 m: far
    dist[1, 46] = 500                                               # 2 m: near
    packets = [(US * 1000 + p * 10**5, build_packet(
        P128, 0x37, [100 + 40 * p, 120 + 40 * p], dist, np.ones((2, 128)),
        azimuth_state=0, op_state=2, us=US + 100 * p)) for p in range(3)]
    scan, _ = next(hesai.decode_packets(packets, calib, as_dataclass=True,
                                        firetimes=_file("Pandar128E3X")))
    t = lidarscan.scan.channel(scan, "t")
    assert t[46, 0] == 38509 and t[46, 1] == 55184        # standard, azimuth state 0, far/near
    packets = [(US * 1000 + p * 10**5, build_packet(
        P128, 0x37, [100 + 40 * p, 120 + 40 * p], dist, np.ones((2, 128)), azimuth_state=0,
        op_state=0, us=US + 100 * p)) for p in range(3)]
    scan, _ = next(hesai.decode_packets(packets, calib, as_dataclass=True,
                                        firetimes=_file("Pandar128E3X")))
    t = lidarscan.scan.channel(scan, "t")
    assert t[0, 0] == 4436 and t[1, 0] == 0              # high performance, state 0: ch 2 idle


@pytest.mark.parametrize("stream,file,match", [
    ("Pandar128E3X/E4X", "Pandar64", "firetimes channels"),
    ("Pandar128E3X/E4X", "per-channel-128", "state table"),
    ("PandarXT16", "Pandar128E3X", "firetimes channels"),
    ("PandarXT16", "XT-16-as-state", "one time per channel"),
    ("PandarQT128", "Pandar128E3X", "firing loops are built in"),
])
def test_a_file_of_another_model_raises(stream: str, file: str, match: str) -> None:
    if file == "per-channel-128":
        source: Any = "Channel,fire time(us)\n" + "".join(f"{k},1.0\n" for k in range(1, 129))
    elif file == "XT-16-as-state":
        source = ("Operational State,2,2\nAzimuth State,0,1\n"
                  + "".join(f"{k},1.0,2.0\n" for k in range(1, 17)))
    else:
        source = _file(file)
    from test_hesai_models import _stream
    packets = _stream(stream, 0x37, packets=4)
    lasers = MODELS[stream]["lasers"]
    with pytest.raises(ConfigError, match=match):
        list(hesai.decode_packets(packets, _calibration_csv(lasers), firetimes=source))


def test_a_file_without_the_packets_state_raises() -> None:
    text = "Operational State,2,2\nAzimuth State,0,1\n" + "".join(
        f"{k},1.0,2.0\n" for k in range(1, 129))
    with pytest.raises(DecodeError, match="high resolution"):
        list(hesai.decode_packets(_stream128(0x37, 0, packets=4), _calibration_csv(128),
                                  firetimes=text))
    # energy saving uses standard's columns
    results = list(hesai.decode_packets(_stream128(0x37, 3, packets=30), _calibration_csv(128),
                                        firetimes=text, as_dataclass=True))
    assert results and "t" in [c.name for c in results[0][0].channels]


def test_without_a_file_nothing_changes() -> None:
    packets = _stream128(0x39, 2)
    scan, info = next(hesai.decode_packets(packets, _calibration_csv(128), as_dataclass=True))
    assert "t" not in [c.name for c in scan.channels]
    assert "firetimes" not in json.loads(info.vendor_metadata)


# ------------------------------------------------------------------------------------ CLI
def test_convert_takes_firetimes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`lidarscan convert --firetimes FILE`: the decoder gets the file (the Pandar64 vendor
    file agrees with the built-in table: same scans, the info says so); a file that cannot
    be read or packets whose decoder takes none: exit 2 naming the problem."""
    from converters.edge import cli
    from lidarscan.mcap import read_scans

    bag, calib = NEBULA / "hesai_pandar64" / "bag", NEBULA / "hesai_pandar64" / "Pandar64.csv"
    outs = {}
    for key, extra in (("plain", []), ("timed", ["--firetimes", str(_file("Pandar64"))])):
        outs[key] = tmp_path / f"{key}.mcap"
        status = cli.main(["convert", str(bag), str(outs[key]), "--calibration", str(calib),
                           "-q", *extra])
        assert status == 0, capsys.readouterr().err
    plain, timed = (list(read_scans(outs[k])) for k in ("plain", "timed"))
    assert len(plain) == len(timed) > 0
    for (a, ia), (b, ib) in zip(plain, timed):
        assert bytes(a.data) == bytes(b.data)
        assert "firetimes" in json.loads(ib.vendor_metadata)
    status = cli.main(["convert", str(bag), str(tmp_path / "bad.mcap"), "--calibration",
                       str(calib), "-q", "--firetimes", str(tmp_path / "missing.csv")])
    err = capsys.readouterr().err
    assert status == 2 and "firetimes" in err and not (tmp_path / "bad.mcap").exists(), err
    vlp = NEBULA / "velodyne_vlp32"
    status = cli.main(["convert", str(vlp / "bag"), str(tmp_path / "v.mcap"), "--calibration",
                       str(vlp / "VLP32.yaml"), "-q", "--firetimes", str(_file("Pandar64"))])
    err = capsys.readouterr().err
    assert status == 2 and "--firetimes" in err and not (tmp_path / "v.mcap").exists(), err
