"""Golden digests of the Velodyne packet decoder's output (bit-identity across rewrites).

Each case decodes a fixed packet stream and hashes, per rotation, every byte the decoder
produces: the scan's header, channel descriptors and data block, ``column_azimuth_angles`` and
``column_time_offsets``, and every field of its LidarInfo. The digests below were recorded with
the decoder as it was before the fused per-rotation kernel (2026-11-25, the two-pass decoder
with ``make_scan``); a faster decoder must reproduce them exactly. Cases: the real VLP-32C and
VLS-128 recordings of ``tests/data/nebula`` (single return) and synthetic streams of every
model in every return mode, each with ``azimuth_model`` "nebula" and "manual", through
``decode_packets`` (``push_many`` of byte runs), ``push`` one packet at a time and
``push_many`` in odd-sized batches; with the C kernel (``converters/_kernels/_velokernel.c``,
when built) and with the numpy reference path (``LIDARSCAN_NO_KERNEL=1``).

Run ``python tests/test_velodyne_golden.py`` to print the digests of the current decoder.
"""

from __future__ import annotations

import dataclasses
import hashlib
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))

from converters.sources.velodyne import MODELS, PacketDecoder, decode_packets  # noqa: E402

DATA = Path(__file__).parent / "data" / "nebula"
REAL = {"velodyne_vlp32": ("VLP32.yaml", 180.0), "velodyne_vls128": ("VLS128.yaml", 0.0)}
MODES = {"strongest": 0x37, "last": 0x38, "dual": 0x39}
PRODUCTS = {"VLP-16": 0x22, "Puck Hi-Res": 0x24, "VLP-32C": 0x28, "HDL-32E": 0x21,
            "VLS-128": 0xA1}


def _update(h: Any, value: Any) -> None:
    if isinstance(value, np.ndarray):
        h.update(f"{value.dtype.str}{value.shape}".encode())
        h.update(np.ascontiguousarray(value).tobytes())
    elif dataclasses.is_dataclass(value):
        for field in dataclasses.fields(value):
            h.update(field.name.encode())
            _update(h, getattr(value, field.name))
    elif isinstance(value, (list, tuple)):
        h.update(f"[{len(value)}".encode())
        for item in value:
            _update(h, item)
    else:
        h.update(repr(value).encode())


def digest(results: list[tuple[Any, Any]]) -> str:
    """sha256 (first 16 hex digits) of every scan and info field of the decoded rotations."""
    h = hashlib.sha256()
    h.update(f"{len(results)}".encode())
    for scan, info in results:
        _update(h, scan)
        _update(h, info)
    return h.hexdigest()[:16]


_PACKETS: dict[str, list[tuple[int, bytes]]] = {}


def _real_packets(folder: str, tmp_path: Path) -> list[tuple[int, bytes]]:
    from test_velodyne_packets import _read_bag
    if folder not in _PACKETS:
        _PACKETS[folder] = [p for _, pk in _read_bag(DATA / folder, tmp_path) for p in pk]
    return _PACKETS[folder]


def _synthetic(name: str, mode: str) -> tuple[list[tuple[int, bytes]], dict[str, Any]]:
    from converters.sources.velodyne.packets import _layout
    from test_velodyne_packets import _random_calibration, synthetic_stream
    product = PRODUCTS[name]
    per_packet = _layout(product, MODES[mode]).sequences       # ~3.3 turns, then a slower one
    packets = synthetic_stream(product, MODES[mode], -(-700 // per_packet),
                               seed=product + MODES[mode], deg_per_sequence=1.7,
                               start_deg=200.0)
    packets += synthetic_stream(product, MODES[mode], 40, seed=3, deg_per_sequence=0.9,
                                start_deg=10.0, stamp_ns=1_700_000_002_000_000_000)
    return packets, _random_calibration(MODELS[product].lasers, product)


def _three_ways(packets: list[tuple[int, bytes]], calib: Any, **kw: Any) -> list[str]:
    """Digests via decode_packets, push() per packet, push_many() in batches of 37."""
    out = [digest(list(decode_packets(packets, calib, as_dataclass=True, **kw)))]
    one = PacketDecoder(calib, as_dataclass=True, **kw)
    out.append(digest([r for s, d in packets for r in one.push(s, d)] + one.flush()))
    rows = np.frombuffer(b"".join(d for _, d in packets), np.uint8).reshape(-1, 1206)
    stamps = np.array([s for s, _ in packets], np.int64)
    many = PacketDecoder(calib, as_dataclass=True, **kw)
    got = []
    for i in range(0, len(rows), 37):
        got += many.push_many(stamps[i:i + 37], rows[i:i + 37])
    out.append(digest(got + many.flush()))
    return out


GOLDEN: dict[str, str] = {
    "velodyne_vlp32/nebula": "d53199ecc38d0725",
    "velodyne_vlp32/manual": "16ecabedc9434f5f",
    "velodyne_vls128/nebula": "e9d5323a139c7f0e",
    "velodyne_vls128/manual": "e90ca8691f90583f",
    "HDL-32E/dual/nebula": "1ddde32585d3e11f",
    "HDL-32E/dual/manual": "111a8690d8df59df",
    "HDL-32E/last/nebula": "904c0374ad0b9639",
    "HDL-32E/last/manual": "1f92714ace63bc40",
    "HDL-32E/strongest/nebula": "714588626923a49e",
    "HDL-32E/strongest/manual": "f7c0972950c3f580",
    "Puck Hi-Res/dual/nebula": "f2a09aa85d85ebe2",
    "Puck Hi-Res/dual/manual": "4ec2365fe3ccdb93",
    "Puck Hi-Res/last/nebula": "4ffbc581051009a2",
    "Puck Hi-Res/last/manual": "bd34d08f1e4a4895",
    "Puck Hi-Res/strongest/nebula": "453131ef76a21ef9",
    "Puck Hi-Res/strongest/manual": "450a923a5962414e",
    "VLP-16/dual/nebula": "4b29440e7d9e29d4",
    "VLP-16/dual/manual": "ba2efc99937f4b50",
    "VLP-16/last/nebula": "51d78bf8c90cba74",
    "VLP-16/last/manual": "ef17697bf35a15a2",
    "VLP-16/strongest/nebula": "960accdbb0effd84",
    "VLP-16/strongest/manual": "d616b24462e0a211",
    "VLP-32C/dual/nebula": "2fbe1d189db5e21f",
    "VLP-32C/dual/manual": "9e015abbe1ba0b77",
    "VLP-32C/last/nebula": "692a37ee3dd4778d",
    "VLP-32C/last/manual": "20a8b2fca813a5b7",
    "VLP-32C/strongest/nebula": "a215638a7fa353a0",
    "VLP-32C/strongest/manual": "9b6d377e0c6d895b",
    "VLS-128/dual/nebula": "ec27fc9eedfae4c0",
    "VLS-128/dual/manual": "7fa1f17e2c43c8a8",
    "VLS-128/last/nebula": "a71bc935ccb576eb",
    "VLS-128/last/manual": "0cd7b80b745b7327",
    "VLS-128/strongest/nebula": "530b706733edad05",
    "VLS-128/strongest/manual": "bc3de1c246087d0a",
}


def _cases() -> list[str]:
    real = [f"{folder}/{model}" for folder in sorted(REAL) for model in ("nebula", "manual")]
    synth = [f"{name}/{mode}/{model}" for name in sorted(PRODUCTS) for mode in sorted(MODES)
             for model in ("nebula", "manual")]
    return real + synth


def _compute(case: str, tmp_path: Path) -> list[str]:
    parts = case.split("/")
    if parts[0] in REAL:
        calib_name, cut = REAL[parts[0]]
        from converters.sources.velodyne import load_calibration
        calib = load_calibration(DATA / parts[0] / calib_name)
        packets = _real_packets(parts[0], tmp_path)
        return _three_ways(packets, calib, cut_angle_deg=cut, azimuth_model=parts[1])
    packets, calib = _synthetic(parts[0], parts[1])
    return _three_ways(packets, calib, azimuth_model=parts[2])


@pytest.mark.parametrize("case", _cases())
def test_decoder_output_is_bit_identical_to_the_golden_digest(case: str,
                                                              tmp_path: Path) -> None:
    got = _compute(case, tmp_path)
    assert got == [GOLDEN[case]] * 3


@pytest.mark.parametrize("case", ["velodyne_vls128/nebula", "VLS-128/dual/nebula",
                                  "VLP-16/dual/nebula", "HDL-32E/strongest/manual"])
def test_numpy_reference_path_is_bit_identical(case: str, tmp_path: Path,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("LIDARSCAN_NO_KERNEL", "1")
    monkeypatch.setenv("LIDARSCAN_NUMBA", "0")
    from converters._kernels import select
    assert select("velodyne").c is None
    assert _compute(case, tmp_path) == [GOLDEN[case]] * 3


@pytest.mark.parametrize("enabled", [False, True], ids=["numpy", "C kernel"])
def test_every_golden_digest_with_the_c_kernel_disabled_and_enabled(
        enabled: bool, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from converters._kernels import select, velodyne
    monkeypatch.setenv("LIDARSCAN_NO_KERNEL", "0" if enabled else "1")
    if enabled and velodyne.library() is None:
        pytest.skip("converters._kernels._velokernel is not built")
    assert (select("velodyne").c is not None) == enabled
    for case in _cases():
        assert _compute(case, tmp_path) == [GOLDEN[case]] * 3, case


@pytest.mark.parametrize("turns", [-0.9, 0.9, 1.2])
def test_c_kernel_rounds_large_rotations_like_the_reference(
        turns: float, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """rot_correction of +-0.9 * 1e6 centidegrees (the C kernel's float32 rounding still exact)
    and beyond its limit (1.2e6: the decoder takes the numpy path): the same bytes as numpy."""
    from converters._kernels import velodyne
    from test_velodyne_packets import synthetic_stream
    if velodyne.library() is None:
        pytest.skip("converters._kernels._velokernel is not built")
    packets, calib = _synthetic("VLS-128", "dual")
    rng = np.random.default_rng(7)
    limit = velodyne.MAX_ROTATION / 100.0 * np.pi / 180.0           # radians
    for las in calib["lasers"]:
        las["rot_correction"] = float(turns * limit * rng.uniform(0.9, 1.0))
    packets = packets[:300] + synthetic_stream(0xA1, 0x39, 200, seed=9, deg_per_sequence=37.0)
    dec = PacketDecoder(calib, as_dataclass=True)
    got = [r for s, d in packets for r in dec.push(s, d)] + dec.flush()
    assert len(got) >= 3 and dec._tables is not None
    assert (dec._tables.plan is not None) == (abs(turns) < 1.0)     # the kernel, or numpy
    kernel = digest(got)
    assert digest(list(decode_packets(packets, calib, as_dataclass=True))) == kernel  # by table
    monkeypatch.setenv("LIDARSCAN_NO_KERNEL", "1")
    assert digest(list(decode_packets(packets, calib, as_dataclass=True))) == kernel


if __name__ == "__main__":
    import tempfile
    with tempfile.TemporaryDirectory() as tmp:
        for c in _cases():
            values = _compute(c, Path(tmp))
            print(f'    "{c}": "{values[0]}",' + ("" if len(set(values)) == 1
                                                    else f"  # DIFFER {values}"))
