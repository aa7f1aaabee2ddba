"""lidarscan.scan.read_views: everything a converter reads of a scan's channels in one call,
checked against the per-channel API (channel, range_m, return_channel) over random scans of
every datatype, count and byte order."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings

import lidarscan
from lidarscan.errors import InfoMismatchError, UnknownChannelError
from lidarscan.scan import ChannelWant, channel, range_m, read_views
from test_scan import _bits, _info, scan_inputs


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    return a.shape == b.shape and a.dtype == b.dtype and np.array_equal(_bits(a), _bits(b))


def _scan_of(inputs: Any) -> tuple[Any, dict[str, np.ndarray]]:
    """(scan, its channels) of one scan_inputs() draw."""
    height, width, channels, big = inputs
    scan = lidarscan.make_scan(_info(height, width), channels, 5, is_bigendian=big,
                               as_dataclass=True)
    return scan, channels


@settings(max_examples=60, deadline=None)
@given(scan_inputs())
def test_views_equal_the_channel_lookups(inputs: Any) -> None:
    scan, channels = _scan_of(inputs)
    wants = [ChannelWant(n, (n,), required=True, first=False) for n in channels]
    wants += [ChannelWant("absent", ("no_such", "nor_this"))]
    found = read_views(scan, wants)
    assert found.channels["absent"] is None
    for name in channels:
        view = found.channels[name]
        assert view is not None and view.dtype.isnative
        assert _same(view, channel(scan, name, native=True))
    assert found.raw is None and found.metres is None and found.azimuth is None


@settings(max_examples=40, deadline=None)
@given(scan_inputs())
def test_first_element_and_per_return_follow_the_return_rule(inputs: Any) -> None:
    scan, channels = _scan_of(inputs)
    for rng in ("range", "range2"):
        if rng not in channels:
            continue
        found = read_views(scan, [ChannelWant("i", ("intensity", "signal"), per_return=True),
                                  ChannelWant("a", ("ambient",), per_return=True)],
                           range_channel=rng, raw=True)
        raw = channel(scan, rng, native=True)
        assert _same(found.raw, raw if raw.ndim == 2 else raw[..., 0])
        # the loop oracle of ChannelWant.per_return: the range's return first, then the names
        # (range2 is a second return only beside range: msgs/README.md)
        suffix = "2" if rng == "range2" and "range" in channels else ""
        for key, names in (("i", ("intensity", "signal")), ("a", ("ambient",))):
            order = [n + suffix for n in names] + list(names) if suffix else list(names)
            name = next((n for n in order if n in channels), None)
            if name is None:
                assert found.channels[key] is None
                continue
            want = channel(scan, name, native=True)
            assert _same(found.channels[key], want if want.ndim == 2 else want[..., 0])


def test_metres_column_arrays_and_azimuth(small_info: Any) -> None:
    info = lidarscan.make_info(stamp_ns=7, frame_id="lidar", vertical_angles=[0.1, -0.1],
                               horizontal_angles=[3.0, 2.0, 1.0], range_multiplier=0.001,
                               range_offset=0.5, as_dataclass=True)
    raw = np.array([[0, 1000, 2500], [7, 0, 65535]], np.uint16)
    scan = lidarscan.make_scan(info, {"range2": raw, "range": raw, "azimuth2": raw,
                                      "azimuth": raw}, 9, is_bigendian=True,
                               column_time_offsets=[0, 10, 20], as_dataclass=True)
    found = read_views(scan, range_channel="range2", info=info, metres=True)
    assert found.metres.shape == (6,) and found.metres.flags.c_contiguous
    assert _same(found.metres, range_m(scan, info, "range2").reshape(-1))
    assert found.metres[0] == np.inf and found.azimuth == "azimuth2"
    assert found.column_time_offsets.tolist() == [0, 10, 20]
    assert found.column_azimuth_angles.size == 0
    assert read_views(scan, range_channel="range").azimuth == "azimuth"
    with pytest.raises(InfoMismatchError, match="range_multiplier"):
        read_views(scan, metres=True)                       # an integer range needs the info


def test_a_missing_required_channel_is_named(small_info: Any) -> None:
    scan = lidarscan.make_scan(small_info, {"range": np.ones((4, 8), np.float32)}, 3,
                               as_dataclass=True)
    with pytest.raises(UnknownChannelError, match="'intensity'"):
        read_views(scan, [ChannelWant("i", ("intensity", "signal"), required=True)])
    with pytest.raises(UnknownChannelError, match="'range2'"):
        read_views(scan, range_channel="range2", raw=True)
