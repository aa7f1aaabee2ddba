"""LidarScan <-> numpy: build scans, view channels without copying, validate scans and infos.

Every function accepts rclpy messages (``lidarscan_msgs.msg``) and the dataclasses of
:mod:`lidarscan.types` (what :func:`lidarscan.decode` returns) alike.
"""

from __future__ import annotations

import array
import dataclasses
import itertools
import math
from collections.abc import Collection, Mapping, Sequence
from typing import Any

import numpy as np

from lidarscan._install import have_messages
from lidarscan.datatypes import DTYPES, FLOAT32, FLOAT64, datatype_of, dtype_of
from lidarscan.errors import (
    ChannelLayoutError,
    InfoMismatchError,
    LinkageError,
    UnknownChannelError,
    ValidationError,
)
from lidarscan.stamps import split_ns, to_ns

__all__ = [
    "ChannelWant",
    "ScanViews",
    "as_array",
    "azimuth_channel",
    "make_scan",
    "ScanBuffer",
    "make_info",
    "channel",
    "channel_names",
    "data_view",
    "range_m",
    "read_views",
    "validate",
    "validate_info",
    "to_native",
    "RANGE_CHANNELS",
    "return_channel",
    "return_channels",
    "return_of",
]

#: Channel names that hold a range (decoded by :func:`range_m`).
RANGE_CHANNELS = ("range", "range2", "range3")

_ALIGN = 8  # channel blocks start at multiples of 8 bytes inside ``data``


def data_view(scan: Any) -> np.ndarray[Any, np.dtype[np.uint8]]:
    """Read-only uint8 view of ``scan.data`` (never a copy; rclpy's buffer is writable)."""
    data = scan.data
    if isinstance(data, np.ndarray) and data.dtype == np.uint8 and data.ndim == 1:
        if not data.flags.writeable:
            return data
        view = data.view()
    else:
        view = np.frombuffer(data, np.uint8)
    view.flags.writeable = False
    return view


def channel_names(scan: Any) -> list[str]:
    """Names of the scan's channels in descriptor order."""
    return [c.name for c in scan.channels]


def return_channel(name: str, number: int) -> str:
    """The name of the ``number``-th return of channel ``name`` (msgs/README.md: the N-th
    return appends N): ``name`` itself for the first return, ``range2`` for (``range``, 2).

    Raises:
        ValidationError: ``number`` below 1.
    """
    if int(number) < 1:
        raise ValidationError("return number", number, "an integer >= 1 (1: the first return)")
    return name if int(number) == 1 else f"{name}{int(number)}"


def return_of(name: str, names: Collection[str]) -> tuple[str, int]:
    """(first-return channel, N) of channel ``name`` among the scan's channel ``names``: the
    inverse of :func:`return_channel` (msgs/README.md's rule).

    ``name`` is the N-th return (N >= 2) of ``base`` when it is ``base`` followed by the
    decimal N (no leading zero) and ``base`` is also one of ``names``: ``range2`` ->
    (``range``, 2), ``intensity3`` -> (``intensity``, 3). Any other name is a first return of
    itself, ``(name, 1)``: ``range``, ``near_ir``, ``range1``, ``beam7`` without ``beam``. (A
    return stored in the same channel, ``count`` = 2, is no separate channel.)
    """
    base = name.rstrip("0123456789")
    digits = name[len(base):]
    if base and digits and digits[0] != "0" and int(digits) >= 2 and base in names:
        return base, int(digits)
    return name, 1


def return_channels(base: str, names: Collection[str]) -> list[str]:
    """The channels among ``names`` that hold the returns of channel ``base``, by return
    number (:func:`return_of`): ``["range", "range2", "range3"]`` for ``"range"`` of a
    triple-return scan; [] without ``base``."""
    found = sorted((number, name) for name in names
                   for first, number in [return_of(name, names)] if first == base)
    return [name for _, name in found]


def _find(scan: Any, name: str) -> Any:
    for desc in scan.channels:
        if desc.name == name:
            return desc
    raise UnknownChannelError("name", name, f"one of {channel_names(scan)}")


def channel(scan: Any, name: str, *, native: bool = False) -> np.ndarray[Any, Any]:
    """Zero-copy, read-only view of one channel.

    Args:
        scan: a LidarScan (rclpy message or decoded dataclass).
        name: channel name, e.g. ``"range"``.
        native: return the values in the machine's byte order: the view itself when the scan's
            byte order already is, else a converted copy (``scan.data`` is never modified).
            Algorithms and compiled kernels take native arrays only; byte order is a property
            of the message, handled here once.

    Returns:
        array of shape (height, width) when the channel's count is 1, else (height, width, count),
        with the declared datatype and the scan's byte order (native order with ``native``),
        aliasing ``scan.data`` unless converted. Column order is the scan's (see
        ``scan.is_destaggered``).

    Raises:
        UnknownChannelError: no channel of that name.
        ChannelLayoutError / UnknownDatatypeError: the descriptor does not fit ``data``.
    """
    desc = _find(scan, name)
    big = bool(scan.is_bigendian)
    dtype = DTYPES.get((desc.datatype, big))
    if dtype is None:                      # not an id: dtype_of names the bad value
        dtype = dtype_of(desc.datatype, big, field=f"channels[{name!r}].datatype")
    height, width, count = int(scan.height), int(scan.width), int(desc.count)
    if count < 1:
        raise ChannelLayoutError(f"channels[{name!r}].count", count, "count >= 1")
    data = data_view(scan)
    n = height * width * count
    offset = int(desc.offset)
    end = offset + n * dtype.itemsize
    if offset < 0 or end > data.size:
        raise ChannelLayoutError(f"channels[{name!r}].offset", offset,
                                 f"a block of {n * dtype.itemsize} bytes inside data "
                                 f"({data.size} bytes)")
    shape = (height, width) if count == 1 else (height, width, count)
    try:
        view = np.frombuffer(data, dtype, n, offset).reshape(shape)
    except ValueError as err:  # e.g. 4294967295 x 0 x 4294967295: too big a shape for numpy
        raise ChannelLayoutError(f"channels[{name!r}] shape", shape,
                                 "height x width x count that numpy can index") from err
    return to_native(view) if native else view


def to_native(values: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """``values`` in the machine's byte order: itself when already native, else a copy."""
    if values.dtype.isnative:
        return values
    return values.astype(values.dtype.newbyteorder("="))


def range_m(scan: Any, info: Any = None, name: str = "range") -> np.ndarray[Any, Any]:
    """A range channel as float32 metres with REP 117 meanings.

    Float channels are returned as float32 (a view when already native float32). Integer channels
    decode as ``raw * info.range_multiplier + info.range_offset`` with raw 0 -> +Inf (no return).

    Returns:
        (height, width) float32, metres along the beam, scan column order.

    Raises:
        InfoMismatchError: an integer range channel without an info whose multiplier is > 0.
    """
    raw = channel(scan, name)
    if raw.ndim == 3:
        raw = raw[..., 0]
    if raw.dtype.kind == "f":   # native float32: always (a view when the scan already is)
        return raw if raw.dtype == np.dtype("=f4") else raw.astype(np.float32)
    mult = float(info.range_multiplier) if info is not None else 0.0
    if not mult > 0.0 or not np.isfinite(mult):
        raise InfoMismatchError("range_multiplier", mult,
                                f"> 0 to decode the integer channel {name!r} "
                                "(pass the scan's LidarInfo)")
    out = raw.astype(np.float64) * mult + float(info.range_offset)
    out = out.astype(np.float32)
    out[raw == 0] = np.inf
    return out


def azimuth_channel(scan: Any, range_channel: str = "range") -> str | None:
    """Name of the scan's per-pixel azimuth channel for ``range_channel``, or None.

    ``azimuth`` followed by the return suffix of the range channel (``range2`` -> ``azimuth2``),
    else ``azimuth`` itself (one azimuth for every return).
    """
    names = {c.name for c in scan.channels}
    suffix = range_channel[len("range"):] if range_channel.startswith("range") else ""
    for name in (f"azimuth{suffix}", "azimuth"):
        if name in names:
            return name
    return None


@dataclasses.dataclass(frozen=True)
class ChannelWant:
    """One channel image a reader wants of each scan (:func:`read_views`).

    Attributes:
        key: the name the reader knows it by (a field name, ``"intensity"``).
        names: candidate channel names, first found wins (aliases).
        per_return: for the N-th return's range channel (``range2``), first look for that
            return's channel of each candidate (``intensity2``), then the candidates themselves
            (a channel measured once per pixel, such as ``ambient``, serves every return).
        required: a missing channel raises :class:`lidarscan.errors.UnknownChannelError`
            (naming the first candidate); else its view is None.
        first: a channel with count > 1 gives its first element (an (H, W) view).
    """

    key: str
    names: tuple[str, ...]
    per_return: bool = False
    required: bool = False
    first: bool = True


@dataclasses.dataclass
class ScanViews:
    """What a reader asked of one scan (:func:`read_views`), native byte order, scan column
    order.

    Attributes:
        raw: the range channel (H, W), its native datatype (first element of a count > 1
            channel), or None (not asked for).
        metres: the range channel as (H*W,) float32 metres, C-contiguous (:func:`range_m`),
            or None (not asked for).
        channels: :attr:`ChannelWant.key` -> (H, W) or (H, W, count) view, None when missing
            and not required.
        column_azimuth_angles: the scan's measured column azimuths, float64 radians (W,) or
            empty (the info's apply).
        column_time_offsets: the scan's column times, ns since the stamp (W,) or empty.
        azimuth: the per-pixel azimuth channel of the range channel (:func:`azimuth_channel`),
            or None.
    """

    raw: np.ndarray[Any, Any] | None
    metres: np.ndarray[Any, Any] | None
    channels: dict[str, np.ndarray[Any, Any] | None]
    column_azimuth_angles: np.ndarray[Any, Any]
    column_time_offsets: np.ndarray[Any, Any]
    azimuth: str | None


def read_views(scan: Any, channels: Sequence[ChannelWant] = (), *, range_channel: str = "range",
               info: Any = None, raw: bool = False, metres: bool = False) -> ScanViews:
    """Everything a converter reads of one scan's channels and column arrays, in one call.

    Args:
        scan: a LidarScan (rclpy message or dataclass).
        channels: the channel images wanted (:class:`ChannelWant`).
        range_channel: the range channel ("range", "range2", ...): its return number selects
            the channels of :attr:`ChannelWant.per_return` and the azimuth channel.
        info: the scan's LidarInfo, to decode an integer range channel for ``metres``.
        raw, metres: whether to read the range channel natively, as metres.

    Returns:
        :class:`ScanViews` (views alias ``scan.data`` where its byte order is native).

    Raises:
        UnknownChannelError: the range channel (when asked for) or a required channel is
            missing.
        InfoMismatchError: ``metres`` of an integer range channel without a multiplier > 0.
    """
    names = [c.name for c in scan.channels]
    raw_view = metres_view = None
    if raw:
        raw_view = channel(scan, range_channel, native=True)
        if raw_view.ndim == 3:
            raw_view = raw_view[..., 0]
    if metres:
        metres_view = np.ascontiguousarray(range_m(scan, info, range_channel)).reshape(-1)
    number = 1
    for want in channels:
        if want.per_return:
            number = return_of(range_channel, names)[1]
            break
    views: dict[str, np.ndarray[Any, Any] | None] = {}
    for want in channels:
        candidates = list(want.names)
        if want.per_return and number != 1:
            candidates = [return_channel(n, number) for n in want.names] + candidates
        found = None
        for name in candidates:
            if name in names:
                found = name
                break
        if found is None and not want.required:
            views[want.key] = None
            continue
        # a missing required channel is reported by the channel lookup itself
        image = channel(scan, candidates[0] if found is None else found, native=True)
        if image.ndim == 3 and want.first:
            image = image[..., 0]
        views[want.key] = image
    return ScanViews(raw=raw_view, metres=metres_view, channels=views,
                     column_azimuth_angles=as_array(scan.column_azimuth_angles, np.float64),
                     column_time_offsets=as_array(scan.column_time_offsets, np.int64),
                     azimuth=azimuth_channel(scan, range_channel))


def _block(values: np.ndarray[Any, Any], name: str, height: int, width: int,
           is_bigendian: bool) -> tuple[int, int, bytes]:
    arr = np.asarray(values)
    if arr.ndim not in (2, 3) or arr.shape[:2] != (height, width):
        raise ValidationError(f"channels[{name!r}].shape", arr.shape,
                              f"({height}, {width}) or ({height}, {width}, count) from the info")
    count = 1 if arr.ndim == 2 else arr.shape[2]
    if count < 1:
        raise ValidationError(f"channels[{name!r}].shape", arr.shape, "count >= 1")
    datatype = datatype_of(arr.dtype, field=f"channels[{name!r}].dtype")
    target = dtype_of(datatype, is_bigendian)
    raw = np.ascontiguousarray(arr, dtype=target).tobytes()
    return datatype, count, raw


def make_scan(info: Any, channels: Mapping[str, Any], stamp_ns: int, *,
              frame_id: str | None = None, is_destaggered: bool = False,
              column_time_offsets: Any = None, column_azimuth_angles: Any = None,
              is_bigendian: bool = False, as_dataclass: bool = False) -> Any:
    """Build a valid LidarScan from channel arrays.

    Args:
        info: the LidarInfo the scan belongs to (its height, width, header.stamp and frame_id).
        channels: name -> array of shape (H, W) or (H, W, count) of int8..uint32, float32 or
            float64. The canonical ``range`` is float32 metres (+Inf = no return). Blocks are laid
            out in mapping order, each starting at a multiple of 8 bytes. The arrays are copied,
            never modified.
        stamp_ns: header.stamp in int ns: the time of measurement column 0.
        frame_id: header.frame_id (default: the info's).
        is_destaggered: whether the arrays are destaggered (see LidarScan.msg).
        column_time_offsets: (W,) int ns of each measurement column relative to ``stamp_ns``.
        column_azimuth_angles: (W,) measured azimuth per measurement column, radians.
        is_bigendian: byte order of the channel blocks (little-endian by default).
        as_dataclass: always return the dataclass :class:`lidarscan.types.LidarScan` (what
            :func:`lidarscan.decode_scan` returns; no ROS libraries needed). When False, the
            dataclass is still returned if ``lidarscan_msgs`` is not built into this
            environment (a plain ``pip install``: see :mod:`lidarscan._install`).

    Returns:
        the rclpy message ``lidarscan_msgs.msg.LidarScan`` (to publish), or the dataclass
        ``lidarscan.types.LidarScan`` (see ``as_dataclass``); every lidarscan and converters
        function takes either. ``lidar_info_time`` equals ``info.header.stamp``.

    Raises:
        ValidationError: wrong shape, unsupported dtype, bad time/azimuth arrays.
    """
    height, width = int(info.height), int(info.width)
    pieces: list[bytes] = []
    descs: list[tuple[str, int, int, int]] = []
    offset = 0
    for name, values in channels.items():
        if not isinstance(name, str) or not name:
            raise ValidationError("channels", name, "non-empty str channel names")
        datatype, count, raw = _block(values, name, height, width, is_bigendian)
        pad = -offset % _ALIGN
        if pad:
            pieces.append(b"\x00" * pad)
            offset += pad
        descs.append((name, offset, datatype, count))
        pieces.append(raw)
        offset += len(raw)
    return _assemble(info, descs, b"".join(pieces), stamp_ns, frame_id, is_destaggered,
                     column_time_offsets, column_azimuth_angles, is_bigendian, as_dataclass)


def _assemble(info: Any, descs: list[tuple[str, int, int, int]], data: Any, stamp_ns: int,
              frame_id: str | None, is_destaggered: bool, column_time_offsets: Any,
              column_azimuth_angles: Any, is_bigendian: bool, as_dataclass: bool) -> Any:
    """The scan (message or dataclass) around ``data``: bytes, or an ``array.array('B')`` /
    uint8 ndarray that becomes the scan's buffer without a copy."""
    height, width = int(info.height), int(info.width)
    times = _column_array(column_time_offsets, width, np.int64, "column_time_offsets")
    azimuths = _column_array(column_azimuth_angles, width, np.float64, "column_azimuth_angles")
    sec, nanosec = split_ns(stamp_ns)
    info_stamp = info.header.stamp
    if frame_id is None:
        frame_id = info.header.frame_id
    if as_dataclass or not have_messages():
        from lidarscan import types
        data_arr = data if isinstance(data, np.ndarray) else np.frombuffer(data, np.uint8)
        return types.LidarScan(
            header=types.Header(types.Time(sec, nanosec), frame_id),
            lidar_info_time=types.Time(int(info_stamp.sec), int(info_stamp.nanosec)),
            height=height, width=width, is_bigendian=bool(is_bigendian),
            is_destaggered=bool(is_destaggered),
            column_time_offsets=_readonly(times), column_azimuth_angles=_readonly(azimuths),
            channels=tuple(types.LidarChannel(*d) for d in descs), data=data_arr)
    from builtin_interfaces.msg import Time
    from lidarscan_msgs.msg import LidarChannel, LidarScan
    from std_msgs.msg import Header
    msg = LidarScan()
    msg.header = Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=frame_id)
    msg.lidar_info_time = Time(sec=int(info_stamp.sec), nanosec=int(info_stamp.nanosec))
    msg.height, msg.width = height, width
    msg.is_bigendian, msg.is_destaggered = bool(is_bigendian), bool(is_destaggered)
    # rosidl converts numpy arrays element by element: hand it array.array / bytes instead.
    msg.column_time_offsets = array.array("q", times.tobytes())
    msg.column_azimuth_angles = array.array("d", azimuths.tobytes())
    msg.channels = [LidarChannel(name=n, offset=o, datatype=t, count=c) for n, o, t, c in descs]
    msg.data = data
    return msg


def _readonly(arr: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    arr.flags.writeable = False
    return arr


class ScanBuffer:
    """Fast path of :func:`make_scan` for producers that fill channels in place.

    Allocates one zeroed ``data`` block laid out exactly as :func:`make_scan` lays out channels
    of these dtypes (mapping order, blocks at multiples of 8 bytes), exposes a writable view of
    each channel to fill, and :meth:`build` wraps the block into the scan **without copying
    it** (an rclpy message gets the ``array.array('B')`` the views write into; a dataclass a
    read-only ndarray over it). make_scan copies each channel out, joins them, and rclpy copies
    again. One buffer makes one scan: after :meth:`build` the views must not be written.

    Args:
        info: the LidarInfo (height, width, header).
        channels: name -> numpy dtype of its elements, or (dtype, count) for ``count`` elements
            per pixel (int8..uint32, float32, float64).
        is_bigendian: byte order of the blocks (the views are in that order).
        as_dataclass: build :mod:`lidarscan.types` dataclasses instead of rclpy messages.
        zeroed: False: the views start with arbitrary bytes (no memset of the block; the
            caller writes every element); the padding between the channels is zero either way.
            rclpy message buffers are always zeroed.

    Attributes:
        views: name -> writable (H, W) or (H, W, count) ndarray over the block, zero-filled
            (unless ``zeroed`` is False).
    """

    def __init__(self, info: Any, channels: Mapping[str, Any], *, is_bigendian: bool = False,
                 as_dataclass: bool = False, zeroed: bool = True) -> None:
        self.info, self.is_bigendian, self.as_dataclass = info, bool(is_bigendian), as_dataclass
        height, width = int(info.height), int(info.width)
        layout = []
        offset = 0
        for name, spec in channels.items():
            if not isinstance(name, str) or not name:
                raise ValidationError("channels", name, "non-empty str channel names")
            dtype, count = spec if isinstance(spec, tuple) else (spec, 1)
            if int(count) < 1:
                raise ValidationError(f"channels[{name!r}] count", count, "count >= 1")
            datatype = datatype_of(np.dtype(dtype), field=f"channels[{name!r}].dtype")
            target = dtype_of(datatype, self.is_bigendian)
            offset += -offset % _ALIGN
            layout.append((name, offset, datatype, int(count), target))
            offset += height * width * int(count) * target.itemsize
        self._descs = [entry[:4] for entry in layout]
        # rclpy keeps an array.array('B') as the message's buffer (no conversion)
        self._data: Any = ((np.zeros if zeroed else np.empty)(offset, np.uint8) if as_dataclass
                           else array.array("B", bytes(offset)))
        block = np.frombuffer(self._data, np.uint8) if not as_dataclass else self._data
        if not zeroed and as_dataclass:
            end = 0
            for _, o, _, c, t in layout:                # the alignment padding
                block[end:o] = 0
                end = o + height * width * c * t.itemsize
        shape = (height, width)
        self.views: dict[str, np.ndarray[Any, Any]] = {
            name: block[o:o + height * width * c * t.itemsize].view(t).reshape(
                shape if c == 1 else (*shape, c))
            for name, o, _, c, t in layout}

    def build(self, stamp_ns: int, *, frame_id: str | None = None,
              is_destaggered: bool = False, column_time_offsets: Any = None,
              column_azimuth_angles: Any = None) -> Any:
        """The LidarScan around the filled block (arguments as in :func:`make_scan`)."""
        data = self._data
        if self.as_dataclass:
            data = _readonly(data)
        return _assemble(self.info, self._descs, data, stamp_ns, frame_id, is_destaggered,
                         column_time_offsets, column_azimuth_angles, self.is_bigendian,
                         self.as_dataclass)


def _column_array(values: Any, width: int, dtype: Any, field: str) -> np.ndarray[Any, Any]:
    if values is None:
        return np.zeros(0, dtype)
    arr = np.asarray(values)
    if arr.size == 0:
        return np.zeros(0, dtype)
    if arr.shape != (width,):
        raise ValidationError(f"{field}.shape", arr.shape, f"({width},) (one per column) or empty")
    if np.dtype(dtype).kind == "i" and arr.dtype.kind not in "iu":
        raise ValidationError(f"{field}.dtype", str(arr.dtype), "integer nanoseconds")
    if np.dtype(dtype).kind == "f" and not np.all(np.isfinite(arr)):
        raise ValidationError(field, arr[~np.isfinite(arr)][:3].tolist(), "finite angles")
    return np.ascontiguousarray(arr, dtype=dtype)


def make_info(*, stamp_ns: int, frame_id: str, vertical_angles: Any, horizontal_angles: Any,
              as_dataclass: bool = False, **fields: Any) -> Any:
    """Build a LidarInfo from arrays (H = len(vertical_angles), W = len(horizontal_angles)).

    Args:
        stamp_ns: header.stamp, the version key (int ns).
        frame_id: header.frame_id, the frame the projected points are expressed in.
        vertical_angles: (H,) radians, row 0 = highest beam.
        horizontal_angles: (W,) radians, azimuth of each measurement column (REP 103, CCW).
        as_dataclass: always return the dataclass :class:`lidarscan.types.LidarInfo` (what
            :func:`lidarscan.decode_info` returns). When False, the dataclass is still returned
            if ``lidarscan_msgs`` is not built into this environment (as in :func:`make_scan`).
        **fields: any other LidarInfo field by name (arrays as numpy/sequences).

    Returns:
        the rclpy message ``lidarscan_msgs.msg.LidarInfo``, or the dataclass
        ``lidarscan.types.LidarInfo`` (see ``as_dataclass``).

    Raises:
        ValidationError / InfoMismatchError: unknown field name or inconsistent arrays.
    """
    from lidarscan import types
    known = {f.name for f in dataclasses.fields(types.LidarInfo)} - {"header"}
    unknown = set(fields) - known
    if unknown:
        raise ValidationError("make_info", sorted(unknown), f"LidarInfo fields: {sorted(known)}")
    sec, nanosec = split_ns(stamp_ns)
    values: dict[str, Any] = {
        "height": len(vertical_angles), "width": len(horizontal_angles),
        "vertical_angles": vertical_angles, "horizontal_angles": horizontal_angles,
    }
    values.update(fields)
    if "lidar_to_sensor_transform" not in values:
        values["lidar_to_sensor_transform"] = np.eye(4).reshape(16)
    defaults = types.LidarInfo()
    arrays: dict[str, Any] = {}
    for name in known:
        default = getattr(defaults, name)
        if isinstance(default, np.ndarray):
            value = values.get(name, default)
            arr = np.ascontiguousarray(np.asarray(value, dtype=default.dtype).reshape(-1))
            arrays[name] = arr
    scalars = {n: values.get(n, getattr(defaults, n)) for n in known if n not in arrays}
    if as_dataclass or not have_messages():
        readonly: dict[str, Any] = {n: _readonly(a) for n, a in arrays.items()}
        info = types.LidarInfo(header=types.Header(types.Time(sec, nanosec), frame_id),
                               **readonly, **scalars)
    else:
        from builtin_interfaces.msg import Time
        from lidarscan_msgs.msg import LidarInfo
        from std_msgs.msg import Header
        info = LidarInfo()
        info.header = Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=frame_id)
        for name, arr in arrays.items():
            if name == "lidar_to_sensor_transform":
                info.lidar_to_sensor_transform = arr
            else:
                setattr(info, name, array.array(_TYPECODES[arr.dtype.char], arr.tobytes()))
        for name, value in scalars.items():
            setattr(info, name, value)
    validate_info(info)
    return info


_TYPECODES = {"d": "d", "q": "q", "l": "q", "i": "i", "H": "H"}


# ------------------------------------------------------------------------------- validation

def as_array(value: Any, dtype: Any) -> np.ndarray[Any, Any]:
    """A message array field (numpy array, ``array.array`` of rclpy, or a sequence) as numpy,
    without a copy where possible.

    Args:
        value: the field, e.g. ``info.horizontal_angles`` or ``scan.column_time_offsets``.
        dtype: the dtype for plain sequences; numpy arrays keep theirs, ``array.array`` its
            typecode (cast with ``.astype`` when a specific dtype matters).
    """
    if isinstance(value, np.ndarray):
        return value
    if isinstance(value, array.array):
        return np.frombuffer(value, dtype=value.typecode)
    return np.asarray(value, dtype=dtype)


#: Former private name of :func:`as_array`, kept for code outside the converter core.
_as_array = as_array


#: LidarInfo arrays in check order: field, length (a multiple of "h" height, "w" width, "hw"
#: pixels, or a fixed number), whether empty is allowed, the dtype of plain sequences (float
#: arrays must also hold finite values).
_INFO_ARRAYS: tuple[tuple[str, tuple[str, int], bool, Any], ...] = (
    ("vertical_angles", ("h", 1), False, float),
    ("horizontal_angles", ("w", 1), False, float),
    ("beam_azimuth_offsets", ("h", 1), True, float),
    ("pixel_azimuth_angles", ("hw", 1), True, float),
    ("pixel_altitude_angles", ("hw", 1), True, float),
    ("beam_origins", ("h", 3), True, float),
    ("beam_range_offsets", ("h", 1), True, float),
    ("pixel_shift_by_row", ("h", 1), True, np.int32),
    ("beam_time_offsets", ("h", 1), True, np.int64),
    ("beam_ids", ("h", 1), True, np.uint16),
    ("lidar_to_sensor_transform", ("", 16), False, float),
)
# np.allclose(a, b, atol) is |a - b| <= atol + 1e-5 * |b|: the bounds of the rigidity test
_LAST_ROW = np.array([0.0, 0.0, 0.0, 1.0])
_LAST_ROW_TOL = 1e-9 + 1e-5 * _LAST_ROW
_EYE3 = np.eye(3)
_EYE3_TOL = 1e-6 + 1e-5 * _EYE3


def _require_finite(arrays: list[tuple[str, np.ndarray[Any, Any]]]) -> None:
    """Raise for the first non-finite value of the first ``(field, array)`` holding one (one
    vectorised test over all of them first: the common case, all finite, costs one pass)."""
    if not arrays:
        return
    joined = arrays[0][1] if len(arrays) == 1 else np.concatenate([a for _, a in arrays])
    if np.isfinite(joined).all():
        return
    for field, arr in arrays:
        bad = np.flatnonzero(~np.isfinite(arr))
        if bad.size:
            raise InfoMismatchError(f"LidarInfo.{field}[{int(bad[0])}]", float(arr[bad[0]]),
                                    "finite values")


def _is_rigid(transform: np.ndarray[Any, Any]) -> bool:
    """Whether a finite row-major 4x4 is rigid: orthonormal rotation (to 1e-6), det > 0, last
    row 0 0 0 1 (to 1e-9): ``np.allclose``'s tests, without its overhead."""
    matrix = np.asarray(transform, float).reshape(4, 4)
    rot = matrix[:3, :3]
    if not ((np.abs(matrix[3] - _LAST_ROW) <= _LAST_ROW_TOL).all()
            and (np.abs(rot @ rot.T - _EYE3) <= _EYE3_TOL).all()):
        return False
    (a, b, c), (d, e, f), (g, h, i) = rot.tolist()
    return a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g) > 0


def validate_info(info: Any) -> None:
    """Check a LidarInfo for internal consistency.

    Each array is read once (a view of a numpy / ``array.array`` field); the finiteness of all
    float arrays is tested in one pass. Errors come in the order of :data:`_INFO_ARRAYS`: a
    length error of a later array is raised after the non-finite values of earlier ones.

    Raises:
        InfoMismatchError: an array of the wrong length, a non-finite angle/offset, a transform
            that is not rigid, a bad range multiplier or limits.
    """
    height, width = int(info.height), int(info.width)
    to_ns(info.header.stamp, field="LidarInfo.header.stamp")
    units = {"h": height, "w": width, "hw": height * width, "": 1}
    floats: list[tuple[str, np.ndarray[Any, Any]]] = []   # still to be tested for finiteness
    pixel_az_size = 0
    arr = np.zeros(0)
    for field, (unit, per_unit), may_be_empty, dtype in _INFO_ARRAYS:
        arr = as_array(getattr(info, field), dtype)
        expected = units[unit] * per_unit
        if arr.size != expected and not (may_be_empty and arr.size == 0):
            _require_finite(floats)
            what = f"{expected}" + (" or 0 (empty)" if may_be_empty else "")
            raise InfoMismatchError(f"LidarInfo.{field}", f"length {arr.size}",
                                    f"length {what} for height={info.height}, width={info.width}")
        if dtype is float and arr.size:
            floats.append((field, arr.reshape(-1)))
        if field == "pixel_azimuth_angles":
            pixel_az_size = arr.size
        elif field == "pixel_altitude_angles" and arr.size != pixel_az_size:
            _require_finite(floats)
            raise InfoMismatchError("LidarInfo.pixel_altitude_angles", f"length {arr.size}",
                                    f"the length of pixel_azimuth_angles ({pixel_az_size})")
    _require_finite(floats)
    transform = arr                                       # the last one of _INFO_ARRAYS
    if transform.any() and not _is_rigid(transform):
        raise InfoMismatchError("LidarInfo.lidar_to_sensor_transform",
                                np.asarray(transform, float).reshape(4, 4).round(6).tolist(),
                                "a rigid transform (orthonormal rotation, last row 0 0 0 1), "
                                "or all zeros for identity")
    scalars = []
    for field in ("range_multiplier", "range_offset", "range_min", "range_max"):
        value = float(getattr(info, field))
        if not math.isfinite(value):
            raise InfoMismatchError(f"LidarInfo.{field}", value, "a finite number")
        scalars.append(value)
    mult, _, range_min, range_max = scalars
    if mult < 0:
        raise InfoMismatchError("LidarInfo.range_multiplier", mult,
                                ">= 0 (0 only when no integer range channel is used)")
    if range_min < 0 or (range_max > 0 and range_min > range_max):
        raise InfoMismatchError("LidarInfo.range_min", range_min,
                                f"0 <= range_min <= range_max ({range_max})")
    if int(info.column_time_increment) < 0:
        raise InfoMismatchError("LidarInfo.column_time_increment",
                                int(info.column_time_increment), ">= 0 ns")


def validate(scan: Any, info: Any = None) -> None:
    """Check a LidarScan (and, if given, that it fits and links to ``info``).

    Checks: channel names unique and non-empty; datatypes 1..8; count >= 1; every block inside
    ``data``; no two blocks overlapping; ``data`` no longer than the last block end (plus
    alignment < 8 bytes); per-column arrays of length 0 or width with finite angles; with info:
    the info itself, height/width equal, ``lidar_info_time == info.header.stamp``, and a usable
    range multiplier for integer range channels.

    Raises:
        ChannelLayoutError, UnknownDatatypeError, ValidationError, InfoMismatchError,
        LinkageError: the first inconsistency found, naming field, value and expectation.
    """
    height, width = int(scan.height), int(scan.width)
    to_ns(scan.header.stamp, field="LidarScan.header.stamp")
    size = len(data_view(scan))
    blocks: list[tuple[int, int, str]] = []
    seen: set[str] = set()
    for i, desc in enumerate(scan.channels):
        name = desc.name
        if not name:
            raise ChannelLayoutError(f"channels[{i}].name", name, "a non-empty name")
        if name in seen:
            raise ChannelLayoutError(f"channels[{i}].name", name, "unique channel names")
        seen.add(name)
        itemsize = dtype_of(desc.datatype, field=f"channels[{i}].datatype ({name!r})").itemsize
        if int(desc.count) < 1:
            raise ChannelLayoutError(f"channels[{i}].count ({name!r})", int(desc.count), ">= 1")
        if max(height, 1) * max(width, 1) * int(desc.count) * itemsize >= 2**63:
            raise ChannelLayoutError(f"channels[{i}].count ({name!r})", int(desc.count),
                                     f"a block size that fits in 63 bits for {height}x{width} "
                                     "(numpy's limit, also for empty grids)")
        start = int(desc.offset)
        end = start + height * width * int(desc.count) * itemsize
        if start < 0 or end > size:
            raise ChannelLayoutError(f"channels[{i}].offset ({name!r})", start,
                                     f"a block [{start}, {end}) inside data of {size} bytes "
                                     f"({height}x{width}x{int(desc.count)} x {itemsize} bytes)")
        blocks.append((start, end, name))
    blocks.sort()
    for (_, e0, n0), (s1, _, n1) in itertools.pairwise(blocks):
        if s1 < e0:
            raise ChannelLayoutError(f"channels[{n1!r}].offset", s1,
                                     f">= {e0}, the end of channel {n0!r} (blocks overlap)")
    last = max((e for _, e, _ in blocks), default=0)
    if size - last >= _ALIGN or (not blocks and size):
        raise ChannelLayoutError("data", f"length {size}",
                                 f"length {last} (end of the last channel block)")
    for field, kind in (("column_time_offsets", np.int64), ("column_azimuth_angles", np.float64)):
        arr = as_array(getattr(scan, field), kind)
        if arr.size not in (0, width):
            raise ValidationError(f"LidarScan.{field}", f"length {arr.size}",
                                  f"length {width} (width) or 0")
        if arr.dtype.kind == "f" and arr.size and not np.all(np.isfinite(arr)):
            raise ValidationError(f"LidarScan.{field}", arr[~np.isfinite(arr)][:3].tolist(),
                                  "finite angles")
    if info is None:
        return
    validate_info(info)
    if (int(info.height), int(info.width)) != (height, width):
        raise InfoMismatchError("LidarScan.height x width", f"{height}x{width}",
                                f"{int(info.height)}x{int(info.width)} from the LidarInfo")
    scan_key = to_ns(scan.lidar_info_time, field="LidarScan.lidar_info_time")
    info_key = to_ns(info.header.stamp, field="LidarInfo.header.stamp")
    if scan_key != info_key:
        raise LinkageError("LidarScan.lidar_info_time", scan_key,
                           f"{info_key} (the LidarInfo's header.stamp, in ns)")
    for desc in scan.channels:
        if desc.name in RANGE_CHANNELS and int(desc.datatype) not in (FLOAT32, FLOAT64) \
                and not float(info.range_multiplier) > 0:
            raise InfoMismatchError("LidarInfo.range_multiplier", float(info.range_multiplier),
                                    f"> 0 for the integer range channel {desc.name!r}")
