"""lidarscan.codec: the compressed LidarScan format restores every byte of the scan.

Layers: golden bytes of the format (decoded, and re-encoded with the zstd library they were made
with), loop-based oracles of the predictors and zigzag, round trips on hypothesis scans (shapes,
every datatype, counts, both byte orders, arbitrary bytes including NaN payloads, +-Inf, -0,
padding bytes and trailing bytes), round trips of the real Ouster frames, and damaged buffers.
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import lidarscan as ls
from lidarscan import codec
from lidarscan.errors import DecodeError
from lidarscan.types import LidarChannel, LidarScan

# compress_scan(_golden_scan()) with zstandard 0.25.0 (libzstd 1.5.7), level 3
GOLDEN = bytes.fromhex(
    "4c53435a010002006700000028b52ffd248cd5020042840e1ac03573ef023affff9d0b242e9d6cc8adeb3f69"
    "dd9d254e92c814277e3cf018a0add7d88df4c534e5120115a20fc860756a61cd8b44a0fcf90c0c00df206c0a"
    "49684c176c319501ce023030180832af981d2a7097cd26e2be558b2400000000000000180000000201000425"
    "00000028b52ffd2418c1000000000000006f00000000001280208000c0833f407f807f424a699d9518000000"
    "0c000000031000040002000000030000000100000000001900000028b52ffd240c61000014161a2001000000"
    "00030000eb5f80ad")


def _golden_scan() -> Any:
    info = ls.make_info(stamp_ns=1_500_000_000, frame_id="lidar",
                        vertical_angles=np.radians([5.0, -5.0]),
                        horizontal_angles=2 * np.pi * (1 - np.arange(3) / 3), as_dataclass=True)
    rng = np.array([[1.0, 2.5, np.inf], [np.float32(-0.0), np.nan, 65.536]], np.float32)
    inten = np.array([[10, 11, 13], [400, 65535, 0]], np.uint16)
    return ls.make_scan(info, {"range": rng, "intensity": inten}, 1_600_000_000,
                        column_time_offsets=[0, 1000, 2000], as_dataclass=True)


def _same(a: Any, b: Any) -> None:
    assert ls.encode(a) == ls.encode(b)


# ----------------------------------------------------------------------------- golden

def test_golden_bytes_decode_to_the_golden_scan() -> None:
    back = codec.decompress_scan(GOLDEN)
    _same(back, _golden_scan())
    r = ls.channel(back, "range")
    assert np.signbit(r[1, 0]) and r[1, 0] == 0 and np.isnan(r[1, 1]) and np.isposinf(r[0, 2])


def test_golden_layout_magic_version_and_methods() -> None:
    assert GOLDEN[:8] == b"LSCZ" + bytes([1, 0]) + struct.pack("<H", 2)
    segs = codec.segments(GOLDEN)
    assert [(s["offset"], s["length"], s["method"]) for s in segs] == [
        (0, 24, "shuffle"), (24, 12, "predict")]
    # six floats, four of them exceptions: byte planes are smaller than the grid
    assert segs[0]["params"] == bytes([4])
    # PREDICT params: UINT16, little-endian, 2 x 3 x 1, a predictor 0..3
    assert segs[1]["params"][:14] == struct.pack("<BBIII", 4, 0, 2, 3, 1)
    assert segs[1]["params"][14] in (0, 1, 2, 3)
    assert segs[1]["params"][15:] == b"\x00"  # not rolled: no row shifts


def test_golden_bytes_are_what_the_encoder_writes() -> None:
    import zstandard
    out = codec.compress_scan(_golden_scan())
    assert out[:8] == GOLDEN[:8]
    assert [(s["offset"], s["length"], s["method"], s["params"]) for s in codec.segments(out)] \
        == [(s["offset"], s["length"], s["method"], s["params"])
            for s in codec.segments(GOLDEN)]
    if zstandard.backend_features is not None and zstandard.__version__ == "0.25.0":
        assert out == GOLDEN


# ------------------------------------------------------------------------------ oracles

def _loop_residual(x: np.ndarray[Any, Any], predictor: int) -> list[int]:
    h, w, c = x.shape
    mod = 1 << (8 * x.dtype.itemsize)
    out = []
    for r in range(h):
        for col in range(w):
            for k in range(c):
                left = int(x[r, col - 1, k]) if col else 0
                up = int(x[r - 1, col, k]) if r else 0
                ul = int(x[r - 1, col - 1, k]) if r and col else 0
                pred = {0: 0, 1: left, 2: up, 3: left + up - ul}[predictor]
                out.append((int(x[r, col, k]) - pred) % mod)
    return out


@pytest.mark.parametrize("predictor", [0, 1, 2, 3])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.uint32])
def test_residuals_match_a_loop_and_invert(predictor: int, dtype: Any,
                                           rng: np.random.Generator) -> None:
    x = rng.integers(0, np.iinfo(dtype).max, (4, 5, 2), dtype=dtype, endpoint=True)
    r = codec._residual(x, predictor)
    assert r.reshape(-1).tolist() == _loop_residual(x, predictor)
    assert np.array_equal(codec._unresidual(r, predictor), x)


def test_zigzag_matches_the_definition() -> None:
    values = np.array([0, -1, 1, -2, 2, 127, -128], np.int8).view(np.uint8)
    assert codec._zigzag(values).tolist() == [0, 1, 2, 3, 4, 254, 255]
    assert np.array_equal(codec._unzigzag(codec._zigzag(values)), values)


def test_quant_keeps_grid_values_and_marks_everything_else_as_exception() -> None:
    v = np.array([[[1.0], [0.001], [np.inf], [-0.0], [np.nan], [1.0004], [-2.5]]], np.float32)
    q, exc = codec._quantise(v, 0.001)
    assert exc.reshape(-1).tolist() == [False, False, True, True, True, True, False]
    assert q.reshape(-1).tolist() == [1000, 1, 1, 1, 1, 1, -2500]  # exceptions: left neighbour


# ---------------------------------------------------------------------------- round trips

_FLOAT_SPECIALS = [np.inf, -np.inf, np.nan, -0.0, 0.0, 1.0, 65.535, 1e-40, 3e38]


@st.composite
def _scans(draw: Any) -> Any:
    height = draw(st.integers(1, 6))
    width = draw(st.integers(1, 9))
    big = draw(st.booleans())
    n = draw(st.integers(0, 4))
    channels = []
    chunks: list[bytes] = []
    offset = 0
    for i in range(n):
        datatype = draw(st.integers(1, 8))
        count = draw(st.integers(1, 3))
        size = {1: 1, 2: 1, 3: 2, 4: 2, 5: 4, 6: 4, 7: 4, 8: 8}[datatype]
        pad = draw(st.integers(0, 9))
        chunks.append(draw(st.binary(min_size=pad, max_size=pad)))
        offset += pad
        k = height * width * count
        if datatype in (7, 8) and draw(st.booleans()):  # mm grid values and specials
            values = np.array(draw(st.lists(
                st.one_of(st.integers(-10**6, 10**6).map(lambda m: m * 0.001),
                          st.sampled_from(_FLOAT_SPECIALS)), min_size=k, max_size=k)))
            block = values.astype((">" if big else "<") + ("f4" if size == 4 else "f8"))
            block = block.tobytes()
        else:
            block = draw(st.binary(min_size=k * size, max_size=k * size))
        channels.append(LidarChannel(f"c{i}", offset, datatype, count))
        chunks.append(block)
        offset += len(block)
    chunks.append(draw(st.binary(max_size=7)))  # trailing bytes
    data = np.frombuffer(b"".join(chunks), np.uint8)
    order = draw(st.permutations(range(len(channels))))
    return LidarScan(height=height, width=width, is_bigendian=big,
                     is_destaggered=draw(st.booleans()),
                     column_time_offsets=np.arange(width, dtype=np.int64) * 7,
                     channels=tuple(channels[i] for i in order), data=data)


@given(_scans(), st.sampled_from([None, 0.001]), st.sampled_from([1, 3]),
       st.lists(st.integers(-40, 40), min_size=1, max_size=6))
def test_roundtrip_is_bit_exact(scan: Any, step: float | None, level: int,
                                shifts: list[int]) -> None:
    from types import SimpleNamespace
    info = SimpleNamespace(pixel_shift_by_row=(shifts * 6)[:scan.height])
    buf = codec.compress_scan(scan, info if len(shifts) > 1 else None, level=level,
                              float_step=step)
    back = codec.decompress_scan(buf)
    _same(back, scan)
    assert back.data.tobytes() == scan.data.tobytes()


def test_roundtrip_of_overlapping_and_out_of_range_channels_falls_back_to_zstd() -> None:
    data = np.arange(40, dtype=np.uint8)
    for channels in ((LidarChannel("a", 0, 4, 1), LidarChannel("b", 2, 4, 1)),
                     (LidarChannel("a", 36, 6, 1),)):
        scan = LidarScan(height=2, width=2, channels=channels, data=data)
        buf = codec.compress_scan(scan)
        assert [s["method"] for s in codec.segments(buf)] == ["zstd"]
        _same(codec.decompress_scan(buf), scan)


def test_rclpy_scan_roundtrips_when_available() -> None:
    pytest.importorskip("lidarscan_msgs.msg")
    scan = ls.make_scan(_info(2, 3), {"range": np.ones((2, 3), np.float32)}, 5)
    _same(codec.decompress_scan(codec.compress_scan(scan)), scan)


def _info(h: int, w: int) -> Any:
    return ls.make_info(stamp_ns=1, frame_id="f", vertical_angles=np.zeros(h),
                        horizontal_angles=np.linspace(0, 1, w), as_dataclass=True)


@pytest.mark.parametrize("range_encoding", ["float32", "uint32_mm"])
@pytest.mark.parametrize("destagger", [False, True])
def test_real_frames_roundtrip_and_beat_zstd_of_the_buffer(range_encoding: str,
                                                           destagger: bool) -> None:
    import zstandard

    from converters.evidence._common import load_frame, ouster_files, ouster_info
    from converters.ouster import scan_from_frame
    for meta, frame_path in ouster_files():
        if frame_path is None:
            continue
        scan = scan_from_frame(load_frame(frame_path), ouster_info(meta), as_dataclass=True,
                               range_encoding=range_encoding, destagger=destagger)
        buf = codec.compress_scan(scan, ouster_info(meta))
        _same(codec.decompress_scan(buf), scan)
        rolled = [s["params"][15] for s in codec.segments(buf) if s["method"] == "predict"]
        assert set(rolled) == {int(not destagger)}  # staggered scans predicted destaggered
        whole = zstandard.ZstdCompressor(level=3).compress(scan.data.tobytes())
        assert len(buf) < 0.8 * len(whole), meta.name
        methods = {s["method"] for s in codec.segments(buf) if s["length"]}
        assert methods <= {"predict", "quant", "zstd"}
        assert ("quant" in methods) == (range_encoding == "float32")


# ------------------------------------------------------------------------------ errors

@pytest.mark.parametrize("mutate, match", [
    (lambda b: b"XXXX" + b[4:], "magic"),
    (lambda b: b[:4] + bytes([2]) + b[5:], "version"),
    (lambda b: b[:20], "bytes"),
    (lambda b: b + b"\x00", "trailing"),
    (lambda b: b[:6] + struct.pack("<H", 3) + b[8:], "bytes"),
])
def test_damaged_buffers_raise_decode_error(mutate: Any, match: str) -> None:
    with pytest.raises(DecodeError, match=match):
        codec.decompress_scan(mutate(GOLDEN))


def test_a_corrupt_payload_raises_decode_error() -> None:
    bad = bytearray(GOLDEN)
    bad[-8] ^= 0xFF  # a literal of the last zstd frame: its checksum fails
    with pytest.raises(DecodeError):
        codec.decompress_scan(bytes(bad))


def test_a_hand_built_raw_segment_decodes() -> None:
    """RAW (method 0) is never chosen by the encoder but is part of the format."""
    skeleton_len = struct.unpack_from("<I", GOLDEN, 8)[0]
    head = GOLDEN[:12 + skeleton_len]                      # magic .. skeleton
    data = _golden_scan().data.tobytes()
    buf = (head[:6] + struct.pack("<H", 1) + head[8:] + struct.pack("<I", len(data))
           + struct.pack("<IIBH", 0, len(data), codec.RAW, 0) + struct.pack("<I", len(data))
           + data)
    _same(codec.decompress_scan(buf), _golden_scan())
