"""Height-filtered LaserScan slices of any PointCloud2 (no firing grid needed), several in one pass.

For clouds that have no LidarScan grid (Livox and other solid-state sensors, stereo, merged or
filtered clouds: everything pointcloud_to_laserscan accepts), with the conventions of the
structured slices (:mod:`converters.slices.converter`; grid, binning, value classes and fusion are
those of :mod:`converters.slices.spec`, read its docstring):

* points: fields ``x``, ``y``, ``z`` of any layout (any offsets, padding, ``point_step``,
  ``row_step``; Livox's 26-byte packed points), either byte order, each FLOAT32 or FLOAT64
  (:func:`converters.shared.cloud_layout.read_points`); a point with a NaN or infinite coordinate is
  skipped. Each point ``p`` (float64) goes once into the target frame: ``R @ p + t`` of the
  ``extrinsics`` (target <- cloud frame), evaluated as ``R[i,0]*x + R[i,1]*y + R[i,2]*z + t[i]``;
* band: the point takes part in a slice iff ``min_height <= z <= max_height`` (inclusive, target
  frame); its planar range is ``rho = sqrt(x*x + y*y)`` and its bin that of ``atan2(y, x)``
  (nearest bin, half-bin to the lower index, +pi and -pi share a bin on a full circle);
* values: ``range_min <= rho <= range_max`` (inclusive) gives ``rho`` (float32); ``rho <
  range_min`` gives ``-Inf`` (too close); ``rho > range_max`` (or beyond the float32 range) gives
  ``+Inf``; per bin a finite value beats ``-Inf`` beats ``+Inf``; the smallest ``rho`` wins and
  carries its intensity; equal values go to the first point in cloud order (row-major
  ``v * width + u``). A cloud carries no "no return" rays, so a bin no point reaches is an empty
  bin: it gets ``fill`` (default: what ``+Inf`` is published as, i.e. free space, as
  pointcloud_to_laserscan does). ``NaN`` never appears unless ``fill`` is NaN;
* default grid: full circle ``[-pi, pi)`` at ``angle_increment = pi/360`` (0.5 deg, the
  increment of pointcloud_to_laserscan; a cloud has no column resolution); ``range_min`` 0,
  ``range_max`` inf;
* time fields: ``header.stamp`` = the cloud's; ``scan_time`` and ``time_increment`` are 0 (a
  cloud's per-point times are not a sweep).

Several slices cost one pass over the points: every point is read and transformed once, its
bin computed once per distinct grid, then fused into each band it falls in (one reduction array
with all slices back to back, as :func:`converters.slices.spec.reduce_min` defines it, then
:func:`converters.slices.spec.decode` and :func:`converters.slices.spec.make_laserscan` per slice).

Backends (:func:`converters._kernels.select`, ``"cloud_slices"``): the numpy reference here
(:func:`_fuse_numpy`, then :func:`converters.slices.spec.decode` per slice) and the optional C kernel
of :mod:`converters._kernels.cloud_slices` (fusion and decoding in one call; it reads the
fields in place in the cloud's buffer, a copy only for a big-endian cloud or x, y, z of mixed
types). They give identical slices (the kernel's module says where numpy's own SIMD
``arctan2``, on AVX-512 CPUs, may differ from libm's by an ulp at a bin edge). What the kernel
needs of a cloud's field layout is worked out once per layout and kept.
"""

from __future__ import annotations

import array
import math
from collections.abc import Mapping
from typing import Any, NamedTuple

import numpy as np

from converters import _kernels

from converters.slices import spec as _grid

from converters.shared import options
from converters.slices.spec import AngleGrid, OutputOptions
from converters.shared.cloud_layout import check_extent, read_points
from converters.shared.frames import check_extrinsics
from converters.slices.converter import _OVERRIDES, SliceSpec, _as_spec, _Slice
from converters.shared.options import IfPresent
from lidarscan.datatypes import FLOAT32, FLOAT64, dtype_of
from lidarscan.errors import ConfigError, ConversionError
from lidarscan.stamps import to_ns

__all__ = ["DEFAULT_ANGLE_INCREMENT", "CloudSliceConverter", "cloud_points",
           "cloud_to_laserscan"]

#: default bin width of a cloud's slices (radians): pointcloud_to_laserscan's pi/360
DEFAULT_ANGLE_INCREMENT = math.pi / 360.0
_F32_MAX = float(np.finfo(np.float32).max)
_MAX_POINTS = 1 << 32            # tie keys are 32 bits


def cloud_points(cloud: Any) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any],
                                      np.ndarray[Any, Any]]:
    """The x, y, z fields of a PointCloud2 as flat (height * width,) arrays in cloud order.

    Views into the message's buffer when it is in native byte order and rows are contiguous
    (else copies); each float32 or float64 as its field says, native byte order.

    Raises:
        ConversionError: a missing x/y/z field, one that is not FLOAT32/FLOAT64 with count 1,
            or inconsistent sizes (:func:`converters.shared.cloud_layout.read_points`).
    """
    x, y, z = _xyz(cloud, read_points(cloud))
    return x, y, z


def _xyz(cloud: Any, points: np.ndarray[Any, Any]) -> tuple[np.ndarray[Any, Any], ...]:
    """:func:`cloud_points` from the cloud's :func:`read_points` view."""
    fields = {str(f.name): f for f in cloud.fields}
    out = []
    for axis in "xyz":
        f = fields.get(axis)
        if f is None:
            raise ConversionError("PointCloud2.fields", sorted(fields),
                                  f"a field '{axis}' (x, y and z are required)")
        if int(f.datatype) not in (FLOAT32, FLOAT64) or max(int(f.count), 1) != 1:
            raise ConversionError(f"PointCloud2 field '{axis}'",
                                  f"datatype {int(f.datatype)} count {int(f.count)}",
                                  f"FLOAT32 ({FLOAT32}) or FLOAT64 ({FLOAT64}), count 1")
        out.append(_native(points[axis].reshape(-1)))
    return tuple(out)


def _native(values: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """``values`` in native byte order (a copy only when they are not)."""
    return values if values.dtype.isnative else values.astype(values.dtype.newbyteorder("="))


def _intensity(cloud: Any, points: np.ndarray[Any, Any], wanted: str | None
               ) -> np.ndarray[Any, Any] | None:
    """(n,) native values of the intensity field (first element of a counted field), or
    None."""
    if wanted is None:
        return None
    names = [str(f.name) for f in cloud.fields]
    if isinstance(wanted, IfPresent) and wanted not in names:
        return None
    if wanted not in names:
        raise ConversionError("intensity_field", str(wanted),
                              f"a field of the cloud ({', '.join(names)}) or None")
    values = points[str(wanted)]
    if values.ndim == 3:
        values = values[..., 0]
    return _native(values.reshape(-1))


def _transform(x: np.ndarray[Any, Any], y: np.ndarray[Any, Any], z: np.ndarray[Any, Any],
               m: np.ndarray[Any, Any], row: int) -> np.ndarray[Any, Any]:
    """Row ``row`` of ``m @ [x y z 1]`` in float64, in the kernel's order of operations."""
    out: np.ndarray[Any, Any] = (m[row, 0] * x + m[row, 1] * y + m[row, 2] * z) + m[row, 3]
    return out


def _fuse_numpy(x: np.ndarray[Any, Any], y: np.ndarray[Any, Any], z: np.ndarray[Any, Any],
                m: np.ndarray[Any, Any], slices: list[_Slice], grids: list[AngleGrid],
                slice_grid: list[int], offsets: np.ndarray[Any, Any], size: int
                ) -> np.ndarray[Any, Any]:
    """The reference: (size,) int64 reduction array of all slices back to back.

    Args:
        x, y, z: (n,) float32/float64 coordinates in the cloud frame, cloud order.
        m: 4x4 float64 target <- cloud.
        slices, grids, slice_grid, offsets, size: the converter's configuration.
    """
    x64, y64, z64 = (np.asarray(a, np.float64) for a in (x, y, z))
    with np.errstate(invalid="ignore", over="ignore"):
        finite = np.isfinite(x64) & np.isfinite(y64) & np.isfinite(z64)
        idx = np.flatnonzero(finite)
        x64, y64, z64 = x64[idx], y64[idx], z64[idx]
        pz = _transform(x64, y64, z64, m, 2)
        bands = [(pz >= s.min_z) & (pz <= s.max_z) for s in slices]
        any_band = np.logical_or.reduce(bands) if bands else np.zeros(idx.size, bool)
        sel = np.flatnonzero(any_band)             # transform and atan2 once per point
        px = _transform(x64[sel], y64[sel], z64[sel], m, 0)
        py = _transform(x64[sel], y64[sel], z64[sel], m, 1)
        rho = np.sqrt(px * px + py * py)
    theta = np.arctan2(py, px)
    grid_bins = [grid.bins(theta) for grid in grids]
    bits = np.where(rho > _F32_MAX, _grid.CODE_POS_INF,
                    rho.astype(np.float32).view(np.int32).astype(np.int64))
    keys = idx[sel].astype(np.int64)
    all_bins, all_codes, all_keys = [], [], []
    for s, g, off, band in zip(slices, slice_grid, offsets, bands):
        bins = grid_bins[g]
        keep = band[sel] & (bins >= 0)
        codes = bits[keep].copy()
        codes[rho[keep] < s.options.range_min] = _grid.CODE_NEG_INF
        codes[rho[keep] > s.options.range_max] = _grid.CODE_POS_INF
        all_bins.append(bins[keep] + off)
        all_codes.append(codes)
        all_keys.append(keys[keep])
    return _grid.reduce_min(size, np.concatenate(all_bins), np.concatenate(all_codes),
                            np.concatenate(all_keys))


class CloudSliceConverter:
    """Several height slices of unstructured PointCloud2s, computed together in one pass.

    Args:
        slices: name -> :class:`converters.slices.converter.SliceSpec` (or a dict of its fields, the
            format of :class:`converters.slices.converter.SliceConverter`); order is kept.
        extrinsics: 4x4 pose of the cloud's frame in the target frame; None = the cloud's frame
            is the target frame. Heights and ranges are measured in the target frame.
        frame_id: header.frame_id of the slices (required with ``extrinsics``; default: the
            cloud's frame).
        angle_min, angle_max, angle_increment: grid (radians); default a full circle from -pi
            at :data:`DEFAULT_ANGLE_INCREMENT`.
        range_min, range_max: inclusive planar limits, metres; default 0 and inf.
        intensity_field: field whose value at the winning point becomes the intensity (any
            datatype, cast to float32), or None for an empty ``intensities``; the default
            ``IfPresent("intensity")`` uses ``intensity`` when the cloud has it.
        use_inf, inf_epsilon, fill: output values (see :class:`converters.slices.spec.OutputOptions`).
        backend: ``"auto"``, ``"numba"`` or ``"numpy"`` (:func:`converters._kernels.select`).

    Raises:
        ConfigError: a bad option, named (``"slices['floor'].max_height"``, ``"range_min"``...).
    """

    def __init__(self, slices: Mapping[str, SliceSpec | Mapping[str, Any]], *,
                 extrinsics: Any = None, frame_id: str | None = None,
                 angle_min: float | None = None, angle_max: float | None = None,
                 angle_increment: float | None = None, range_min: float | None = None,
                 range_max: float | None = None,
                 intensity_field: str | None = IfPresent("intensity"),
                 use_inf: bool = True, inf_epsilon: float = 1.0, fill: float | None = None,
                 backend: str = "auto") -> None:
        if not isinstance(slices, Mapping):
            raise ConfigError("slices", slices, "a non-empty dict of name -> SliceSpec")
        specs = {name: _as_spec(name, spec) for name, spec in slices.items()}
        common = {"angle_min": angle_min, "angle_max": angle_max,
                  "angle_increment": angle_increment, "range_min": range_min,
                  "range_max": range_max, "use_inf": use_inf, "inf_epsilon": inf_epsilon,
                  "fill": fill}
        options.slice_options(specs, {**common, "extrinsics": extrinsics, "frame_id": frame_id,
                                      "intensity_channel": None, "range_channel": "range",
                                      "backend": backend})
        options.name("intensity_field", intensity_field, allow_none=True)
        kernel = _kernels.select("cloud_slices", backend=backend).c
        self.extrinsics = check_extrinsics(extrinsics)
        self._frame_id = frame_id
        self.intensity_field = intensity_field
        self.slices = [self._build_slice(name, spec, common) for name, spec in specs.items()]
        self._size, self._offsets, self._grids, self._slice_grid = _grid.output_layout(
            [s.grid for s in self.slices])
        self._plan = None if kernel is None else self._kernel_plan()
        self._layouts: dict[Any, _Layout] = {}

    @staticmethod
    def _build_slice(name: str, spec: SliceSpec, common: Mapping[str, Any]) -> _Slice:
        if getattr(spec, "holes", None):
            raise ConfigError(f"slices[{name!r}].holes", spec.holes,
                              "off: a cloud has no rays to see a missing floor along (holes "
                              "need a LidarScan: to_laserscan / SliceConverter)")
        opts = {k: getattr(spec, k) if getattr(spec, k) is not None else common[k]
                for k in _OVERRIDES if k not in options.HOLE_KEYS}
        inc = DEFAULT_ANGLE_INCREMENT if opts["angle_increment"] is None \
            else opts["angle_increment"]
        amin = -math.pi if opts["angle_min"] is None else opts["angle_min"]
        amax = amin + 2.0 * math.pi if opts["angle_max"] is None else opts["angle_max"]
        grid = AngleGrid.create(amin, amax, inc)
        rmin = 0.0 if opts["range_min"] is None else opts["range_min"]
        rmax = math.inf if opts["range_max"] is None else opts["range_max"]
        out = OutputOptions.create(rmin, rmax, bool(opts["use_inf"]), opts["inf_epsilon"],
                                   opts["fill"])
        return _Slice(name, float(spec.min_height), float(spec.max_height), grid, out)

    def _kernel_plan(self) -> Any:
        """The configuration as the compiled kernel takes it."""
        from converters._kernels.cloud_slices import CloudSlicePlan

        m = self.extrinsics
        s, g = self.slices, self._grids
        return CloudSlicePlan(
            m=np.r_[m[:3, :3].reshape(-1), m[:3, 3]], zlo=[x.min_z for x in s],
            zhi=[x.max_z for x in s], rlo=[x.options.range_min for x in s],
            rhi=[x.options.range_max for x in s], sgrid=self._slice_grid, soff=self._offsets,
            inf_value=[x.options.inf_value for x in s],
            fill_value=[x.options.fill_value for x in s], gmin=[x.angle_min for x in g],
            ginc=[x.increment for x in g], gsize=[x.size for x in g],
            gfull=[x.full_circle for x in g], size=self._size)

    def fuse(self, cloud: Any) -> np.ndarray[Any, np.dtype[np.int64]]:
        """(total bins,) int64 reduction array of all slices back to back (diagnostics, tests).

        Raises:
            ConversionError: see :func:`cloud_points`; more than 2**32 points.
        """
        if self._plan is not None:
            return self._run(cloud, decode=False)[0]
        return self._fuse_numpy(read_points(cloud), cloud)

    def _fuse_numpy(self, points: np.ndarray[Any, Any], cloud: Any
                    ) -> np.ndarray[Any, np.dtype[np.int64]]:
        x, y, z = _xyz(cloud, points)
        if x.size >= _MAX_POINTS:
            raise ConversionError("PointCloud2 height * width", x.size, f"< {_MAX_POINTS}")
        return _fuse_numpy(x, y, z, self.extrinsics, self.slices, self._grids,
                           self._slice_grid, self._offsets, self._size)

    def convert(self, cloud: Any) -> dict[str, Any]:
        """All slices of one cloud.

        Args:
            cloud: a ``sensor_msgs/PointCloud2`` (rclpy or any object with its fields; ``data``
                bytes, array.array, memoryview or a uint8 numpy array). Never modified.

        Returns:
            slice name -> rclpy ``sensor_msgs.msg.LaserScan``, in configuration order, stamped
            with the cloud's stamp.

        Raises:
            ConversionError: missing or non-float x/y/z, inconsistent sizes, a required
                intensity field that is missing.
        """
        stamp = to_ns(cloud.header.stamp, field="PointCloud2.header.stamp")
        if self._plan is not None:
            _, ranges, ints = self._run(cloud, decode=True)
        else:
            ranges, ints = self._decode_numpy(cloud)
        frame = self._frame_id or str(cloud.header.frame_id)
        out: dict[str, Any] = {}
        for s, off in zip(self.slices, self._offsets):
            part = slice(off, off + s.grid.size)
            out[s.name] = _grid.make_laserscan(
                stamp_ns=stamp, frame_id=frame, grid=s.grid, ranges=ranges[part],
                intensities=None if ints is None else ints[part], options=s.options)
        return out

    def _decode_numpy(self, cloud: Any
                      ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any] | None]:
        """The reference: published ranges and winners' intensities (float32, all slices back
        to back; None without intensity), :func:`converters.slices.spec.decode` per slice."""
        points = read_points(cloud)
        best = self._fuse_numpy(points, cloud)
        intensity = _intensity(cloud, points, self.intensity_field)
        ranges = np.empty(self._size, np.float32)
        ints = None if intensity is None else np.zeros(self._size, np.float32)
        for s, off in zip(self.slices, self._offsets):
            part = slice(off, off + s.grid.size)
            ranges[part], winners = _grid.decode(best[part], s.options)
            if ints is not None and intensity is not None:
                hit = winners >= 0
                ints[part][hit] = intensity[winners[hit]].astype(np.float32)
        return ranges, ints

    def _layout(self, cloud: Any) -> _Layout:
        """What the kernel needs of the cloud's field layout (validated, then kept per
        layout)."""
        fields = tuple((str(f.name), int(f.offset), int(f.datatype), int(f.count))
                       for f in cloud.fields)
        key = (fields, int(cloud.point_step), bool(cloud.is_bigendian))
        layout = self._layouts.get(key)
        if layout is None:
            layout = _Layout.of(cloud, self.intensity_field)
            if len(self._layouts) > 64:
                self._layouts.clear()
            self._layouts[key] = layout
        return layout

    def _run(self, cloud: Any, decode: bool
             ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any], np.ndarray[Any, Any] | None]:
        """The compiled kernel on one cloud: (reduction array, published ranges or an empty
        array without ``decode``, winners' intensities or None)."""
        layout = self._layout(cloud)
        height, width = int(cloud.height), int(cloud.width)
        if height * width >= _MAX_POINTS:
            raise ConversionError("PointCloud2 height * width", height * width,
                                  f"< {_MAX_POINTS}")
        step, row_step = layout.step, int(cloud.row_step)
        addr, nbytes, keep = _address(cloud.data)
        if height and width:
            check_extent(height, width, step, row_step, nbytes)
        inten = layout.intensity
        if layout.direct:
            xyz = (addr + layout.xyz[0], addr + layout.xyz[1], addr + layout.xyz[2])
            xyz_type = layout.xyz_type
            intensity = None if inten is None else (addr + inten[0], step, row_step, inten[1])
        else:             # big-endian, or x, y, z of different types: native copies
            points = read_points(cloud)
            keep = np.empty((height * width, 3), np.float64)
            for k, values in enumerate(_xyz(cloud, points)):
                keep[:, k] = values
            base = keep.__array_interface__["data"][0]
            xyz, xyz_type = (base, base + 8, base + 16), 1
            step, row_step = 24, 24 * width
            values = _intensity(cloud, points, self.intensity_field)
            intensity = None
            if values is not None:
                values = np.ascontiguousarray(values)
                code = _loader_type_code(values)
                intensity = (values.__array_interface__["data"][0], values.itemsize,
                             values.itemsize * width, code)
                keep = (keep, values)
        best = np.empty(self._size, np.int64)
        ranges = np.empty(self._size if decode else 0, np.float32)
        ints = np.empty(self._size, np.float32) if decode and intensity is not None else None
        self._plan.run(height, width, xyz, step, row_step, xyz_type, intensity, best,
                       ranges if decode else None, ints)
        del keep
        return best, ranges, ints


def _loader_type_code(values: np.ndarray[Any, Any]) -> int:
    """The kernels' type code of a native array (:data:`converters._kernels._loader.TYPE_CODES`)."""
    from converters._kernels._loader import type_code

    code = type_code(values)
    if code is None:                               # not a PointField type: never happens
        raise ConversionError("intensity_field", str(values.dtype), "a PointField datatype")
    return code


def _address(data: Any) -> tuple[int, int, Any]:
    """(address, size in bytes, the object to keep alive) of a cloud's ``data``."""
    if isinstance(data, array.array):
        addr, n = data.buffer_info()
        return addr, n * data.itemsize, data
    if isinstance(data, np.ndarray):
        buf = np.ascontiguousarray(data).reshape(-1).view(np.uint8)
    else:
        buf = np.frombuffer(data, np.uint8)
    return buf.__array_interface__["data"][0], buf.nbytes, buf


class _Layout(NamedTuple):
    """What the kernel needs of one field layout (:meth:`CloudSliceConverter._layout`).

    Attributes:
        direct: the kernel reads the cloud's buffer in place (native byte order, x, y, z of
            one type); else it reads native float64 copies.
        step: point_step.
        xyz: byte offsets of x, y, z; xyz_type: their type code (0 float32, 1 float64).
        intensity: (byte offset, type code) of the intensity field's first element, or None.
    """

    direct: bool
    step: int
    xyz: tuple[int, int, int]
    xyz_type: int
    intensity: tuple[int, int] | None

    @classmethod
    def of(cls, cloud: Any, wanted: str | None) -> _Layout:
        """Validated as :func:`cloud_points` and :func:`_intensity` do (their errors)."""
        from converters._kernels._loader import TYPE_CODES

        points = read_points(cloud)
        _xyz(cloud, points)
        _intensity(cloud, points, wanted)
        fields = {str(f.name): f for f in cloud.fields}
        types = {int(fields[a].datatype) for a in "xyz"}
        bigendian = bool(cloud.is_bigendian)
        intensity = None
        name = None if wanted is None else str(wanted)
        if name is not None and name in fields:
            f = fields[name]
            intensity = (int(f.offset), TYPE_CODES[dtype_of(int(f.datatype)).str[1:]])
        return cls(direct=not bigendian and len(types) == 1, step=int(cloud.point_step),
                   xyz=(int(fields["x"].offset), int(fields["y"].offset),
                        int(fields["z"].offset)),
                   xyz_type=0 if types == {FLOAT32} else 1, intensity=intensity)


def cloud_to_laserscan(cloud: Any, *, min_height: float, max_height: float,
                       extrinsics: Any = None, frame_id: str | None = None,
                       angle_min: float | None = None, angle_max: float | None = None,
                       angle_increment: float | None = None, range_min: float | None = None,
                       range_max: float | None = None,
                       intensity_field: str | None = IfPresent("intensity"),
                       use_inf: bool = True, inf_epsilon: float = 1.0,
                       fill: float | None = None, backend: str = "auto") -> Any:
    """One height slice of a PointCloud2 as a ``sensor_msgs.msg.LaserScan``.

    Arguments are those of :class:`CloudSliceConverter` with a single slice
    ``(min_height, max_height)`` (inclusive, metres in the target frame); for several slices of
    the same cloud use :class:`CloudSliceConverter` (one pass).
    """
    converter = CloudSliceConverter(
        {"slice": SliceSpec(min_height, max_height)}, extrinsics=extrinsics, frame_id=frame_id,
        angle_min=angle_min, angle_max=angle_max, angle_increment=angle_increment,
        range_min=range_min, range_max=range_max, intensity_field=intensity_field,
        use_inf=use_inf, inf_epsilon=inf_epsilon, fill=fill, backend=backend)
    return converter.convert(cloud)["slice"]
