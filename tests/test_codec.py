"""lidarscan.codec: the compressed LidarScan format restores every byte of the scan.

Layers: golden bytes of the format (version 2 decoded, and re-encoded with the zstd library they
were made with, by the numpy reference coder and by the compiled one; version 1 still
decoded), loop-based oracles of the predictors, zigzag, masked
pixels' fill and the bit-length coding, round trips on hypothesis scans (shapes,
every datatype, counts, both byte orders, arbitrary bytes including NaN payloads, +-Inf, -0,
padding bytes and trailing bytes), round trips of the real Ouster frames, and damaged buffers;
the compiled residual coder (numba, ``converters._kernels.select("codec")``) against the numpy
reference step by step and scan by scan (same bytes), also through the MCAP writer.
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import lidarscan as ls
from lidarscan import _codec_bits as cbits
from lidarscan import codec
from lidarscan.errors import DecodeError
from lidarscan.types import LidarChannel, LidarScan

# version 1: compress_scan(_golden_scan()) of the version 1 encoder, zstandard 0.25.0 (libzstd
# 1.5.7), level 3; it must stay decodable
GOLDEN_V1 = bytes.fromhex(
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

# version 2: compress_scan(_golden_scan_v2()) with zstandard 0.25.0 (libzstd 1.5.7), level 3
GOLDEN_V2 = bytes.fromhex(
    "4c53435a020003006a00000028b52ffd248ced0200f40300010000010000000046c323060000006c69646172"
    "0065cd1d0400000020000300000072616e6765070a000000696e74656e736974790200000b32000000000b00"
    "408009c3fd304f68f6c03600fb5765d633df5356c6c9e3dcd904b6edd04c3a00000020000000000000001d00"
    "000028b52ffd6400007d00002800d00007000310003c4a8858c4020e0748d60d00000028b52ffd2400010000"
    "99e9d851000400000000000000020000061a00070004000000200000000100000003000201fca9f1d24d6250"
    "3fb00000001d00000028b52ffd2410810000ffffffffeffffffffbfffffffefffffff54a4c893c00000028b5"
    "2ffd247d7d0100682f2020202525202527002720200f00301780859402204fa7056821e70060d72202e602ce"
    "021d212063cb0e124e0ba31813322e00000028b52ffd243c0d0100b8d6b5ad6b5a68637df7df7df7df7f6e7a"
    "e7aeb9eb9e9d000300801874ff83285a4daf3f301900000028b52ffd240c6100000000807f0000c07f000000"
    "80d86d3d8300020000000100000512000400040000002000000001000000030002019b0000001800000028b5"
    "2ffd24105d0000287bdef7bdef0100308a16e27affca4800000028b52ffd2466dd010034021c1c1c1c232025"
    "1c251c20252600001c1c00001c25261c2626170026260000172626000900b80168328069070ac13883c11856"
    "4605b99db93786026d282f00000028b52ffd2422110100faaaaaaaaaaaaaaaaa9aa9a9a9a9dee94a505145c0"
    "f18f40f40f3d040f40f40f40f04d5a40fc000300000001000005160004000400000020000000010000000400"
    "010000020000340000001d00000028b52ffd248085000038000d0011000f00020000271e140c01e1b75eb50f"
    "00000028b52ffd2402110000be92ee86b210")


def _golden_scan_v2() -> Any:
    """4 x 32: range on the mm grid with +Inf, NaN and -0 exceptions (QUANT2, masked),
    intensity with every fifth pixel zero (PREDICT2, zeros masked), intensity2 predicted
    from intensity (PREDICT2, REF)."""
    h, w = 4, 32
    info = ls.make_info(stamp_ns=1_500_000_000, frame_id="lidar",
                        vertical_angles=np.radians(np.linspace(5, -5, h)),
                        horizontal_angles=2 * np.pi * (1 - np.arange(w) / w), as_dataclass=True)
    mm = 1000 + 7 * np.arange(h * w).reshape(h, w) % 23 * 11
    rng = (mm * 0.001).astype(np.float32)
    rng[1, 3], rng[2, 5], rng[3, 7] = np.inf, np.nan, -0.0
    inten = (np.arange(h * w).reshape(h, w) * 37 % 200).astype(np.uint16)
    rows, cols = np.mgrid[:h, :w]
    inten[(rows + cols * 3) % 5 == 0] = 0
    second = inten.copy()  # a second return: mostly the first (REF predictor)
    second[0, 1], second[2, 9], second[3, 30] = 7, 0, 65535
    return ls.make_scan(info, {"range": rng, "intensity": inten, "intensity2": second},
                        1_600_000_000, column_time_offsets=np.arange(w) * 1000,
                        as_dataclass=True)


def test_golden_v1_bytes_still_decode_to_the_golden_scan() -> None:
    back = codec.decompress_scan(GOLDEN_V1)
    _same(back, _golden_scan())
    r = ls.channel(back, "range")
    assert np.signbit(r[1, 0]) and r[1, 0] == 0 and np.isnan(r[1, 1]) and np.isposinf(r[0, 2])
    assert [(s["offset"], s["length"], s["method"]) for s in codec.segments(GOLDEN_V1)] == [
        (0, 24, "shuffle"), (24, 12, "predict")]


def _coder(name: str) -> Any:
    """The residual coder ``name``: "numpy" (the reference, None) or "compiled" (skipped
    without numba)."""
    return None if name == "numpy" else _compiled()


@pytest.mark.parametrize("coder", ["numpy", "compiled"])
def test_golden_v2_bytes_decode_to_the_golden_scan(coder: str) -> None:
    back = codec.decompress_scan(GOLDEN_V2, coder=_coder(coder))
    _same(back, _golden_scan_v2())
    r = ls.channel(back, "range")
    assert np.isposinf(r[1, 3]) and np.isnan(r[2, 5]) and np.signbit(r[3, 7]) and r[3, 7] == 0


def test_golden_v2_layout_magic_version_and_methods() -> None:
    assert GOLDEN_V2[:8] == b"LSCZ" + bytes([2, 0]) + struct.pack("<H", 3)
    segs = codec.segments(GOLDEN_V2)
    assert [(s["offset"], s["length"], s["method"]) for s in segs] == [
        (0, 512, "quant2"), (512, 256, "predict2"), (768, 256, "predict2")]
    # QUANT2: FLOAT32, little-endian, 4 x 32 x 1, predictor, not rolled, extra, masked, step
    q = segs[0]["params"]
    assert q[:14] == struct.pack("<BBIII", 7, 0, 4, 32, 1)
    assert q[14] in (0, 1, 2, 3) and q[15] == 0 and q[16] in (1, 2) and q[17] == 1
    assert struct.unpack("<d", q[18:]) == (0.001,)
    p = segs[1]["params"]
    assert p[:14] == struct.pack("<BBIII", 4, 0, 4, 32, 1) and p[17] == 1 and len(p) == 18
    # intensity2: predictor 4 (REF) from the block at byte offset 512 (intensity)
    r = segs[2]["params"]
    assert r[14] == codec.REF and len(r) == 22 and struct.unpack("<I", r[18:]) == (512,)


def test_a_reference_after_its_block_raises_decode_error() -> None:
    params = codec.segments(GOLDEN_V2)[2]["params"]
    at = GOLDEN_V2.index(params) + 18  # intensity2's reference offset
    buf = bytearray(GOLDEN_V2)
    buf[at:at + 4] = struct.pack("<I", 768)  # itself: not decoded yet
    with pytest.raises(DecodeError, match="reference"):
        codec.decompress_scan(bytes(buf))


@pytest.mark.parametrize("shifts", [None, [3, 1, 0, 2]])
def test_second_returns_are_predicted_from_the_first_and_roundtrip(
        shifts: list[int] | None, rng: np.random.Generator) -> None:
    from types import SimpleNamespace
    first = rng.integers(0, 5000, (4, 64), dtype=np.uint16)
    second = np.where(rng.random(first.shape) < 0.9, first, rng.integers(0, 5000, first.shape))
    scan = ls.make_scan(_info(4, 64), {"range": first, "range2": second.astype(np.uint16)}, 5,
                        as_dataclass=True)
    buf = codec.compress_scan(scan, SimpleNamespace(pixel_shift_by_row=shifts)
                              if shifts else None)
    assert [s["params"][14] for s in codec.segments(buf)][1] == codec.REF
    _same(codec.decompress_scan(buf), scan)


@pytest.mark.parametrize("coder", ["numpy", "compiled"])
def test_golden_bytes_are_what_the_encoder_writes(coder: str) -> None:
    import zstandard
    out = codec.compress_scan(_golden_scan_v2(), level=3, coder=_coder(coder), version=2)
    _same(codec.decompress_scan(out, coder=_coder(coder)), _golden_scan_v2())
    assert out[:8] == GOLDEN_V2[:8]
    assert [(s["offset"], s["length"], s["method"], s["params"]) for s in codec.segments(out)] \
        == [(s["offset"], s["length"], s["method"], s["params"])
            for s in codec.segments(GOLDEN_V2)]
    if zstandard.backend_features is not None and zstandard.__version__ == "0.25.0":
        assert out == GOLDEN_V2


def test_a_version_1_buffer_may_not_hold_version_2_methods() -> None:
    head = struct.pack("<IIB", 24, 12, codec.PREDICT)  # the PREDICT segment of GOLDEN_V1
    bad = GOLDEN_V1.replace(head, struct.pack("<IIB", 24, 12, codec.PREDICT2))
    assert bad != GOLDEN_V1
    with pytest.raises(DecodeError, match="method"):
        codec.decompress_scan(bad)


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
    r = cbits.residual(x, predictor)
    assert r.reshape(-1).tolist() == _loop_residual(x, predictor)
    assert np.array_equal(cbits.unresidual(r, predictor), x)


def test_zigzag_matches_the_definition() -> None:
    values = np.array([0, -1, 1, -2, 2, 127, -128], np.int8).view(np.uint8)
    assert cbits.zigzag(values).tolist() == [0, 1, 2, 3, 4, 254, 255]
    assert np.array_equal(cbits.unzigzag(cbits.zigzag(values)), values)


def test_quant_keeps_grid_values_and_marks_everything_else_as_exception() -> None:
    v = np.array([[[1.0], [0.001], [np.inf], [-0.0], [np.nan], [1.0004], [-2.5]]], np.float32)
    q, exc = codec._quantise(v, 0.001)
    assert exc.reshape(-1).tolist() == [False, False, True, True, True, True, False]
    assert q.reshape(-1).tolist() == [1000, 1, 0, 0, 0, 0, -2500]  # exceptions: 0


def _loop_symbols(z: list[int], extra: int) -> tuple[list[int], str]:
    """Symbols and the low-bit stream (a '0'/'1' string) of the version 2 coding, by the
    definition in the module docstring."""
    symbols, groups = [], {}
    for v in z:
        b = v.bit_length()
        e = min(max(b - 1, 0), extra)
        k = max(b - 1 - e, 0)
        top = (v >> k) & ((1 << e) - 1)
        symbols.append(b << extra | top)
        groups.setdefault(k, []).append(format(v & ((1 << k) - 1), f"0{k}b") if k else "")
    return symbols, "".join("".join(groups[k]) for k in sorted(groups))


@given(st.lists(st.integers(0, 2**32 - 1) | st.integers(0, 40), max_size=60))
def test_bit_length_coding_matches_the_definition_and_inverts(values: list[int]) -> None:
    import zstandard
    z = np.array(values, np.uint32)
    extra, frame, low = codec._pack_residuals(z, 3)
    symbols, bits = _loop_symbols(values, extra)
    assert list(zstandard.ZstdDecompressor().decompress(frame)) == symbols
    stream = zstandard.ZstdDecompressor().decompress(low)
    assert "".join(format(x, "08b") for x in stream) == bits + "0" * (-len(bits) % 8)
    parts = codec._unpack_residuals(frame, low, len(values), 4, extra, "test")
    assert cbits.unpack(parts[0], extra, parts[1], parts[2]).tolist() == values


def _loop_fill(x: np.ndarray[Any, Any], valid: np.ndarray[Any, Any], predictor: int
               ) -> np.ndarray[Any, Any]:
    """Invalid pixels take their own prediction, in row-major order (Python ints, wrapping)."""
    h, w, c = x.shape
    mod = 1 << (8 * x.dtype.itemsize)
    f = [[[0] * c for _ in range(w)] for _ in range(h)]
    for r in range(h):
        for col in range(w):
            for k in range(c):
                if valid[r, col, k]:
                    f[r][col][k] = int(x[r, col, k])
                    continue
                left = f[r][col - 1][k] if col else 0
                up = f[r - 1][col][k] if r else 0
                ul = f[r - 1][col - 1][k] if r and col else 0
                f[r][col][k] = {0: 0, 1: left, 2: up, 3: left + up - ul}[predictor] % mod
    return np.array(f, x.dtype)


@pytest.mark.parametrize("predictor", [0, 1, 2, 3])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.uint32])
def test_masked_pixels_hold_their_prediction_and_cost_no_residual(
        predictor: int, dtype: Any, rng: np.random.Generator) -> None:
    x = rng.integers(0, np.iinfo(dtype).max, (5, 7, 2), dtype=dtype, endpoint=True)
    valid = rng.random(x.shape) < 0.6
    f = cbits.predicted_fill(x, valid, predictor)
    assert np.array_equal(f, _loop_fill(x, valid, predictor))
    assert not cbits.residual(f, predictor)[~valid].any()
    z = cbits.masked_residuals(x, valid, predictor)
    assert z.size == valid.sum()
    back = cbits.unmask_residuals(z, valid, x.shape, predictor)
    assert np.array_equal(back[valid], x[valid])


# ---------------------------------------------------------------------------- round trips

_INT = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4"}
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
        elif datatype <= 6 and draw(st.booleans()):  # small integers, many zeros (masked)
            values = np.array(draw(st.lists(st.sampled_from([0, 0, 0, 1, 2, 7, 100]),
                                            min_size=k, max_size=k)))
            block = values.astype((">" if big else "<") + _INT[datatype]).tobytes()
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


# -------------------------------------------------------------- compiled residual coder

def _compiled() -> Any:
    pytest.importorskip("numba")
    from converters._kernels import select
    coder = select("codec").numba
    if coder is None:
        pytest.skip("numba disabled (LIDARSCAN_NUMBA=0)")
    return coder


@given(st.lists(st.integers(0, 2**32 - 1) | st.integers(0, 300) | st.just(0), max_size=300))
def test_compiled_coder_matches_the_numpy_reference(values: list[int]) -> None:
    from lidarscan._codec_bits import NUMPY, bitlen_table
    coder = _compiled()
    z = np.array(values, np.uint32)
    ref = NUMPY.symbols(z, bitlen_table())
    got = coder.symbols(z, bitlen_table())
    for a, b in zip(ref[:4], got[:4], strict=True):
        assert a.dtype == b.dtype and a.tolist() == b.tolist()
    assert [int(ref[4]), int(ref[5])] == [int(got[4]), int(got[5])] \
        == [int(ref[1].sum()), int(ref[3].sum())]
    for extra, sym, k in ((1, ref[0], ref[1]), (2, ref[2], ref[3])):
        low = NUMPY.pack_low(z, k)
        assert coder.pack_low(z, k).tobytes() == low.tobytes()
        counts = NUMPY.low_counts(sym, extra)
        assert coder.low_counts(sym, extra).tolist() == counts.tolist()
        assert cbits.unpack(sym, extra, counts, low).tolist() == values
        if values:  # the compiled decoder's unpacking, a 1 x n grid predicted by NONE
            out = np.empty((1, len(values), 1), np.uint32)
            got_z = coder.decode(sym, extra, counts, low, None, cbits.NONE, None, out)
            assert got_z.reshape(-1).tolist() == cbits.unzigzag(z).tolist()


@given(st.integers(1, 5), st.integers(1, 7), st.integers(1, 2), st.sampled_from(["u1", "u2", "u4"]),
       st.integers(0, 4), st.booleans(), st.integers(0, 2**32 - 1))
def test_compiled_prediction_matches_the_numpy_reference(h: int, w: int, c: int, dtype: str,
                                                         predictor: int, masked: bool,
                                                         seed: int) -> None:
    from lidarscan._codec_bits import NUMPY
    coder = _compiled()
    rng = np.random.default_rng(seed)
    x = rng.integers(0, np.iinfo(dtype).max, (h, w, c), dtype=dtype, endpoint=True)
    ref = rng.integers(0, np.iinfo(dtype).max, (h, w, c), dtype=dtype, endpoint=True) \
        if predictor == cbits.REF else None
    valid = rng.random((h, w, c)) < 0.7 if masked else None
    x.setflags(write=False)  # as a view of a message's data: read, never written
    z = NUMPY.residuals(x, valid, predictor, ref)
    assert z.dtype == np.uint32
    costs = NUMPY.costs(x, valid, ref)
    assert costs[predictor] == sum(int(v).bit_length() for v in z.tolist())
    assert (costs[cbits.REF] == -1) == (ref is None)
    assert coder.costs(x, valid, ref).tolist() == costs.tolist()
    assert coder.residuals(x, valid, predictor, ref).tolist() == z.tolist()
    want = cbits.unmask_residuals(z.astype(x.dtype), valid, x.shape, predictor, ref)
    shifts = rng.integers(-3 * w, 3 * w, h)
    for sign in (1, -1):
        assert coder.roll(x, shifts, sign).tolist() == cbits.roll(x, shifts, sign).tolist()
    for extra in (1, 2):  # the decoder: unpacking, then the inverse prediction
        sym, k = NUMPY.symbols(z, cbits.bitlen_table())[2 * extra - 2:2 * extra]
        counts, low = NUMPY.low_counts(sym, extra), NUMPY.pack_low(z, k)
        for impl in (NUMPY, coder):
            out = impl.decode(sym, extra, counts, low, valid, predictor, ref, np.empty_like(x))
            assert out.tolist() == want.tolist()
    if valid is not None:
        assert np.array_equal(want[valid], x[valid])
    else:
        assert np.array_equal(want, x)


_SPECIAL_WORDS = [0x7FC00000, 0xFFC00001, 0x7F800000, 0xFF800000, 0x80000000, 0, 1, 0x4F000000,
                  0xCF000000, 0x7F7FFFFF]


@given(st.lists(st.integers(0, 2**32 - 1) | st.sampled_from(_SPECIAL_WORDS)
                | st.integers(-3_000_000, 3_000_000).map(
                    lambda mm: int(np.float32(mm * 0.001).view(np.uint32))), max_size=80),
       st.sampled_from([0.001, 0.004, 1.0, 1e-7]))
def test_compiled_quantisation_matches_the_numpy_reference(words: list[int], step: float
                                                           ) -> None:
    from lidarscan._codec_bits import NUMPY
    coder = _compiled()
    v = np.array(words, np.uint32).view(np.float32)
    q, exc = NUMPY.quantise(v, step)
    got_q, got_exc = coder.quantise(v, step)
    assert got_q.tolist() == q.tolist() and got_exc.tolist() == exc.tolist()
    back = NUMPY.dequantise(q, step)
    assert back.view(np.uint32)[~exc].tolist() == v.view(np.uint32)[~exc].tolist()
    assert coder.dequantise(q, step).view(np.uint32).tolist() == back.view(np.uint32).tolist()


@given(_scans(), st.sampled_from([None, 0.001]))
def test_compiled_coder_writes_the_reference_bytes_and_roundtrips(scan: Any,
                                                                  step: float | None) -> None:
    coder = _compiled()
    buf = codec.compress_scan(scan, float_step=step, coder=coder)
    assert buf == codec.compress_scan(scan, float_step=step)
    _same(codec.decompress_scan(buf, coder=coder), scan)


def test_compiled_coder_on_a_real_frame_and_its_switch(monkeypatch: Any) -> None:
    from converters._kernels import select
    from converters.edge.evidence._common import load_frame, ouster_files, ouster_info
    from converters.sources.ouster.metadata import scan_from_frame
    coder = _compiled()
    meta, path = next((m, p) for m, p in ouster_files() if p is not None)
    info = ouster_info(meta)
    scan = scan_from_frame(load_frame(path), info, as_dataclass=True)
    buf = codec.compress_scan(scan, info, coder=coder)
    assert buf == codec.compress_scan(scan, info)
    _same(codec.decompress_scan(buf, coder=coder), scan)
    assert codec.decompress_scan(GOLDEN_V2, coder=coder).data.tobytes() == \
        _golden_scan_v2().data.tobytes()
    monkeypatch.setenv("LIDARSCAN_NUMBA", "0")
    assert select("codec").numba is None


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

    from converters.edge.evidence._common import load_frame, ouster_files, ouster_info
    from converters.sources.ouster.metadata import scan_from_frame
    for meta, frame_path in ouster_files():
        if frame_path is None:
            continue
        scan = scan_from_frame(load_frame(frame_path), ouster_info(meta), as_dataclass=True,
                               range_encoding=range_encoding, destagger=destagger)
        buf = codec.compress_scan(scan, ouster_info(meta))
        _same(codec.decompress_scan(buf), scan)
        rolled = [s["params"][15] for s in codec.segments(buf)
                  if s["method"] in ("predict2", "quant2", "xpredict")]
        assert set(rolled) == {int(not destagger)}  # staggered scans predicted destaggered
        whole = zstandard.ZstdCompressor(level=3).compress(scan.data.tobytes())
        assert len(buf) < 0.8 * len(whole), meta.name
        methods = {s["method"] for s in codec.segments(buf) if s["length"]}
        assert methods <= {"predict2", "quant2", "xpredict", "zstd"}
        assert "xpredict" in methods  # format version 3 (the default): reflectivity
        assert ("quant2" in methods) == (range_encoding == "float32")


# ------------------------------------------------------------------------------ errors

@pytest.mark.parametrize("mutate, match", [
    (lambda b: b"XXXX" + b[4:], "magic"),
    (lambda b: b[:4] + bytes([4]) + b[5:], "version"),
    (lambda b: b[:20], "bytes"),
    (lambda b: b + b"\x00", "trailing"),
    (lambda b: b[:6] + struct.pack("<H", 4) + b[8:], "bytes"),
])
def test_damaged_buffers_raise_decode_error(mutate: Any, match: str) -> None:
    with pytest.raises(DecodeError, match=match):
        codec.decompress_scan(mutate(GOLDEN_V2))


def test_a_corrupt_payload_raises_decode_error() -> None:
    bad = bytearray(GOLDEN_V2)
    bad[-8] ^= 0xFF  # a byte of the last zstd frame (low bits): its checksum fails
    with pytest.raises(DecodeError):
        codec.decompress_scan(bytes(bad))


def test_a_hand_built_raw_segment_decodes() -> None:
    """RAW (method 0) is never chosen by the encoder but is part of the format."""
    skeleton_len = struct.unpack_from("<I", GOLDEN_V1, 8)[0]
    head = GOLDEN_V1[:12 + skeleton_len]                      # magic .. skeleton
    data = _golden_scan().data.tobytes()
    buf = (head[:6] + struct.pack("<H", 1) + head[8:] + struct.pack("<I", len(data))
           + struct.pack("<IIBH", 0, len(data), codec.RAW, 0) + struct.pack("<I", len(data))
           + data)
    _same(codec.decompress_scan(buf), _golden_scan())


def test_float_metres_of_coarser_units_use_the_coarser_grid(rng: np.random.Generator) -> None:
    """float32 metres of 4 mm units (Velodyne, Hesai) are coded on the 4 mm grid."""
    units = np.cumsum(rng.integers(-3, 4, (4, 64)), axis=1) + 2500
    units[:, ::7] = 0
    metres = np.where(units > 0, (units * 0.004).astype(np.float32), np.float32(np.inf))
    scan = ls.make_scan(_info(4, 64), {"range": metres.astype(np.float32)}, 5,
                        as_dataclass=True)
    buf = codec.compress_scan(scan)
    seg = codec.segments(buf)[0]
    assert seg["method"] == "quant2"
    assert struct.unpack_from("<d", seg["params"], 18)[0] == pytest.approx(0.004, abs=1e-15)
    _same(codec.decompress_scan(buf), scan)


# ------------------------------------------------------------- MCAP channel and the CLI

def _ouster_pair() -> tuple[Any, Any]:
    from converters.edge.evidence._common import load_frame, ouster_files, ouster_info
    from converters.sources.ouster.metadata import scan_from_frame
    meta, path = next((m, p) for m, p in ouster_files() if p is not None)
    info = ouster_info(meta)
    return info, scan_from_frame(load_frame(path), info, as_dataclass=True)


def test_mcap_writer_compresses_scans_and_the_reader_decompresses(tmp_path: Any) -> None:
    from lidarscan.mcap import CODEC_ENCODING, SCAN_TYPE, McapWriter, read_messages, read_scans
    info, scan = _ouster_pair()
    path = tmp_path / "z.mcap"
    with McapWriter(path, scan_encoding=CODEC_ENCODING) as writer:
        writer.write("/info", info)
        writer.write("/scan", scan)
        writer.write("/scan", ls.encode(scan), msgtype=SCAN_TYPE)  # CDR bytes: compressed too
    items = list(read_messages(path))
    scans = [m for m in items if m.msgtype == SCAN_TYPE]
    assert [m.encoding for m in scans] == [CODEC_ENCODING] * 2
    assert all(m.payload[:5] == b"LSCZ" + bytes([codec.VERSION]) for m in scans)
    assert scans[0].metadata["lidarscan.codec.version"] == str(codec.VERSION)
    # the info written before the scans gives the destaggered prediction (rolled segments)
    assert {s["params"][15] for s in codec.segments(scans[0].payload)
            if s["method"] in ("predict2", "quant2")} == {1}
    assert all(ls.encode(m.decode()) == ls.encode(scan) for m in scans)
    assert [ls.encode(s) for s, _ in read_scans(path)] == [ls.encode(scan)] * 2


def test_mcap_writer_and_records_take_the_compiled_coder(tmp_path: Any) -> None:
    from lidarscan.mcap import CODEC_ENCODING, SCAN_TYPE, McapWriter, read_messages
    coder = _compiled()
    info, scan = _ouster_pair()
    payloads = []
    for name, given in (("ref.mcap", None), ("fast.mcap", coder)):
        with McapWriter(tmp_path / name, scan_encoding=CODEC_ENCODING,
                        codec_coder=given) as writer:
            writer.write("/info", info)
            writer.write("/scan", scan)
        record = next(m for m in read_messages(tmp_path / name) if m.msgtype == SCAN_TYPE)
        assert ls.encode(record.decode(coder)) == ls.encode(scan)
        payloads.append(record.payload)
    assert payloads[0] == payloads[1]


def test_mcap_writer_refuses_another_encoding_or_a_compressed_non_scan(tmp_path: Any) -> None:
    from lidarscan.errors import ConfigError, SchemaError
    from lidarscan.mcap import CODEC_ENCODING, INFO_TYPE, McapWriter
    with pytest.raises(ConfigError, match="scan_encoding"):
        McapWriter(tmp_path / "a.mcap", scan_encoding="zstd")
    with McapWriter(tmp_path / "b.mcap") as writer, pytest.raises(SchemaError, match="encoding"):
        writer.write("/info", b"LSCZ", msgtype=INFO_TYPE, encoding=CODEC_ENCODING)


def test_cli_convert_compress_and_back_is_bit_exact(tmp_path: Any,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    from converters.edge import cli
    from lidarscan.mcap import CODEC_ENCODING, McapWriter, read_messages
    info, scan = _ouster_pair()
    plain = tmp_path / "plain.mcap"
    with McapWriter(plain) as writer:
        writer.write("/os/lidar_info", info)
        writer.write("/os/lidar_scan", scan)
    packed, back = tmp_path / "packed.mcap", tmp_path / "back.mcap"
    assert cli.main(["convert", str(plain), str(packed), "--compress", "-q"]) == 0
    assert cli.main(["convert", str(packed), str(back), "-q", "--chunk-compression", "lz4"]) == 0
    assert packed.stat().st_size < 0.8 * plain.stat().st_size
    originals, compressed, restored = (list(read_messages(p)) for p in (plain, packed, back))
    assert [m.encoding for m in compressed] == ["cdr", CODEC_ENCODING]
    assert [m.encoding for m in restored] == ["cdr", "cdr"]
    assert [(m.topic, m.log_time_ns, m.payload) for m in restored] == \
        [(m.topic, m.log_time_ns, m.payload) for m in originals]
    capsys.readouterr()
    assert cli.main(["info", str(packed)]) == 0
    out = capsys.readouterr().out
    assert f"(compressed: {CODEC_ENCODING})" in out and "no problems found" in out
    assert cli.main(["view", str(packed), "--out", str(tmp_path / "views")]) == 0
    assert list((tmp_path / "views").glob("range_image_*.png"))


def test_a_rosbag2_directory_keeps_the_encoding(tmp_path: Any) -> None:
    from converters.sources.bags import open_bag
    from lidarscan.mcap import CODEC_ENCODING, SCAN_TYPE, McapWriter
    info, scan = _ouster_pair()
    (tmp_path / "bag").mkdir()
    with McapWriter(tmp_path / "bag" / "bag_0.mcap", scan_encoding=CODEC_ENCODING) as writer:
        writer.write("/info", info)
        writer.write("/scan", scan)
    items = [m for m in open_bag(tmp_path / "bag").messages() if m.msgtype == SCAN_TYPE]
    assert [m.encoding for m in items] == [CODEC_ENCODING]
    assert ls.encode(items[0].decode()) == ls.encode(scan)
