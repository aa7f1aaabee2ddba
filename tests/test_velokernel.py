"""The two paths of the Velodyne C kernel (``converters/_kernels/_velokernel.c``): same bytes.

``vdk_fill`` takes its AVX2 path (slot-major tiles of 16 packets) for layouts with one firing
sequence per packet (a dual-return VLS-128) on a CPU with AVX2, and its portable path otherwise
or when ``converters._kernels.velodyne.SIMD`` is 0 (``LIDARSCAN_VELODYNE_SIMD=0`` at import).
Checked here: the golden digests of
``tests/test_velodyne_golden.py`` with the portable path forced, and the kernel called directly
on random packets (random block azimuths, with and without equal azimuths in a packet; random
row order and rot_correction; odd begin / count / column; with and without the azimuth channel;
one and two return slots) by both paths and, for the real layout, by the numpy reference.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))

from converters._kernels import velodyne as kv  # noqa: E402
from converters.sources.velodyne import packets as vp  # noqa: E402

pytestmark = pytest.mark.skipif(kv.library() is None,
                                reason="converters._kernels._velokernel is not built")


@pytest.mark.parametrize("case", ["VLS-128/dual/nebula", "VLS-128/dual/manual",
                                  "VLP-16/dual/nebula"])
def test_golden_digests_with_the_portable_path_forced(case: str, tmp_path: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    from test_velodyne_golden import GOLDEN, _compute
    monkeypatch.setattr(kv, "SIMD", 0)
    assert _compute(case, tmp_path) == [GOLDEN[case]] * 3


def _packets(rng: np.random.Generator, n: int) -> np.ndarray[Any, Any]:
    """(n, 1206) dual-return VLS-128 packets, random points; block azimuths random, equal in
    the eight blocks of every other run of packets (as the sensor sends them)."""
    rows = rng.integers(0, 256, (n, 1206), dtype=np.uint8)
    heads = rows[:, :1200].reshape(n, 12, 100)
    azimuth = rng.integers(0, 36000, (n, 12))
    same = (np.arange(n) // 7) % 2 == 0
    azimuth[same] = azimuth[same, :1]
    heads[:, :, 2], heads[:, :, 3] = azimuth & 0xFF, azimuth >> 8
    dist = rows[:, :1200].reshape(n, 12, 100)[:, :, 4:].reshape(n, 12, 32, 3)
    copy = rng.random((n, 4, 32)) < 0.3            # identical pairs (strongest == last)
    for bank in range(4):
        dist[:, 2 * bank + 1, :, :2][copy[:, bank]] = dist[:, 2 * bank, :, :2][copy[:, bank]]
    return rows


def _views(rows: int, width: int, angles: bool, returns: int = 2) -> dict[str, Any]:
    names = ["range", "intensity", "range2", "intensity2"][:2 * returns]
    if angles:
        names += ["azimuth", "azimuth2"][:returns]
    return {name: np.full((rows, width), 7, np.uint8 if name.startswith("intensity")
                          else np.uint16) for name in names}


def _fill(plan: Any, rows: np.ndarray[Any, Any], begin: int, count: int, column: int,
          views: dict[str, Any], simd: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(kv, "SIMD", int(simd))
    kv.fill(kv.library(), plan, rows, begin, count, column, views)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("angles", [True, False], ids=["nebula", "manual"])
def test_simd_path_equals_portable_path_and_numpy(seed: int, angles: bool,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(seed)
    layout = vp._layout(0xA1, 0x39)
    order = rng.permutation(128)
    scale = 9e5 if seed == 3 else 3000.0          # near the kernel's rotation limit too
    rotation = rng.uniform(-scale, scale, 128) if angles else None
    tables = vp._tables(layout, order, rotation, kv.library())
    assert tables.plan is not None
    rows = _packets(rng, 203)
    width = 230
    for begin, count, column in [(0, 203, 0), (5, 160, 17), (3, 37, 1), (0, 15, 0),
                                 (int(rng.integers(0, 40)), int(rng.integers(16, 150)), 9)]:
        got = []
        for simd in (True, False):
            views = _views(128, width, angles)
            _fill(tables.plan, rows, begin, count, column, views, simd, monkeypatch)
            got.append(views)
        reference = _views(128, width, angles)
        sub = {k: v[:, column:] for k, v in reference.items()}
        vp._fill_views([rows], begin, count, layout, vp._Tables(tables.offsets,
                                                                tables.rotation), sub)
        for name in got[0]:
            assert np.array_equal(got[0][name], got[1][name]), (name, begin, count, column)
            assert np.array_equal(got[0][name], reference[name]), (name, begin, count, column)


@pytest.mark.parametrize("angles", [True, False], ids=["nebula", "manual"])
def test_simd_path_equals_portable_path_with_one_return_slot(
        angles: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    """A one-sequence plan with one return slot and fewer rows (no sensor sends it; the
    kernel's shape rules allow it): both paths write the same bytes."""
    rng = np.random.default_rng(11)
    layout = vp._layout(0xA1, 0x39)
    tables = vp._tables(layout, rng.permutation(128), rng.uniform(-500, 500, 128),
                         kv.library())
    full = tables.plan
    offsets = full.offsets[:1, :, rng.permutation(128)[:77]]
    plan = kv.Plan(offsets, full.factor.reshape(12, 32), full.rotation.reshape(12, 32),
                   full.family, full.dual, full.n_blocks)
    rows = _packets(rng, 120)
    got = []
    for simd in (True, False):
        views = _views(77, 130, angles, returns=1)
        _fill(plan, rows, 2, 117, 5, views, simd, monkeypatch)
        got.append(views)
    for name in got[0]:
        assert np.array_equal(got[0][name], got[1][name]), name


# ------------------------------------------------------------ packets read through addresses

@pytest.mark.parametrize("simd", [1, 0], ids=["default", "portable"])
@pytest.mark.parametrize("product, mode", [(0xA1, 0x39), (0xA1, 0x37), (0x22, 0x39),
                                           (0x28, 0x37)])
def test_fill_through_an_address_table_equals_the_rows(product: int, mode: int, simd: int,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """The packets as separate ``bytes`` (their addresses from ``table``, scattered in memory)
    give the same bytes as the same packets as rows of one array, on both paths; ``words``
    reads the same header words."""
    rng = np.random.default_rng(product + mode)
    layout = vp._layout(product, mode)
    lasers = layout.model.lasers
    tables = vp._tables(layout, rng.permutation(lasers), rng.uniform(-3000, 3000, lasers),
                        kv.library())
    assert tables.plan is not None
    rows = _packets(rng, 150)
    pairs = [(int(i) - 75, rows[i].tobytes()) for i in rng.permutation(150)]
    order = np.array([s + 75 for s, _ in pairs])
    rows = rows[order]                                    # the rows in the pairs' order
    found = kv.table(pairs)
    assert found is not None
    addresses, stamps = found
    assert stamps.tolist() == [s for s, _ in pairs]
    monkeypatch.setattr(kv, "SIMD", simd)
    lib = kv.library()
    width = 150 * layout.sequences + 20
    for begin, count, column in [(0, 150 * layout.sequences, 0), (7, 131, 3), (1, 17, 19)]:
        a, b = _views(lasers, width, True, layout.dual + 1), _views(lasers, width, True,
                                                                   layout.dual + 1)
        kv.fill(lib, tables.plan, rows, begin, count, column, a)
        kv.fill(lib, tables.plan, addresses, begin, count, column, b)
        for name in a:
            assert np.array_equal(a[name], b[name]), (name, begin, count, column)
    at = np.array([1, 51, 551, 600, 601, 602])
    assert np.array_equal(kv.words(lib, addresses, at), rows.view("<u2")[:, at])
    wide = np.zeros((150, 1300), np.uint8)
    wide[:, 3:1209] = rows                                # rows at odd addresses, strided
    assert np.array_equal(kv.words(lib, wide[:, 3:1209], at), rows.view("<u2")[:, at])


def test_table_takes_tuples_of_an_int_and_1206_bytes_only() -> None:
    """``table`` stops at the first pair that is not a 2-tuple of an int within int64 and a
    1206-byte ``bytes`` (the decoder then joins the chunk as before): its index."""
    class Sub(bytes):
        pass

    data = bytes(range(256)) * 4 + bytes(182)
    fine = (5, data)
    odd: list[Any] = [(5, bytearray(data)), (5, memoryview(data)), (5, data[:-1]),
                      (5, data + b"\0"), [5, data], (5, data, 0), (5,), (np.int64(5), data),
                      (True, data), (2 ** 63, data), (-2 ** 63 - 1, data), (5.0, data),
                      (5, Sub(data)), (5, np.frombuffer(data, np.uint8)), None]
    module = kv._module()
    for item in odd:
        out, stamps = np.empty(4, np.uintp), np.empty(4, np.int64)
        assert module.table([fine, fine, item, fine], out, stamps) == 2, item
        assert kv.table([fine, item]) is None
    found = kv.table([(2 ** 63 - 1, data), (-2 ** 63, data), (0, data)])
    assert found is not None
    assert found[1].tolist() == [2 ** 63 - 1, -2 ** 63, 0]
    assert kv.table([]) is not None
    with pytest.raises(TypeError):
        module.table((fine,), np.empty(1, np.uintp), np.empty(1, np.int64))   # not a list
    with pytest.raises(ValueError, match="too small"):
        module.table([fine, fine], np.empty(1, np.uintp), np.empty(2, np.int64))
