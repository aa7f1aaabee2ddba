"""lidarscan.codec format version 3: XPREDICT (:mod:`lidarscan._codec_v3`) restores every byte.

Layers: golden bytes of version 3 (decoded, and re-encoded with the zstd library they were made
with), a loop-based oracle of the prediction P (the module docstring's formula, pixel by pixel
with Python integers and IEEE float32 words) against the numpy reference, the params' byte
round trip, round trips of hypothesis scans built for XPREDICT (shapes, signal / target
datatypes, float32 or integer ranges with NaN, +-Inf, -0 and negative values, no-return pixels,
both byte orders, rolled rows) and of generic scans written as version 3 (the default), the
compiled fit and prediction (``converters._kernels.codec3``, in the compiled coder) against the
numpy reference on hypothesis inputs (signal, range and target dtypes, byte orders, NaN, +-Inf,
no-return pixels, rolled rows, the medians) and scan by scan (same bytes, also where no block
has XPREDICT's sources), the real Ouster frames (smaller than version 2, same bytes with the
compiled coder), and damaged buffers.
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import lidarscan as ls
from lidarscan import _codec_v3 as v3
from lidarscan import codec
from lidarscan.errors import DecodeError, EncodeError
from lidarscan.types import LidarChannel, LidarScan

# compress_scan(_golden_scan_v3(), level=3, version=3) with zstandard 0.25.0 (libzstd 1.5.7)
GOLDEN_V3 = bytes.fromhex(
    "4c53435a030003006c00000028b52ffd248cfd0200a204101cb027ad01d8922471608534762a77b75865c221"
    "1304204ae3b6c94e016f1ac9312e415852d8fa60e4e928740b812175d6cdc20184875d2771e90183e3f0e532"
    "0b004309187517f43eb160089b2b0bae72b7a7eba7568293c7b9b309e61379743a0000002000000000000000"
    "1d00000028b52ffd6400007d00002800d00007000310003c4a8858c4020e0748d60d00000028b52ffd240001"
    "000099e9d851800300000000000000020000061a00070004000000200000000100000003000201fca9f1d24d"
    "62503f950000001d00000028b52ffd2410810000ffffffffeffffffffbffffffffffffffa57d16862e000000"
    "28b52ffd247e0d0100703c2624002a002a242a2a00000024070051c950f380251c6e6344750fd84f046dd271"
    "ba942500000028b52ffd244dc500008028a54a54461863e80fa03e80fa03fc400200552064e288b569775915"
    "00000028b52ffd24084100000000807f0000c07f93e6653b0002000000010000051200040004000000200000"
    "0001000000030002005f0000003800000028b52ffd24805d010088111c261c15002727000000000000000000"
    "0b003c13800c005fcd36863a00078035701eaa78000d0b000b4115b48c1f00000028b52ffd24189500006055"
    "5554d34d39e99e99e99e8001001cc00281fcc5b0000300008000000007400002000400000020000000010000"
    "000000020000020000040000000007481000000200324d0000ab4d000004002b800080bc7f16805000000000"
    "00000001000000400000002a00000028b52ffd2480ed00005000001a00040008001d00070047d8009011c8d1"
    "e603c08c81c719c002e1e281690e00000028b52ffd2401090000ee09733bcc")


def _golden_scan_v3() -> Any:
    """4 x 32: range 10.0-10.4 m (mm grid) with +Inf and NaN, signal, reflectivity = signal
    times a range-dependent gain with two outliers (XPREDICT)."""
    h, w = 4, 32
    info = ls.make_info(stamp_ns=1_500_000_000, frame_id="lidar",
                        vertical_angles=np.radians(np.linspace(5, -5, h)),
                        horizontal_angles=2 * np.pi * (1 - np.arange(w) / w), as_dataclass=True)
    rows, cols = np.mgrid[:h, :w]
    mm = 10000 + (cols * 997 + rows * 131) % 400
    rng = (mm * 0.001).astype(np.float32)
    rng[1, 3], rng[2, 5] = np.inf, np.nan
    signal = ((cols * 37 + rows * 11) % 250 + 5).astype(np.uint16)
    gain = 0.3 + 0.01 * (np.nan_to_num(rng.astype(np.float64), posinf=0.0) - 10)
    refl = np.where(np.isfinite(rng), np.clip(np.rint(signal * gain), 0, 255), 0)
    refl = refl.astype(np.uint8)
    refl[0, 9], refl[3, 30] = 255, 1
    return ls.make_scan(info, {"range": rng, "signal": signal, "reflectivity": refl},
                        1_600_000_000, column_time_offsets=np.arange(w) * 1000,
                        as_dataclass=True)


def _same(a: Any, b: Any) -> None:
    assert ls.encode(a) == ls.encode(b)


# ----------------------------------------------------------------------------- golden

def test_golden_v3_bytes_decode_to_the_golden_scan() -> None:
    _same(codec.decompress_scan(GOLDEN_V3), _golden_scan_v3())


def test_golden_v3_layout_version_methods_and_params() -> None:
    assert GOLDEN_V3[:8] == b"LSCZ" + bytes([3, 0]) + struct.pack("<H", 3)
    segs = codec.segments(GOLDEN_V3)
    assert [(s["offset"], s["length"], s["method"]) for s in segs] == [
        (0, 512, "quant2"), (512, 256, "predict2"), (768, 128, "xpredict")]
    prm = segs[2]["params"]
    assert prm[:14] == struct.pack("<BBIII", 2, 0, 4, 32, 1) and prm[15] == 0  # u8, not rolled
    p = v3.unpack_params(prm[18:], "test")
    assert (p.signal_offset, p.signal_datatype, p.range_offset, p.range_datatype) == (512, 4,
                                                                                      0, 7)
    assert p.row_gain.size == 4 and p.knee == 80


@pytest.mark.parametrize("compiled", [False, True])
def test_golden_v3_bytes_are_what_the_encoder_writes(compiled: bool) -> None:
    import zstandard
    coder = _compiled_x() if compiled else None
    out = codec.compress_scan(_golden_scan_v3(), level=3, version=3, coder=coder)
    assert [(s["offset"], s["method"], s["params"]) for s in codec.segments(out)] == [
        (s["offset"], s["method"], s["params"]) for s in codec.segments(GOLDEN_V3)]
    if zstandard.backend_features is not None and zstandard.__version__ == "0.25.0":
        assert out == GOLDEN_V3


def test_version_3_is_the_default_2_is_written_on_request_and_others_are_refused() -> None:
    scan = _golden_scan_v3()
    assert codec.VERSION == 3 and codec.compress_scan(scan)[4] == 3
    v2 = codec.compress_scan(scan, version=2)
    assert v2[4] == 2 and {s["method"] for s in codec.segments(v2)} <= {"quant2", "predict2"}
    _same(codec.decompress_scan(v2), scan)
    for bad in (1, 4, True):
        with pytest.raises(EncodeError, match="version"):
            codec.compress_scan(scan, version=bad)


# ----------------------------------------------------------------------- the prediction

def _f32_word(x: float) -> int:
    return int(struct.unpack("<I", struct.pack("<f", x))[0])


def _predict_loop(s: np.ndarray[Any, Any], r: np.ndarray[Any, Any], p: v3.XParams,
                  top: int) -> np.ndarray[Any, Any]:
    """The module docstring's P, pixel by pixel (Python integers, float32 words)."""
    out = np.zeros(s.shape, np.int64)
    for y in range(s.shape[0]):
        for x in range(s.shape[1]):
            rv = float(np.float32(r[y, x]))
            if not np.isfinite(rv) or rv <= 0:
                continue
            rb = min(max((_f32_word(rv) >> 18) - p.bin0, 0), p.gain.size - 1)
            u = max(int(s[y, x]), 0) * int(p.gain[rb]) * int(p.row_gain[y]) + (1 << 30)
            u = max(u >> 31, 0)
            if u >= p.knee:
                kb = min(max((_f32_word(float(np.float32(u))) >> 20) - p.ubin0, 0),
                         p.comp.size - 1)
                u = int(p.comp[kb])
            out[y, x] = min(u, top)
    return out


_RANGE_SPECIALS = [np.inf, -np.inf, np.nan, -0.0, 0.0, -3.5]


@st.composite
def _sources(draw: Any) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any], v3.XParams]:
    h, w = draw(st.integers(1, 5)), draw(st.integers(1, 7))
    sig_type = draw(st.sampled_from(["u1", "u2", "i2", "u4", "i4"]))
    info = np.iinfo(sig_type)
    s = np.array(draw(st.lists(st.integers(max(info.min, -5), min(info.max, 70000)),
                               min_size=h * w, max_size=h * w)), sig_type).reshape(h, w)
    if draw(st.booleans()):
        r = np.array(draw(st.lists(st.floats(0.0625, 400, width=32)
                                   | st.sampled_from(_RANGE_SPECIALS),
                                   min_size=h * w, max_size=h * w)), np.float32).reshape(h, w)
    else:
        r = np.array(draw(st.lists(st.integers(0, 2**32 - 1), min_size=h * w,
                                   max_size=h * w)), np.uint32).reshape(h, w)
    ng, nc = draw(st.integers(1, 40)), draw(st.integers(1, 20))
    p = v3.XParams(0, 4, 0, 7, draw(st.integers(900, 1100)),
                   np.array(draw(st.lists(st.integers(0, 2**24 - 1), min_size=ng,
                                          max_size=ng)), np.uint32),
                   np.array(draw(st.lists(st.integers(0, 65535), min_size=h, max_size=h)),
                            np.uint16),
                   draw(st.integers(0, 300)), draw(st.integers(1000, 1200)),
                   np.array(draw(st.lists(st.integers(0, 65535), min_size=nc, max_size=nc)),
                            np.uint16))
    return s, r, p


@given(_sources(), st.sampled_from([np.uint8, np.uint16, np.uint32]))
def test_prediction_matches_the_loop_oracle(src: Any, dtype: Any) -> None:
    s, r, p = src
    got = v3.predict(s, r, p, dtype)
    assert got.dtype == dtype
    np.testing.assert_array_equal(got, _predict_loop(s, r, p, int(np.iinfo(dtype).max)))


@given(_sources())
def test_params_bytes_roundtrip(src: Any) -> None:
    p = src[2]
    q = v3.unpack_params(v3.pack_params(p), "test")
    assert v3.pack_params(q) == v3.pack_params(p)
    for name in ("gain", "row_gain", "comp"):
        np.testing.assert_array_equal(getattr(q, name), getattr(p, name))


def test_fit_predicts_a_linear_reflectivity_to_a_count() -> None:
    rng_ = np.random.default_rng(3)
    s = rng_.integers(100, 300, (8, 64)).astype(np.uint16)
    r = rng_.uniform(2, 60, (8, 64)).astype(np.float32)
    f = np.clip(np.rint(s * 0.25), 0, 255).astype(np.uint8)
    p = v3.fit(f, s, r, (0, 4), (0, 7), 100)
    assert p is not None
    d = f.astype(np.int64) - v3.predict(s, r, p, np.uint8)
    assert np.abs(d).max() <= 1 and np.count_nonzero(d) <= 0.15 * d.size  # ~3 pixels a bin


def test_source_names_follow_the_return_suffix() -> None:
    names = ["range", "signal", "reflectivity", "range2", "signal2", "reflectivity2"]
    assert v3.source_names("reflectivity", names) == ("signal", "range")
    assert v3.source_names("reflectivity2", names) == ("signal2", "range2")
    assert v3.source_names("reflectivity", ["range", "intensity"]) == ("intensity", "range")
    assert v3.source_names("reflectivity", ["reflectivity", "signal"]) is None
    assert v3.source_names("near_ir", names) is None


# ------------------------------------------------------- the compiled fit and prediction

def _compiled_x() -> Any:
    """The compiled coder (``test_codec._compiled``, not imported here: its module's @given
    tests would nest in this module's)."""
    pytest.importorskip("numba")
    from converters._kernels import select
    coder = select("codec").numba
    if coder is None:
        pytest.skip("numba disabled (LIDARSCAN_NUMBA=0)")
    assert coder.xfit is not None and coder.xpredict is not None
    return coder


def _order(a: np.ndarray[Any, Any], big: bool) -> np.ndarray[Any, Any]:
    """a with the same values in big-endian (non-native) order when ``big``."""
    return a.astype(a.dtype.newbyteorder(">")) if big and a.dtype.itemsize > 1 else a


@settings(max_examples=80, deadline=None)
@given(_sources(), st.sampled_from([np.uint8, np.uint16, np.uint32]), st.booleans(),
       st.lists(st.integers(-40, 40), min_size=5, max_size=5), st.integers(0, 2**32 - 1))
def test_compiled_prediction_matches_the_reference(src: Any, dtype: Any, big: bool,
                                                   shifts: list[int], seed: int) -> None:
    s, r, p = src
    x = np.random.default_rng(seed).integers(0, np.iinfo(dtype).max, s.shape,
                                             dtype=np.int64, endpoint=True).astype(dtype)
    rows = None if shifts[0] % 2 else np.array(shifts[:s.shape[0]], np.int64)  # any sign
    coder = _compiled_x()
    for sign in (1, -1):
        want = v3.residual(x, s, r, p, rows, sign)
        got = coder.xpredict(_order(x, big), _order(s, big), _order(r, big), p, rows, sign)
        assert got.dtype == want.dtype and got.dtype.isnative
        np.testing.assert_array_equal(got, want)
    d = coder.xpredict(x, s, r, p, rows, 1)
    np.testing.assert_array_equal(coder.xpredict(d, s, r, p, rows, -1), x)  # inverse


@st.composite
def _fit_inputs(draw: Any) -> tuple[np.ndarray[Any, Any], ...]:
    """(f, s, r): a target roughly signal x a range gain (some arbitrary pixels), any
    signal type (negative values included), float32 ranges with NaN, +-Inf, -0 and
    no-return zeros, or integer ranges."""
    h, w = draw(st.integers(1, 6)), draw(st.integers(1, 40))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    sig_type = draw(st.sampled_from(["u1", "i1", "u2", "i2", "u4", "i4"]))
    info = np.iinfo(sig_type)
    s = rng.integers(max(info.min, -3), min(info.max, draw(st.sampled_from([255, 2000]))),
                     (h, w), endpoint=True).astype(sig_type)
    if draw(st.booleans()):
        r = rng.uniform(0.1, draw(st.sampled_from([2.0, 80.0, 300.0])), (h, w)).astype(
            np.float32)
        special = rng.random(h * w) < 0.2
        r.reshape(-1)[special] = rng.choice(np.array(_RANGE_SPECIALS, np.float32),
                                             int(special.sum()))
    else:  # integer units of any type (negative values of a signed one: no prediction)
        range_type = draw(st.sampled_from(["u2", "i4", "u4"]))
        top = min(np.iinfo(range_type).max, draw(st.sampled_from([100, 2**20, 2**32 - 1])))
        r = rng.integers(-5 if range_type == "i4" else 0, top, (h, w), dtype=np.int64,
                         endpoint=True).astype(range_type)
    tgt = draw(st.sampled_from([np.uint8, np.uint16]))
    gain = 0.2 + 0.3 * rng.random()
    f = np.clip(np.rint(np.maximum(s, 0) * gain), 0, np.iinfo(tgt).max).astype(tgt)
    f.reshape(-1)[rng.random(h * w) < 0.1] = rng.integers(0, 256)
    return f, s, r


@settings(max_examples=80, deadline=None)
@given(_fit_inputs(), st.sampled_from([0, 80, 300]))
def test_compiled_fit_matches_the_reference(grids: Any, knee: int) -> None:
    f, s, r = grids
    want = v3.fit(f, s, r, (8, 4), (0, 7), knee)
    got = _compiled_x().xfit(f, s, r, (8, 4), (0, 7), knee)
    assert (got is None) == (want is None)
    if want is not None:
        assert v3.pack_params(got) == v3.pack_params(want)


def test_compiled_fit_on_a_subsample_matches_the_reference() -> None:
    rng = np.random.default_rng(7)
    h, w = 64, 1031  # several columns per fitted one, a width that the step does not divide
    s = rng.integers(0, 3000, (h, w)).astype(np.uint16)
    r = rng.uniform(0.3, 120, (h, w)).astype(np.float32)
    f = np.clip(np.rint(s * (0.1 + r / 400)), 0, 255).astype(np.uint8)
    r[rng.random((h, w)) < 0.1] = np.inf
    assert v3.fit_step(f.size) > 1
    for big in (False, True):
        got = _compiled_x().xfit(_order(f, big), _order(s, big), _order(r, big), (0, 4), (0, 7))
        assert v3.pack_params(got) == v3.pack_params(v3.fit(f, s, r, (0, 4), (0, 7)))


@given(st.lists(st.tuples(st.integers(0, 9), st.integers(0, 12)), max_size=80),
       st.integers(1, 12), st.integers(1, 5))
def test_compiled_medians_match_the_reference(pairs: list[tuple[int, int]], n: int,
                                              scale: int) -> None:
    from converters._kernels import codec3
    _compiled_x()
    keys = np.array([k % n for k, _ in pairs], np.int64)
    values = np.array([v / scale for _, v in pairs], np.float64)
    np.testing.assert_array_equal(codec3._medians(keys, values, n),
                                  v3._medians(keys, values, n))


# ------------------------------------------------------------------------ round trips

_INT = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4"}


@st.composite
def _xscans(draw: Any) -> LidarScan:
    """Scans with range, signal and reflectivity channels (XPREDICT candidates), in either
    byte order; reflectivity mostly a function of signal and range, some pixels arbitrary."""
    h, w = draw(st.integers(1, 6)), draw(st.integers(1, 9))
    big = draw(st.booleans())
    order = ">" if big else "<"
    n = h * w
    float_range = draw(st.booleans())
    if float_range:
        r = np.array(draw(st.lists(st.integers(1, 200_000).map(lambda m: m * 0.001)
                                   | st.sampled_from(_RANGE_SPECIALS), min_size=n,
                                   max_size=n)), np.float32)
        range_block, range_type = r.astype(order + "f4").tobytes(), 7
    else:
        r = np.array(draw(st.lists(st.integers(0, 2**32 - 1) | st.integers(0, 5000),
                                   min_size=n, max_size=n)), np.uint32)
        range_block, range_type = r.astype(order + "u4").tobytes(), 6
    sig_type = draw(st.sampled_from([2, 3, 4, 6]))
    s = np.array(draw(st.lists(st.integers(0, 255), min_size=n, max_size=n)))
    tgt_type = draw(st.sampled_from([1, 2, 4, 6]))
    rf = np.nan_to_num(r.astype(np.float64), nan=0, posinf=0, neginf=0)
    f = np.clip(np.rint(s * (0.2 + 0.001 * np.clip(rf, 0, 1000))), 0, 120).astype(np.int64)
    noise = draw(st.lists(st.integers(0, n - 1), max_size=4))
    f[noise] = draw(st.integers(0, 127))
    blocks = [("range", range_type, range_block),
              ("signal", sig_type, s.astype(order + _INT[sig_type]).tobytes()),
              ("reflectivity", tgt_type, f.astype(order + _INT[tgt_type]).tobytes())]
    channels, chunks, offset = [], [], 0
    for name, datatype, block in blocks:
        pad = draw(st.integers(0, 3))
        chunks.append(b"\x00" * pad)
        offset += pad
        channels.append(LidarChannel(name, offset, datatype, 1))
        chunks.append(block)
        offset += len(block)
    return LidarScan(height=h, width=w, is_bigendian=big, is_destaggered=False,
                     column_time_offsets=np.arange(w, dtype=np.int64),
                     channels=tuple(channels),
                     data=np.frombuffer(b"".join(chunks), np.uint8))


@settings(max_examples=60, deadline=None)
@given(_xscans(), st.lists(st.integers(-40, 40), min_size=1, max_size=6))
def test_roundtrip_of_xpredict_scans_is_bit_exact(scan: Any, shifts: list[int]) -> None:
    from types import SimpleNamespace

    from lidarscan._codec_bits import NUMPY
    desc = scan.channels[2]
    size = {1: 1, 2: 1, 4: 2, 6: 4}[int(desc.datatype)]
    block = memoryview(scan.data)[desc.offset:desc.offset + scan.height * scan.width * size]
    roll = (np.array((shifts * 6)[:scan.height]) % scan.width) if len(shifts) > 1 else None
    # the XPREDICT coding itself, whether or not the encoder would keep it
    got = v3.encode_block(block, desc, scan, 1, roll, NUMPY)
    if got is not None:
        data = np.array(scan.data)
        out = v3.decode_block("test", int(desc.offset), len(block), got[0], got[1], data, NUMPY)
        assert out.tobytes() == bytes(block)
    info = SimpleNamespace(pixel_shift_by_row=(shifts * 6)[:scan.height])
    buf = codec.compress_scan(scan, info if len(shifts) > 1 else None, version=3)
    assert buf[4] == 3
    back = codec.decompress_scan(buf)
    _same(back, scan)
    assert back.data.tobytes() == scan.data.tobytes()
    coder = _compiled_x()  # the compiled fit and prediction: the same bytes
    assert codec.compress_scan(scan, info if len(shifts) > 1 else None, version=3,
                               coder=coder) == buf
    assert codec.decompress_scan(buf, coder=coder).data.tobytes() == scan.data.tobytes()


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 6), st.integers(1, 9), st.binary(min_size=6 * 9 * 7, max_size=6 * 9 * 7),
       st.booleans())
def test_roundtrip_of_arbitrary_bytes_written_as_version_3(h: int, w: int, raw: bytes,
                                                           big: bool) -> None:
    n = h * w
    data = np.frombuffer(raw[:7 * n], np.uint8)
    chans = (LidarChannel("range", 0, 7, 1), LidarChannel("signal", 4 * n, 4, 1),
             LidarChannel("reflectivity", 6 * n, 2, 1))
    scan = LidarScan(height=h, width=w, is_bigendian=big, is_destaggered=True,
                     column_time_offsets=np.arange(w, dtype=np.int64), channels=chans,
                     data=data)
    back = codec.decompress_scan(codec.compress_scan(scan, version=3))
    assert back.data.tobytes() == data.tobytes()


@pytest.mark.parametrize("case", ["no reflectivity", "float reflectivity", "sources after",
                                  "count 2", "no signal"])
def test_blocks_without_xpredict_sources_are_coded_as_version_2(case: str) -> None:
    rng = np.random.default_rng(5)
    h, w = 8, 300
    rng_m = rng.uniform(1, 50, (h, w)).astype(np.float32)
    signal = rng.integers(0, 500, (h, w)).astype(np.uint16)
    refl = np.clip(signal // 4, 0, 255).astype(np.uint8)
    chans: dict[str, Any] = {"range": rng_m, "signal": signal, "reflectivity": refl}
    if case == "no reflectivity":
        del chans["reflectivity"]
    elif case == "float reflectivity":
        chans["reflectivity"] = refl.astype(np.float32)
    elif case == "sources after":
        chans = {"reflectivity": refl, "range": rng_m, "signal": signal}
    elif case == "count 2":
        chans["reflectivity"] = np.stack([refl, refl], axis=-1)
    else:
        del chans["signal"]
    info = ls.make_info(stamp_ns=1, frame_id="lidar",
                        vertical_angles=np.radians(np.linspace(5, -5, h)),
                        horizontal_angles=2 * np.pi * (1 - np.arange(w) / w), as_dataclass=True)
    scan = ls.make_scan(info, chans, 2, as_dataclass=True)
    buf = codec.compress_scan(scan, version=3)
    assert "xpredict" not in {s["method"] for s in codec.segments(buf)}
    coder = _compiled_x()
    assert codec.compress_scan(scan, version=3, coder=coder) == buf
    _same(codec.decompress_scan(buf, coder=coder), scan)


def test_real_ouster_frames_are_smaller_in_version_3_and_roundtrip() -> None:
    from converters.edge.evidence.compression import real_scans
    coder = _compiled_x()
    for label, info, scan, _ in real_scans():
        v2 = codec.compress_scan(scan, info, coder=coder, version=2)
        out = codec.compress_scan(scan, info, coder=coder, version=3)
        assert codec.compress_scan(scan, info, version=3) == out  # numpy reference: same bytes
        assert "xpredict" in {s["method"] for s in codec.segments(out)}, label
        assert len(out) < 0.95 * len(v2), label
        _same(codec.decompress_scan(out, coder=coder), scan)


# ------------------------------------------------------------------------------ errors

def _with_params(buf: bytes, index: int, params: bytes) -> bytes:
    """``buf`` with segment ``index``'s params replaced (same container otherwise)."""
    segs = codec._parse(buf)[3]
    old = segs[index][3]
    assert buf.count(old) == 1
    head = struct.pack("<H", len(old)) + old
    return buf.replace(head, struct.pack("<H", len(params)) + params)


def test_a_source_after_its_block_raises_decode_error() -> None:
    prm = codec.segments(GOLDEN_V3)[2]["params"]
    p = v3.unpack_params(prm[18:], "test")
    p.signal_offset = 768  # the block itself: not decoded yet
    with pytest.raises(DecodeError, match="source offset"):
        codec.decompress_scan(_with_params(GOLDEN_V3, 2, prm[:18] + v3.pack_params(p)))


def test_wrong_row_gains_and_truncated_params_raise_decode_error() -> None:
    prm = codec.segments(GOLDEN_V3)[2]["params"]
    p = v3.unpack_params(prm[18:], "test")
    p.row_gain = p.row_gain[:3]
    with pytest.raises(DecodeError, match="row gains"):
        codec.decompress_scan(_with_params(GOLDEN_V3, 2, prm[:18] + v3.pack_params(p)))
    for cut in (5, 20, len(prm) - 1):
        with pytest.raises(DecodeError):
            codec.decompress_scan(_with_params(GOLDEN_V3, 2, prm[:cut]))


def test_a_version_2_buffer_may_not_hold_xpredict() -> None:
    bad = GOLDEN_V3[:4] + bytes([2]) + GOLDEN_V3[5:]
    with pytest.raises(DecodeError, match="version 2"):
        codec.decompress_scan(bad)
