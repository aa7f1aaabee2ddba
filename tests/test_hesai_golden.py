"""Golden digests of the Hesai packet decoder's output (bit-identity across rewrites).

Each case decodes a fixed packet stream and hashes, per rotation, every byte the decoder
produces: the scan's header, channel descriptors and data block (every channel),
``column_azimuth_angles`` and ``column_time_offsets``, and every field of its LidarInfo. The
digests below were recorded with the decoder as it was before the speed work of 2026-11-25
(main's per-rotation units kernel); a faster decoder must reproduce them exactly. Exception, on
purpose: the Pandar128E3X/E4X cases were re-recorded after the 128 series got the manual's
block start times (t0 + 3.148 us) and its operational state (standard / high resolution) in
the same change set; the speed work alone had left their old digests unchanged.

Cases: the real Pandar64, PandarXT32 and PandarQT64 recordings of ``tests/data/nebula`` (sensor
and receive time sources) and the synthetic streams the other Hesai tests build, of every model
in every return mode they accept (``test_hesai._stream``: Pandar40P, Pandar64, PandarXT32,
PandarQT64, 2.3 turns; ``test_hesai_models._stream``: PandarXT16, PandarXT32M, PandarQT128,
Pandar128E3X/E4X, 150 packets, several wraps; the QT128 and 128-series also with every optional
part of the header flags), each through ``decode_packets``, ``push`` one packet at a time and
``push_many`` in batches of 37; and the numpy reference path (no compiled kernel).

Run ``python tests/test_hesai_golden.py`` to print the digests of the current decoder.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))

from converters.sources.hesai import rotation as _hesai_rotation  # noqa: E402

from converters.sources.hesai import decoder as hesai
from test_velodyne_golden import digest  # noqa: E402  (the same hash of every field)

DATA = Path(__file__).parent / "data" / "nebula"
REAL = {"hesai_pandar64": "Pandar64.csv", "hesai_xt32": "PandarXT32.csv",
        "hesai_qt64": "PandarQT64.csv"}


def _three_ways(packets: list[tuple[int, bytes]], calib: Any, **kw: Any) -> list[str]:
    """Digests via decode_packets, push() per packet, push_many() in batches of 37."""
    out = [digest(list(hesai.decode_packets(packets, calib, as_dataclass=True, **kw)))]
    one = hesai.PacketDecoder(calib, as_dataclass=True, **kw)
    out.append(digest([r for s, d in packets for r in one.push(s, d)] + one.flush()))
    size = len(packets[0][1])
    rows = np.frombuffer(b"".join(d for _, d in packets), np.uint8).reshape(-1, size)
    stamps = np.array([s for s, _ in packets], np.int64)
    many = hesai.PacketDecoder(calib, as_dataclass=True, **kw)
    got = []
    for i in range(0, len(rows), 37):
        got += many.push_many(stamps[i:i + 37], rows[i:i + 37])
    out.append(digest(got + many.flush()))
    return out


def _mode_name(mode: int) -> str:
    return "+".join(hesai.RETURN_MODES[mode])


def _cases() -> list[str]:
    import test_hesai
    import test_hesai_models
    real = [f"{name}/{ts}" for name in sorted(REAL) for ts in ("sensor", "receive")]
    old = [f"{model}/{_mode_name(mode)}" for model, mode in test_hesai.MODEL_MODES]
    new = [f"{model}/{_mode_name(mode)}" for model, mode in test_hesai_models.CASES]
    flags = [f"{model}/strongest/flags{f:#04x}" for model in ("PandarQT128", "Pandar128E3X/E4X")
             for f in (0x00, 0x1F)]
    states = [f"Pandar128E3X/E4X/{mode}/state{state}" for mode in ("strongest", "last+strongest")
              for state in (0, 3)]
    return real + old + new + flags + states


def _compute(case: str) -> list[str]:
    import test_hesai
    import test_hesai_models
    parts = case.split("/")
    if parts[0] in REAL:
        csv = DATA / parts[0] / REAL[parts[0]]
        return _three_ways(test_hesai._packets(parts[0]), csv, time_source=parts[1])
    if parts[0] == "Pandar128E3X":
        parts = ["Pandar128E3X/E4X", *parts[2:]]
    model, mode_name = parts[0], parts[1]
    mode = next(m for m, kinds in hesai.RETURN_MODES.items() if "+".join(kinds) == mode_name)
    if model in test_hesai.LAYOUT:
        csv = test_hesai._calibration_csv(test_hesai.LAYOUT[model]["lasers"])
        packets = test_hesai._stream(model, mode, rotations=2.3, start=20000)
        return _three_ways(packets, csv)
    csv = test_hesai._calibration_csv(test_hesai_models.MODELS[model]["lasers"], seed=4)
    kw = {}
    if len(parts) > 2 and parts[2].startswith("flags"):
        kw = {"flags": int(parts[2][5:], 16)}
    elif len(parts) > 2:
        kw = {"op_state": int(parts[2][5:])}
    packets = test_hesai_models._stream(model, mode, packets=150, step=500, **kw)
    return _three_ways(packets, csv)


GOLDEN: dict[str, str] = {
    "hesai_pandar64/sensor": "4fb499a9577c401f",
    "hesai_pandar64/receive": "f33fe2b22ae597b8",
    "hesai_qt64/sensor": "10fafdc91ac1d2a3",
    "hesai_qt64/receive": "9528c4c014698a79",
    "hesai_xt32/sensor": "8e898cb19e770d3d",
    "hesai_xt32/receive": "d7744bcd26669c16",
    "Pandar40P/first": "e8012e586fcb30c0",
    "Pandar40P/strongest": "ad413b234c33b64d",
    "Pandar40P/last": "a4547ec754ac3e11",
    "Pandar40P/last+strongest": "134fd852ad0a7869",
    "Pandar64/first": "21b5c565807e8271",
    "Pandar64/strongest": "5d5882e01bcad0ae",
    "Pandar64/last": "cfdaa05bfdabaf69",
    "Pandar64/last+strongest": "db00eb3548570fbc",
    "PandarXT32/first": "d201de8232951aeb",
    "PandarXT32/strongest": "c0811341fa24aae7",
    "PandarXT32/last": "8d3b5c1e3f641c5a",
    "PandarXT32/last+strongest": "691eea091e6a8a6b",
    "PandarQT64/first": "07df1af97af49f8b",
    "PandarQT64/strongest": "ad1f8d80be759e17",
    "PandarQT64/last": "d2213050547b3eeb",
    "PandarQT64/first+last": "b4671826328ec21b",
    "PandarXT16/first": "c7fd74921b576c3f",
    "PandarXT16/strongest": "e4a289fe5aa198b5",
    "PandarXT16/last": "d30407dccdab0852",
    "PandarXT16/last+strongest": "6dd736ae4fab6a03",
    "PandarXT16/first+last": "c3d7f626a385ce57",
    "PandarXT16/first+strongest": "2073623f3cdac9ce",
    "PandarXT32M/first": "803a09ed8a8927a0",
    "PandarXT32M/strongest": "917272630193294f",
    "PandarXT32M/last": "249c240f2e06633f",
    "PandarXT32M/last+strongest": "4e1cb5e019f1812f",
    "PandarXT32M/first+last": "30c946b8aa2e283e",
    "PandarXT32M/first+strongest": "163c3626209595b1",
    "PandarXT32M/first+last+strongest": "2191be773ad274b7",
    "PandarQT128/first": "25ec7dc0e0454b0e",
    "PandarQT128/strongest": "71684b30bb3860f5",
    "PandarQT128/last": "4bfe278db566c7fc",
    "PandarQT128/last+strongest": "a592c2c4b66f65cd",
    "PandarQT128/first+last": "753519fb15edadc2",
    "PandarQT128/first+strongest": "eb9e88ef8f564a07",
    "Pandar128E3X/E4X/first": "04ab31dc9a028920",
    "Pandar128E3X/E4X/strongest": "e70f6b18a969ea03",
    "Pandar128E3X/E4X/last": "410f39c5178db1a0",
    "Pandar128E3X/E4X/last+strongest": "b4135fb0b09c1b64",
    "Pandar128E3X/E4X/first+last": "1d16d3bd749b4485",
    "Pandar128E3X/E4X/first+strongest": "7cbee09e7c0886fb",
    "PandarQT128/strongest/flags0x00": "71684b30bb3860f5",
    "PandarQT128/strongest/flags0x1f": "71684b30bb3860f5",
    "Pandar128E3X/E4X/strongest/flags0x00": "e70f6b18a969ea03",
    "Pandar128E3X/E4X/strongest/flags0x1f": "e70f6b18a969ea03",
    "Pandar128E3X/E4X/strongest/state0": "02a115118034dcb1",
    "Pandar128E3X/E4X/strongest/state3": "cf427114eb30f6c2",
    "Pandar128E3X/E4X/last+strongest/state0": "8fb9b6a703b57a54",
    "Pandar128E3X/E4X/last+strongest/state3": "e390ac8b054081e9",
}


@pytest.mark.parametrize("case", _cases())
def test_decoder_output_is_bit_identical_to_the_golden_digest(case: str) -> None:
    assert _compute(case) == [GOLDEN[case]] * 3


@pytest.mark.parametrize("case", ["hesai_pandar64/sensor", "hesai_xt32/receive",
                                  "hesai_qt64/sensor", "PandarXT32M/first+last+strongest",
                                  "PandarQT128/last+strongest",
                                  "Pandar128E3X/E4X/strongest/flags0x1f",
                                  "Pandar128E3X/E4X/last+strongest/state0"])
def test_numpy_reference_path_is_bit_identical(case: str,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(_hesai_rotation, "_KERNEL", None)   # where _units looks it up
    assert _compute(case) == [GOLDEN[case]] * 3


if __name__ == "__main__":
    for c in _cases():
        values = _compute(c)
        print(f'    "{c}": "{values[0]}",' + ("" if len(set(values)) == 1
                                                else f"  # DIFFER {values}"))
