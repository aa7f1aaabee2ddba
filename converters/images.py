"""LidarScan <-> one ``sensor_msgs/Image`` per channel (the image alternative), losslessly.

Conventions:

* One image per channel, keyed by channel name (images have no name field: a publisher puts
  each on its own topic, e.g. ``~/range_image``). Every image carries the scan's header (stamp of
  measurement column 0, frame id); nothing else of the scan travels (``lidar_info_time``,
  ``column_time_offsets`` and ``column_azimuth_angles`` have no place in an image: pass them to
  :func:`from_images` to restore them).
* Encodings per REP 118 / ``sensor_msgs/image_encodings``: a float32 range is ``32FC1`` in
  metres (+Inf no return, REP 117), integer channels ``8UC1``, ``8SC1``, ``16UC1``, ``16SC1``,
  ``32SC1``, float ``32FC1`` / ``64FC1``; a channel with count N > 1 is N-channel (``16UC2``).
* UINT32 (Ouster's native millimetres): ``image_encodings`` has no unsigned 32-bit name, so the
  datatype travels in the encoding as ``32UC<n>``, the name the ``<bits><U|S|F>C<n>`` pattern of
  ``image_encodings`` gives it (and OpenCV 5's ``CV_32U``): the image alone says what it holds
  and :func:`from_images` rebuilds UINT32 with nothing else given. Consumers that only take
  ``image_encodings`` names (cv_bridge) can ask ``uint32_as="32S"``: ``32SC1``, the same bits read
  signed; :func:`from_images` then needs ``datatypes`` to restore UINT32.
* Values are never converted: the image holds the channel's bytes in the scan's byte order
  (``is_bigendian`` copied), so the round trip is bit-exact (NaN payloads, -0, +-Inf included).
* Column order: destaggered images by default (what image tools expect: each column one
  azimuth), using ``info.pixel_shift_by_row``; ``destagger=False`` keeps the scan's order.
"""

from __future__ import annotations

import array
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from lidarscan.datatypes import dtype_of
from lidarscan.errors import ConversionError, UnknownChannelError

__all__ = ["ENCODINGS", "encoding_of", "from_images", "to_images"]

#: PointField datatype id -> encoding prefix (bits and kind); UINT32 is ``32U`` (module header).
ENCODINGS = {1: "8S", 2: "8U", 3: "16S", 4: "16U", 5: "32S", 6: "32U", 7: "32F", 8: "64F"}
_DATATYPE_OF_PREFIX = {prefix: datatype for datatype, prefix in ENCODINGS.items()}
_ALIASES = {"mono8": "8UC1", "mono16": "16UC1"}
_UINT32_PREFIXES = ("32U", "32S")


def encoding_of(datatype: int, count: int = 1, *, uint32_as: str = "32U") -> str:
    """Image encoding of a channel: ``32FC1`` for FLOAT32, ``16UC2`` for UINT16 count 2,
    ``32UC1`` for UINT32 (``32SC1`` with ``uint32_as="32S"``), ...

    Raises:
        UnknownDatatypeError: ``datatype`` is not a PointField id.
        ConversionError: ``uint32_as`` is not ``32U`` or ``32S``.
    """
    dtype_of(datatype)  # validates the id
    if uint32_as not in _UINT32_PREFIXES:
        raise ConversionError("uint32_as", uint32_as, f"one of {list(_UINT32_PREFIXES)}")
    prefix = uint32_as if int(datatype) == 6 else ENCODINGS[int(datatype)]
    return f"{prefix}C{int(count)}"


def _parse_encoding(encoding: str, name: str) -> tuple[int, int]:
    enc = _ALIASES.get(encoding, encoding)
    prefix, sep, count = enc.partition("C")
    if not sep or prefix not in _DATATYPE_OF_PREFIX or not count.isdigit() or int(count) < 1:
        raise ConversionError(f"images[{name!r}].encoding", encoding,
                              "one of 8UC<n>, 8SC<n>, 16UC<n>, 16SC<n>, 32SC<n>, 32UC<n>, "
                              "32FC<n>, 64FC<n>, mono8, mono16")
    return _DATATYPE_OF_PREFIX[prefix], int(count)


def _order(info: Any, scan_destaggered: bool, want_destaggered: bool
           ) -> tuple[Any, bool] | None:
    """(projector, True to destagger / False to restagger) or None when no reordering."""
    if scan_destaggered == want_destaggered:
        return None
    import lidarscan as ls
    proj = ls.make_projector(info)
    if not np.any(proj.shifts):
        return None
    return proj, want_destaggered


def to_images(scan: Any, info: Any, *, channels: Sequence[str] | None = None,
              destagger: bool = True, uint32_as: str = "32U",
              as_dataclass: bool = False) -> dict[str, Any]:
    """One ``sensor_msgs/Image`` per channel of a LidarScan.

    Args:
        scan: the LidarScan (rclpy message or dataclass).
        info: its LidarInfo (for ``pixel_shift_by_row``; only read when reordering columns).
        channels: names to convert, in order (default: every channel of the scan).
        destagger: images in destaggered column order (else the scan's own order).
        uint32_as: ``"32U"`` (default: UINT32 channels are ``32UC<n>``, lossless) or ``"32S"``
            (``32SC<n>``, ``image_encodings`` names only; the reader then passes ``datatypes``).
        as_dataclass: return :mod:`lidarscan.types` dataclasses instead of rclpy messages.

    Returns:
        channel name -> Image (height x width, encoding per channel datatype and count, header
        and byte order of the scan, ``step`` = width x count x itemsize).

    Raises:
        UnknownChannelError: a requested channel is not in the scan.
        ConversionError: ``uint32_as`` is neither ``32U`` nor ``32S``.
    """
    import lidarscan as ls
    encoding_of(6, uint32_as=uint32_as)  # validates the option before any work
    names = ls.channel_names(scan) if channels is None else list(channels)
    order = _order(info, bool(scan.is_destaggered), bool(destagger) or bool(scan.is_destaggered))
    descs = {c.name: c for c in scan.channels}
    if as_dataclass:
        from lidarscan.types import message_class
        image_cls = message_class("sensor_msgs/msg/Image")
    else:
        from sensor_msgs.msg import Image as image_cls  # type: ignore[no-redef]
    out = {}
    for name in names:
        if name not in descs:
            raise UnknownChannelError("channels", name, f"one of {list(descs)}")
        arr = ls.channel(scan, name)
        if order is not None:
            proj, forward = order
            arr = proj.destagger(arr) if forward else proj.restagger(arr)
        desc = descs[name]
        raw = np.ascontiguousarray(arr).tobytes()
        step = int(scan.width) * int(desc.count) * arr.dtype.itemsize
        fields = dict(height=int(scan.height), width=int(scan.width),
                      encoding=encoding_of(int(desc.datatype), int(desc.count),
                                           uint32_as=uint32_as),
                      is_bigendian=int(bool(scan.is_bigendian)), step=step)
        if as_dataclass:
            out[name] = image_cls(header=scan.header, data=np.frombuffer(raw, np.uint8), **fields)
        else:
            from builtin_interfaces.msg import Time
            from std_msgs.msg import Header
            header = Header(stamp=Time(sec=int(scan.header.stamp.sec),
                                       nanosec=int(scan.header.stamp.nanosec)),
                            frame_id=str(scan.header.frame_id))
            msg = image_cls(header=header, **fields)
            msg.data = array.array("B", raw)
            out[name] = msg
    return out


def from_images(images: Mapping[str, Any], info: Any, *, destaggered: bool = True,
                is_destaggered: bool | None = None,
                datatypes: Mapping[str, int] | None = None,
                column_time_offsets: Any = None, column_azimuth_angles: Any = None,
                as_dataclass: bool = False) -> Any:
    """A LidarScan from one image per channel (inverse of :func:`to_images`).

    Args:
        images: channel name -> ``sensor_msgs/Image`` (rclpy or dataclass), in channel order;
            all of one size (the info's), one byte order, one header.
        info: the LidarInfo (size, ``pixel_shift_by_row``, the link stamp).
        destaggered: column order of the images.
        is_destaggered: column order of the scan to build (default: the images').
        datatypes: channel name -> PointField datatype of the same size overriding the
            encoding's (``UINT32`` for a ``32SC1`` image written with
            ``uint32_as="32S"``); default from the encoding (``32UC1`` is UINT32).
        column_time_offsets, column_azimuth_angles: the scan's per-column arrays (images carry
            none; default zeros / empty as :func:`lidarscan.make_scan`).
        as_dataclass: return a :class:`lidarscan.types.LidarScan`.

    Returns:
        The LidarScan: header of the first image, ``lidar_info_time`` = ``info.header.stamp``,
        channels with the images' bytes (bit-exact), byte order of the images.

    Raises:
        ConversionError: no images, unknown encoding, sizes, steps, headers or byte orders that
            disagree, a datatype override of another size.
    """
    import lidarscan as ls
    from lidarscan.stamps import to_ns
    if not images:
        raise ConversionError("images", images, "at least one channel image")
    height, width = int(info.height), int(info.width)
    target = destaggered if is_destaggered is None else bool(is_destaggered)
    order = _order(info, bool(destaggered), target)
    first = next(iter(images.values()))
    big = bool(first.is_bigendian)
    overrides = dict(datatypes or {})
    channels: dict[str, np.ndarray[Any, Any]] = {}
    for name, img in images.items():
        datatype, count = _parse_encoding(str(img.encoding), name)
        if name in overrides:
            wanted = int(overrides[name])
            if dtype_of(wanted).itemsize != dtype_of(datatype).itemsize:
                raise ConversionError(f"datatypes[{name!r}]", wanted,
                                      f"a datatype of {dtype_of(datatype).itemsize} bytes "
                                      f"(the image is {img.encoding})")
            datatype = wanted
        dtype = dtype_of(datatype, big)
        step = width * count * dtype.itemsize
        if (int(img.height), int(img.width)) != (height, width):
            raise ConversionError(f"images[{name!r}] size", (int(img.height), int(img.width)),
                                  f"({height}, {width}) from the LidarInfo")
        if int(img.step) != step or bool(img.is_bigendian) != big:
            raise ConversionError(f"images[{name!r}].step/is_bigendian",
                                  (int(img.step), bool(img.is_bigendian)),
                                  f"({step}, {big}): packed rows, one byte order for all")
        if (to_ns(img.header.stamp), img.header.frame_id) != (to_ns(first.header.stamp),
                                                               first.header.frame_id):
            raise ConversionError(f"images[{name!r}].header", img.header,
                                  "the header of the other images (one scan)")
        buf = img.data
        raw = np.frombuffer(buf if not isinstance(buf, list) else bytes(buf), np.uint8)
        if raw.size != height * step:
            raise ConversionError(f"images[{name!r}].data", raw.size,
                                  f"{height * step} bytes (height x step)")
        arr = raw.view(dtype).reshape((height, width) if count == 1 else (height, width, count))
        if order is not None:
            proj, forward = order
            arr = proj.destagger(arr) if forward else proj.restagger(arr)
        channels[name] = arr
    return ls.make_scan(info, channels, to_ns(first.header.stamp),
                        frame_id=str(first.header.frame_id), is_destaggered=target,
                        column_time_offsets=column_time_offsets,
                        column_azimuth_angles=column_azimuth_angles, is_bigendian=big,
                        as_dataclass=as_dataclass)
