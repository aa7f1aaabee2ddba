"""lidarscan.scan.ScanBuffer: fill channels in place, wrap without a copy; same bytes as make_scan."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

import lidarscan
from lidarscan.errors import ValidationError
from lidarscan.scan import ScanBuffer, make_info, make_scan


def _info(height: int = 3, width: int = 5, as_dataclass: bool = True) -> Any:
    return make_info(stamp_ns=1_000, frame_id="lidar",
                     vertical_angles=np.linspace(0.2, -0.2, height),
                     horizontal_angles=np.linspace(0, -6, width), range_multiplier=0.004,
                     as_dataclass=as_dataclass)


def _channels(height: int, width: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    return {"range": rng.integers(0, 65535, (height, width)).astype(np.uint16),
            "intensity": rng.integers(0, 255, (height, width)).astype(np.uint8),   # 15 bytes:
            "t": rng.integers(-10**6, 10**6, (height, width)).astype(np.int32),    # padding
            "normal": rng.normal(size=(height, width, 3)).astype(np.float32),
            "range2": rng.uniform(0, 9, (height, width)).astype(np.float64)}


@pytest.mark.parametrize("as_dataclass", [True, False])
@pytest.mark.parametrize("bigendian", [False, True])
def test_golden_equal_to_make_scan_and_round_trip(as_dataclass: bool, bigendian: bool) -> None:
    info = _info(as_dataclass=as_dataclass)
    values = _channels(3, 5)
    kw: dict[str, Any] = dict(column_time_offsets=np.arange(5) * 7,
                              column_azimuth_angles=np.linspace(1, 0, 5), frame_id="f")
    ref = make_scan(info, values, 123_456_789_012, is_bigendian=bigendian,
                    as_dataclass=as_dataclass, **kw)
    buf = ScanBuffer(info, {k: (v.dtype, v.shape[2]) if v.ndim == 3 else v.dtype
                            for k, v in values.items()},
                     is_bigendian=bigendian, as_dataclass=as_dataclass)
    for name, v in values.items():
        assert not buf.views[name].any()                 # zero-filled
        buf.views[name][...] = v
    scan = buf.build(123_456_789_012, **kw)
    assert bytes(scan.data) == bytes(ref.data)            # golden: make_scan's bytes
    assert [(c.name, c.offset, c.datatype, c.count) for c in scan.channels] == \
        [(c.name, c.offset, c.datatype, c.count) for c in ref.channels]
    assert (scan.header, scan.lidar_info_time, scan.is_bigendian) == \
        (ref.header, ref.lidar_info_time, ref.is_bigendian)
    assert list(scan.column_time_offsets) == list(ref.column_time_offsets)
    lidarscan.scan.validate(scan, info)
    for name, v in values.items():                        # round trip through the readers
        np.testing.assert_array_equal(lidarscan.scan.channel(scan, name), v)


def test_build_wraps_the_filled_block() -> None:
    info = _info(as_dataclass=False)
    buf = ScanBuffer(info, {"range": np.uint16})
    buf.views["range"][1, 2] = 0xBEEF
    msg = buf.build(0)
    assert lidarscan.scan.channel(msg, "range")[1, 2] == 0xBEEF
    assert msg.data.typecode == "B" and len(msg.data) == 3 * 5 * 2
    dc = ScanBuffer(_info(), {"range": np.uint16}, as_dataclass=True)
    scan = dc.build(0)
    assert np.shares_memory(scan.data, dc.views["range"]) and not scan.data.flags.writeable


def test_bad_channel_specs_raise() -> None:
    for bad in ({"": np.uint8}, {"x": np.complex64}, {"x": (np.uint8, 0)}):
        with pytest.raises(ValidationError):
            ScanBuffer(_info(), bad)
