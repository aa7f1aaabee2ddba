"""Ouster importer: sensor metadata JSON -> LidarInfo, decoded frames -> LidarScan.

Geometry mapping (exact; see ``msgs/msg/LidarInfo.msg`` and the Ouster "Lidar range to XYZ"
formula). With H beams, W measurement columns, angles in degrees and lengths in mm in the JSON:

=========================  ==================================================================
LidarInfo field            from the metadata
=========================  ==================================================================
horizontal_angles[c]       2*pi*(1 - c/W)   (encoder angle; columns sweep clockwise)
beam_azimuth_offsets[u]    -radians(beam_azimuth_angles[u])  (Ouster's sign is clockwise)
vertical_angles[u]         radians(beam_altitude_angles[u])  (row 0 = top, as Ouster's rows)
beam_origins[u]            (B03*cos(beta_u), -B03*sin(beta_u), B23) / 1000
beam_range_offsets[u]      -n / 1000, n = B03 if B23 == 0 else hypot(B03, B23)
lidar_to_sensor_transform  lidar_to_sensor_transform, translation mm -> m (or identity)
pixel_shift_by_row         data_format.pixel_shift_by_row
column_time_increment      1e9 / (fps * W) ns, fps from lidar_mode ("1024x10") or fps
range_multiplier           0.001 (raw ranges are mm), range_offset 0
=========================  ==================================================================

B is ``beam_to_lidar_transform`` (mm); when absent (firmware 2.x), B = I with
B03 = ``lidar_origin_to_beam_origin_mm`` or the product default (OS-0 27.67, OS-1 15.806,
OS-2 13.762, others 12.163 mm). Every Ouster beam of a column fires at the column's time, so
``beam_time_offsets`` is empty (all zero).

Both JSON layouts are read: the flat layout of firmware 2.x (``beam_altitude_angles`` etc. at the
top level plus a ``data_format`` object) and the nested layout of newer firmware / ouster-sdk
(``beam_intrinsics``, ``lidar_intrinsics``, ``lidar_data_format``, ``config_params``,
``sensor_info``, ...).
"""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from lidarscan.errors import DecodeError, ValidationError
from lidarscan.scan import make_info, make_scan

__all__ = [
    "default_beam_origin_mm",
    "info_from_metadata",
    "load_metadata",
    "scan_from_frame",
    "scans_from_recording",
]

#: Beam-origin distance (mm) used when the metadata has neither ``beam_to_lidar_transform`` nor
#: ``lidar_origin_to_beam_origin_mm`` (per product family, as the Ouster SDK does).
_DEFAULT_BEAM_ORIGIN_MM = {"0": 27.67, "1": 15.806, "2": 13.762}
_OTHER_BEAM_ORIGIN_MM = 12.163

#: Nominal valid range interval (m) per product family: wide envelopes around the datasheet
#: figures, so that no real return is outside; informational (projection never filters).
_RANGE_LIMITS = {"0": (0.3, 120.0), "1": (0.3, 240.0), "2": (0.3, 450.0)}
_OTHER_RANGE_LIMITS = (0.3, 240.0)

_RANGE_MULTIPLIER = 0.001  # Ouster ranges are integer millimetres

_IDENTITY = [1.0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]


# ------------------------------------------------------------------------------ metadata

def load_metadata(src: str | os.PathLike[str] | Mapping[str, Any]) -> tuple[dict[str, Any], str]:
    """Parse Ouster metadata given as a path, JSON text or an already parsed mapping.

    Returns:
        (parsed dict, JSON text): the text is the file's content verbatim (or ``json.dumps`` of a
        mapping).

    Raises:
        DecodeError: unreadable file or invalid JSON, or JSON that is not an object.
    """
    if isinstance(src, Mapping):
        data = dict(src)
        try:
            text = json.dumps(data)
        except (TypeError, ValueError) as err:
            raise DecodeError("metadata", type(src).__name__,
                              "a JSON-serialisable mapping") from err
        return data, text
    if isinstance(src, (bytes, bytearray)):
        src = bytes(src).decode("utf-8", errors="replace")
    if isinstance(src, str) and src.lstrip().startswith("{"):
        text = src
    else:
        path = Path(os.fspath(src))
        try:
            text = path.read_text(encoding="utf-8")
        except OSError as err:
            raise DecodeError("metadata", str(path),
                              "a readable Ouster metadata JSON file, JSON text or a dict") from err
    try:
        data = json.loads(text)
    except json.JSONDecodeError as err:
        raise DecodeError("metadata", text[:60],
                          f"valid JSON ({err.msg} at line {err.lineno} column {err.colno})"
                          ) from err
    if not isinstance(data, dict):
        raise DecodeError("metadata", type(data).__name__, "a JSON object at the top level")
    return data, text


def _family(prod_line: str) -> str:
    """Product family digit ("0", "1", "2") of e.g. "OS-1-128", "OS0-64", or "" if unknown."""
    match = re.match(r"\s*OS-?(\d)", prod_line, re.IGNORECASE)
    return match.group(1) if match else ""


def default_beam_origin_mm(prod_line: str) -> float:
    """Product default of ``lidar_origin_to_beam_origin_mm`` (OS-0/1/2, else 12.163 mm)."""
    return _DEFAULT_BEAM_ORIGIN_MM.get(_family(prod_line), _OTHER_BEAM_ORIGIN_MM)


class _Lookup:
    """Reads metadata keys from the nested layout (section -> key) or the flat legacy one."""

    def __init__(self, data: dict[str, Any]) -> None:
        self.data = data
        self.nested = isinstance(data.get("beam_intrinsics"), dict) or isinstance(
            data.get("sensor_info"), dict)

    def get(self, key: str, sections: tuple[str, ...], default: Any = None) -> Any:
        """First value of ``key`` found in ``sections`` (nested) or at the top level / in
        ``data_format`` (legacy); ``default`` when absent everywhere."""
        for section in sections:
            sub = self.data.get(section)
            if isinstance(sub, dict) and key in sub:
                return sub[key]
        if key in self.data:
            return self.data[key]
        legacy_fmt = self.data.get("data_format")
        if isinstance(legacy_fmt, dict) and key in legacy_fmt:
            return legacy_fmt[key]
        return default

    def require(self, key: str, sections: tuple[str, ...]) -> Any:
        value = self.get(key, sections)
        if value is None:
            where = f"{sections[0]}.{key}" if self.nested and sections else key
            raise DecodeError(f"metadata.{where}", None,
                              "this key in the Ouster metadata (flat firmware-2.x layout or the "
                              "nested beam_intrinsics/lidar_data_format/... layout)")
        return value


def _float_array(value: Any, field: str, length: int | None = None) -> np.ndarray[Any, Any]:
    try:
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as err:
        raise DecodeError(f"metadata.{field}", value, "a list of numbers") from err
    if length is not None and arr.size != length:
        raise ValidationError(f"metadata.{field}", f"length {arr.size}", f"length {length}")
    if not np.all(np.isfinite(arr)):
        raise ValidationError(f"metadata.{field}", arr[~np.isfinite(arr)][:3].tolist(),
                              "finite numbers")
    return arr


#: Upper bound on columns per frame accepted from metadata (Ouster modes go up to 4096); it keeps
#: a corrupt file from allocating gigabytes of per-column tables.
MAX_COLUMNS = 1 << 16


def _int(value: Any, field: str) -> int:
    try:
        result = int(value)
    except (TypeError, ValueError, OverflowError) as err:
        raise DecodeError(f"metadata.{field}", value, "an integer") from err
    if result != value and not isinstance(value, str):
        raise DecodeError(f"metadata.{field}", value, "an integer")
    return result


def _parse_mode(mode: Any) -> tuple[int, int]:
    """(columns, fps) of a lidar_mode string like "1024x10"."""
    match = re.fullmatch(r"\s*(\d+)\s*x\s*(\d+)\s*", str(mode))
    if not match or int(match.group(1)) <= 0 or int(match.group(2)) <= 0:
        raise DecodeError("metadata.lidar_mode", mode,
                          'a lidar mode "<columns>x<fps>" such as "1024x10"')
    return int(match.group(1)), int(match.group(2))


def _transform_m(value: Any, field: str) -> np.ndarray[Any, Any]:
    """Row-major 4x4 in mm -> float64 (16,) with the translation in metres."""
    matrix = _float_array(value, field, 16).reshape(4, 4).copy()
    matrix[:3, 3] *= 0.001
    return matrix.reshape(16)


def info_from_metadata(src: str | os.PathLike[str] | Mapping[str, Any], *, stamp_ns: int = 0,
                       frame_id: str | None = None, use_lidar_to_sensor: bool = True,
                       as_dataclass: bool = False) -> Any:
    """LidarInfo from Ouster sensor metadata (exact geometry, see the module docstring).

    Args:
        src: path to the metadata JSON, the JSON text, or the parsed dict (flat firmware-2.x
            layout or the current nested layout).
        stamp_ns: header.stamp of the info (its version key), int ns.
        frame_id: header.frame_id; default "os_sensor", or "os_lidar" when
            ``use_lidar_to_sensor`` is false.
        use_lidar_to_sensor: express points in Ouster's sensor frame (apply the metadata's
            lidar_to_sensor_transform, usually yaw 180 deg plus a z offset); false: in the lidar
            frame (identity transform). User extrinsics (ouster-sdk's ``extrinsic``,
            sensor -> body) are never applied: that is a TF concern.
        as_dataclass: return :class:`lidarscan.types.LidarInfo` instead of the rclpy message.

    Returns:
        ``lidarscan_msgs.msg.LidarInfo`` (H = pixels_per_column, W = columns_per_frame) with
        vendor "Ouster", model = prod_line, serial = prod_sn, firmware = build_rev, beam_ids
        0..H-1 and the JSON text verbatim in ``vendor_metadata``.

    Raises:
        DecodeError: unreadable/invalid JSON or a missing key (named in the error).
        ValidationError: arrays of the wrong length, non-finite values, inconsistent sizes.
    """
    data, text = load_metadata(src)
    meta = _Lookup(data)
    beam = ("beam_intrinsics",)
    fmt = ("lidar_data_format",)
    ident = ("sensor_info",)

    altitudes = _float_array(meta.require("beam_altitude_angles", beam), "beam_altitude_angles")
    height = altitudes.size
    if height == 0:
        raise ValidationError("metadata.beam_altitude_angles", "length 0", "one angle per beam")
    azimuths = _float_array(meta.require("beam_azimuth_angles", beam), "beam_azimuth_angles",
                            height)
    pixels = meta.get("pixels_per_column", fmt)
    if pixels is not None and _int(pixels, "pixels_per_column") != height:
        raise ValidationError("metadata.pixels_per_column", pixels,
                              f"{height} (the length of beam_altitude_angles)")

    mode = meta.get("lidar_mode", ("config_params",))
    mode_cols, mode_fps = _parse_mode(mode) if mode is not None else (0, 0)
    columns = meta.get("columns_per_frame", fmt)
    width = _int(columns, "columns_per_frame") if columns is not None else mode_cols
    if not 0 < width <= MAX_COLUMNS:
        raise DecodeError("metadata.columns_per_frame", width,
                          f"a column count in 1..{MAX_COLUMNS} (columns_per_frame or lidar_mode)")
    if mode_cols and mode_cols != width:
        raise ValidationError("metadata.columns_per_frame", width,
                              f"{mode_cols} (from lidar_mode {mode!r})")
    fps_value = meta.get("fps", fmt)
    fps = _int(fps_value, "fps") if fps_value not in (None, 0) else mode_fps
    column_time_increment = round(1e9 / (fps * width)) if fps > 0 else 0

    shifts_value = meta.get("pixel_shift_by_row", fmt)
    if shifts_value is not None:
        shifts = _float_array(shifts_value, "pixel_shift_by_row", height)
        if not np.all(shifts == np.round(shifts)):
            raise ValidationError("metadata.pixel_shift_by_row", shifts.tolist()[:8], "integers")
        shifts = shifts.astype(np.int64)
    else:
        # firmware 1.x metadata: no data_format; derive a stagger from the beam azimuths
        # (any constant added to all shifts is an equally valid destaggered layout).
        shifts = np.round((azimuths - azimuths.min()) * width / 360.0).astype(np.int64)

    prod_line = str(meta.get("prod_line", ident, "") or "")
    b2l = meta.get("beam_to_lidar_transform", beam)
    if b2l is not None:
        b_matrix = _float_array(b2l, "beam_to_lidar_transform", 16).reshape(4, 4)
        b03, b23 = float(b_matrix[0, 3]), float(b_matrix[2, 3])
    else:
        origin = meta.get("lidar_origin_to_beam_origin_mm", beam)
        b03 = (float(_float_array(origin, "lidar_origin_to_beam_origin_mm", 1)[0])
               if origin is not None else default_beam_origin_mm(prod_line))
        b23 = 0.0
    n_mm = b03 if b23 == 0.0 else math.hypot(b03, b23)

    beta = -np.deg2rad(azimuths)
    origins = np.stack([b03 * np.cos(beta), -b03 * np.sin(beta), np.full(height, b23)], -1)
    origins *= 0.001

    if use_lidar_to_sensor:
        transform = _transform_m(meta.require("lidar_to_sensor_transform", ("lidar_intrinsics",)),
                                 "lidar_to_sensor_transform")
        default_frame = "os_sensor"
    else:
        transform = np.asarray(_IDENTITY, np.float64)
        default_frame = "os_lidar"

    range_min, range_max = _RANGE_LIMITS.get(_family(prod_line), _OTHER_RANGE_LIMITS)
    return make_info(
        stamp_ns=stamp_ns,
        frame_id=default_frame if frame_id is None else frame_id,
        vertical_angles=np.deg2rad(altitudes),
        horizontal_angles=2.0 * np.pi * (1.0 - np.arange(width, dtype=np.float64) / width),
        beam_azimuth_offsets=beta,
        beam_origins=origins.reshape(-1),
        beam_range_offsets=np.full(height, -0.001 * n_mm),
        lidar_to_sensor_transform=transform,
        pixel_shift_by_row=shifts.astype(np.int32),
        column_time_increment=column_time_increment,
        beam_ids=np.arange(height, dtype=np.uint16),
        range_multiplier=_RANGE_MULTIPLIER,
        range_offset=0.0,
        range_min=range_min,
        range_max=range_max,
        vendor="Ouster",
        model=prod_line,
        serial_number=str(meta.get("prod_sn", ident, "") or ""),
        firmware_version=str(meta.get("build_rev", ident, "") or ""),
        vendor_metadata=text,
        as_dataclass=as_dataclass,
    )


# --------------------------------------------------------------------------------- frames

#: canonical channel name -> accepted frame keys (the .npz names, then ouster-sdk field names)
_CHANNELS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("intensity", ("signal", "SIGNAL")),
    ("reflectivity", ("reflectivity", "REFLECTIVITY")),
    ("ambient", ("near_ir", "NEAR_IR")),
    ("flags", ("flags", "FLAGS")),
)
_CHANNELS2: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("intensity2", ("signal2", "SIGNAL2")),
    ("reflectivity2", ("reflectivity2", "REFLECTIVITY2")),
    ("flags2", ("flags2", "FLAGS2")),
)
_RANGE_KEYS = ("range_mm", "RANGE")
_RANGE2_KEYS = ("range2_mm", "RANGE2")
_TIME_KEYS = ("timestamps_ns", "timestamp")
_STATUS_KEYS = ("status",)


def _pick(frame: Mapping[str, Any], keys: tuple[str, ...]) -> tuple[str, Any] | None:
    for key in keys:
        if key in frame and frame[key] is not None:
            return key, frame[key]
    return None


def _image(frame: Mapping[str, Any], keys: tuple[str, ...], height: int, width: int
           ) -> np.ndarray[Any, Any] | None:
    found = _pick(frame, keys)
    if found is None:
        return None
    key, value = found
    arr = np.asarray(value)
    if arr.shape != (height, width):
        raise ValidationError(f"frame[{key!r}].shape", arr.shape,
                              f"({height}, {width}) from the LidarInfo")
    if arr.dtype.kind not in "iu":
        raise ValidationError(f"frame[{key!r}].dtype", str(arr.dtype), "an integer image")
    return arr


def _narrow(arr: np.ndarray[Any, Any], key: str) -> np.ndarray[Any, Any]:
    """Integer image in a PointField type (uint64/int64 from some readers -> uint32/uint16)."""
    if arr.dtype.itemsize <= 4:
        return arr
    if arr.size and (arr.min() < 0 or arr.max() > np.iinfo(np.uint32).max):
        raise ValidationError(f"frame[{key!r}]", int(arr.max()), "values that fit in uint32")
    return arr.astype(np.uint32)


def _column_times(frame: Mapping[str, Any], width: int, valid: np.ndarray[Any, Any],
                  increment: int) -> np.ndarray[Any, Any] | None:
    """(W,) int64 ns of every measurement column on the sensor clock, or None if absent.

    Valid columns keep their timestamp; invalid ones (outside the column window, dropped) are
    filled by linear interpolation between valid neighbours and by the nominal increment
    beyond the first/last valid column.
    """
    found = _pick(frame, _TIME_KEYS)
    if found is None:
        return None
    key, value = found
    times = np.asarray(value)
    if times.shape != (width,) or times.dtype.kind not in "iu":
        raise ValidationError(f"frame[{key!r}]", f"{times.dtype} {times.shape}",
                              f"({width},) integer nanoseconds")
    times = times.astype(np.int64)
    usable = valid & (times != 0)
    if usable.all():
        return times
    if not usable.any():
        return None
    index = np.flatnonzero(usable)
    columns = np.arange(width)
    filled = np.interp(columns, index, times[index].astype(np.float64))
    first, last = index[0], index[-1]
    filled[:first] = times[first] - (first - columns[:first]) * increment
    filled[last + 1:] = times[last] + (columns[last + 1:] - last) * increment
    out = np.round(filled).astype(np.int64)
    out[usable] = times[usable]
    return out


def scan_from_frame(frame: Mapping[str, Any], info: Any, *, stamp_ns: int | None = None,
                    range_encoding: str = "float32", destagger: bool = False,
                    as_dataclass: bool = False) -> Any:
    """LidarScan from one decoded Ouster frame (staggered images, one column per measurement).

    Args:
        frame: arrays by name, as in the test fixtures / ouster-sdk ``LidarFrame`` fields:
            ``range_mm`` (or ``RANGE``) (H, W) uint32 mm, 0 = no return; optional ``signal``,
            ``reflectivity``, ``near_ir``, ``flags`` and the second-return ``range2_mm``,
            ``signal2``, ``reflectivity2``, ``flags2``; ``timestamps_ns`` (W,) column times
            (sensor clock, ns); ``status`` (W,) column status (bit 0 = valid).
        info: the LidarInfo of the sensor (from :func:`info_from_metadata`).
        stamp_ns: header.stamp; default the (sensor-clock) time of measurement column 0, i.e.
            its timestamp, or, when column 0 is not valid, the first valid column's timestamp
            minus its index times ``info.column_time_increment``.
        range_encoding: "float32": ``range`` channel in float32 metres (raw 0 -> +Inf);
            "uint32_mm": ``range`` stays the raw UINT32 millimetres (lossless; decoded with
            ``info.range_multiplier`` = 0.001, raw 0 = no return).
        destagger: store the images destaggered (``is_destaggered`` true).
        as_dataclass: return :class:`lidarscan.types.LidarScan` instead of the rclpy message.

    Returns:
        LidarScan with channels range, intensity (signal, uint16), reflectivity (uint8), ambient
        (near_ir, uint16), flags (uint8) -- those present in ``frame`` -- then range2,
        intensity2, reflectivity2, flags2 for dual-return frames. Columns whose status is not
        valid get no return (range +Inf / raw 0); other channels are copied unchanged.
        ``column_time_offsets`` = column timestamps - timestamp of column 0 (always relative to
        the sensor-clock column 0, also when ``stamp_ns`` is given).

    Raises:
        ValidationError: missing range image, wrong shapes/dtypes, bad ``range_encoding`` or an
            info whose range_multiplier is not 0.001 for "uint32_mm".
    """
    height, width = int(info.height), int(info.width)
    if range_encoding not in ("float32", "uint32_mm"):
        raise ValidationError("range_encoding", range_encoding, '"float32" or "uint32_mm"')
    if range_encoding == "uint32_mm" and not math.isclose(float(info.range_multiplier),
                                                          _RANGE_MULTIPLIER, rel_tol=1e-12):
        raise ValidationError("LidarInfo.range_multiplier", float(info.range_multiplier),
                              '0.001 (millimetres) for range_encoding="uint32_mm"')
    rng = _image(frame, _RANGE_KEYS, height, width)
    if rng is None:
        raise ValidationError("frame", sorted(frame), f"a range image under one of {_RANGE_KEYS}")

    valid = np.ones(width, bool)
    found = _pick(frame, _STATUS_KEYS)
    if found is not None:
        status = np.asarray(found[1])
        if status.shape != (width,) or status.dtype.kind not in "iub":
            raise ValidationError("frame['status']", f"{status.dtype} {status.shape}",
                                  f"({width},) integer column status")
        valid = (status.astype(np.int64) & 1) != 0

    def ranges(raw: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
        raw = raw.astype(np.uint32)  # a copy: never touch the caller's arrays
        raw[:, ~valid] = 0
        if range_encoding == "uint32_mm":
            return raw
        metres = (raw.astype(np.float64) * _RANGE_MULTIPLIER).astype(np.float32)
        metres[raw == 0] = np.inf
        return metres

    channels: dict[str, np.ndarray[Any, Any]] = {"range": ranges(rng)}
    for name, keys in _CHANNELS:
        arr = _image(frame, keys, height, width)
        if arr is not None:
            channels[name] = _narrow(arr, keys[0])
    rng2 = _image(frame, _RANGE2_KEYS, height, width)
    if rng2 is not None:
        channels["range2"] = ranges(rng2)
    for name, keys in _CHANNELS2:
        arr = _image(frame, keys, height, width)
        if arr is not None:
            channels[name] = _narrow(arr, keys[0])

    increment = int(info.column_time_increment)
    times = _column_times(frame, width, valid, increment)
    offsets = None
    if times is not None:
        offsets = times - times[0]
        if stamp_ns is None:
            stamp_ns = int(times[0])
    if stamp_ns is None:
        raise ValidationError("stamp_ns", None,
                              "a stamp (the frame has no valid column timestamps)")

    if destagger:
        from lidarscan.geometry import make_projector
        projector = make_projector(info)
        channels = {name: projector.destagger(arr) for name, arr in channels.items()}
    return make_scan(info, channels, int(stamp_ns), is_destaggered=destagger,
                     column_time_offsets=offsets, as_dataclass=as_dataclass)


# ------------------------------------------------------------- recordings (ouster-sdk, optional)

def scans_from_recording(path: str | os.PathLike[str], *,
                         meta: str | os.PathLike[str] | None = None, stamp_ns: int = 0,
                         use_lidar_to_sensor: bool = True, range_encoding: str = "float32",
                         destagger: bool = False, as_dataclass: bool = False
                         ) -> Iterator[tuple[Any, Any]]:
    """Read an Ouster pcap/OSF recording through ouster-sdk (optional extra ``[ouster]``).

    Args:
        path: the recording (.pcap with ``meta``, or .osf with embedded metadata).
        meta: metadata JSON path for a pcap (optional if ouster-sdk finds it itself).
        stamp_ns: version key of the produced LidarInfo.
        use_lidar_to_sensor, range_encoding, destagger, as_dataclass: as in
            :func:`info_from_metadata` / :func:`scan_from_frame`.

    Yields:
        (LidarScan, LidarInfo) per frame of the first sensor; the same info for every frame.

    Raises:
        ImportError: ouster-sdk is not installed.
    """
    try:
        import ouster.sdk as ouster_sdk
    except ImportError as err:  # pragma: no cover - depends on the environment
        raise ImportError("reading Ouster recordings needs ouster-sdk: "
                          "pip install 'lidarscan[ouster]'") from err
    kwargs: dict[str, Any] = {}
    if meta is not None:
        kwargs["meta"] = [os.fspath(meta)]
    open_source: Any = getattr(ouster_sdk, "open_source")  # noqa: B009 (not re-exported)
    source = open_source(os.fspath(path), **kwargs)
    try:
        infos = source.sensor_info
        sensor = infos[0] if isinstance(infos, (list, tuple)) else infos
        info = info_from_metadata(sensor.to_json_string(), stamp_ns=stamp_ns,
                                  use_lidar_to_sensor=use_lidar_to_sensor,
                                  as_dataclass=as_dataclass)
        names = {"RANGE": "range_mm", "RANGE2": "range2_mm", "SIGNAL": "signal",
                 "SIGNAL2": "signal2", "REFLECTIVITY": "reflectivity",
                 "REFLECTIVITY2": "reflectivity2", "NEAR_IR": "near_ir", "FLAGS": "flags",
                 "FLAGS2": "flags2"}
        for item in source:
            # a LidarFrame, or a FrameSet / list with one frame per sensor (first sensor used)
            frame: Any = item if hasattr(item, "status") else item[0]
            if frame is None:
                continue
            arrays: dict[str, Any] = {names[f]: np.asarray(frame.field(f))
                                      for f in frame.fields if f in names}
            arrays["timestamps_ns"] = np.asarray(frame.timestamp)
            arrays["status"] = np.asarray(frame.status)
            yield scan_from_frame(arrays, info, range_encoding=range_encoding,
                                  destagger=destagger, as_dataclass=as_dataclass), info
    finally:
        close = getattr(source, "close", None)
        if callable(close):
            close()

