"""The converter caches of to_pointcloud2 / to_laserscan (converters.shared.converter_cache):
an info object is keyed once per stamp, another object of the same content shares the
converter, a new version (new stamp, in place or not) gets its own, nothing is shared by
threads."""

from __future__ import annotations

import threading
from typing import Any

import numpy as np
import pytest

import lidarscan
from converters.pointcloud2 import converter as pc2
from converters.slices import converter as sl
from lidarscan.errors import LidarScanError
from lidarscan.stamps import split_ns

pytest.importorskip("sensor_msgs.msg")


def _info(stamp_ns: int = 5_000, tilt: float = 15.0) -> Any:
    """An rclpy LidarInfo message (mutable in place), 16 x 64."""
    return lidarscan.make_info(
        stamp_ns=stamp_ns, frame_id="lidar",
        vertical_angles=np.radians(np.linspace(tilt, -tilt, 16)),
        horizontal_angles=2 * np.pi * (1 - np.arange(64) / 64), column_time_increment=10_000)


def _scan(info: Any, stamp_ns: int = 10**9) -> Any:
    ranges = np.random.default_rng(stamp_ns).uniform(1.0, 5.0, (16, 64)).astype(np.float32)
    return lidarscan.make_scan(info, {"range": ranges}, stamp_ns)


@pytest.fixture(params=["pointcloud2", "laserscan"])
def api(request: Any, monkeypatch: pytest.MonkeyPatch) -> tuple[Any, Any]:
    """(convert(scan, info), the module's cache), with a fresh cache."""
    if request.param == "pointcloud2":
        monkeypatch.setattr(pc2, "_CACHE", pc2.ConverterCache())
        return (lambda scan, info: pc2.to_pointcloud2(scan, info)), pc2
    monkeypatch.setattr(sl, "_CACHE", sl.ConverterCache())
    return (lambda scan, info: sl.to_laserscan(scan, info, min_height=-1.0,
                                               max_height=1.0)), sl


def _converters(module: Any) -> list[Any]:
    return list(module._CACHE.idle.values())


def test_same_object_and_same_content_share_one_converter(api: Any) -> None:
    convert, module = api
    info = _info()
    convert(_scan(info), info)
    (conv,) = _converters(module)
    assert len(module._CACHE.keys) == 1
    convert(_scan(info), info)
    copy = lidarscan.decode_info(lidarscan.encode(info))       # another object, same content
    convert(_scan(copy), copy)
    assert _converters(module) == [conv] and len(module._CACHE.keys) == 2


def test_an_info_changed_in_place_with_a_new_stamp_is_a_new_version(api: Any) -> None:
    convert, module = api
    info = _info(stamp_ns=5_000)
    convert(_scan(info), info)
    (old,) = _converters(module)
    # the same message object, re-used for a new version: new geometry, new stamp
    info.vertical_angles = np.radians(np.linspace(5.0, -5.0, 16)).tolist()
    info.header.stamp.sec, info.header.stamp.nanosec = split_ns(6_000)
    out = convert(_scan(info), info)                 # linked to 6000: no LinkageError
    assert out is not None
    assert len(_converters(module)) == 2 and _converters(module)[0] is old
    new = _converters(module)[1]
    assert lidarscan.make_projector(new.info).info_stamp_ns == 6_000


def test_an_info_that_cannot_be_keyed_is_reported_by_the_converter(api: Any) -> None:
    convert, module = api
    info = _info()
    with pytest.raises((AttributeError, LidarScanError)):    # what the constructor says
        convert(_scan(info), object())
    assert _converters(module) == [] and module._CACHE.keys == {}


def test_concurrent_calls_never_share_a_converter(api: Any, monkeypatch: pytest.MonkeyPatch
                                                  ) -> None:
    convert, module = api
    info = _info()
    busy: set[int] = set()
    clash = []
    lock = threading.Lock()
    cls = pc2.PointCloud2Converter if module is pc2 else sl.SliceConverter
    real = cls.convert

    def watched(self: Any, *args: Any, **kwargs: Any) -> Any:
        with lock:
            if id(self) in busy:
                clash.append(id(self))
            busy.add(id(self))
        try:
            return real(self, *args, **kwargs)
        finally:
            with lock:
                busy.discard(id(self))

    monkeypatch.setattr(cls, "convert", watched)
    scans = [_scan(info, 10**9 + k) for k in range(8)]
    threads = [threading.Thread(target=lambda s=s: [convert(s, info) for _ in range(5)])
               for s in scans]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not clash and 1 <= len(_converters(module)) <= module._CACHE.size
