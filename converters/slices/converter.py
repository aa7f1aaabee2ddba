"""Height-filtered LaserScan slices of a LidarScan, several in one pass.

A slice keeps the points whose height ``z`` in the target frame lies in ``[min_height,
max_height]`` (inclusive) and publishes, per bin of an angle grid, the minimum planar range
``sqrt(x*x + y*y)`` (inclusive ``[range_min, range_max]``). Grid, binning, value classes (REP 117)
and fusion rules are those of :mod:`converters.slices.spec` (read its docstring); in short:

* default grid: full circle ``[-pi, pi)`` at the sensor's column resolution ``2*pi / W``;
  nearest bin in float64, half-bin to the lower index, +pi and -pi share a bin;
* a finite in-range value beats ``-Inf`` (too close) beats ``+Inf`` (no return / beyond
  ``range_max``) beats ``NaN`` (invalid pixel) beats an empty bin (``fill``); min range wins and
  carries its intensity; equal ranges go to the first pixel in *measurement* order
  (row-major, row ``u`` then measurement column ``c``), so staggered and destaggered scans give
  identical slices;
* a pixel with no return (+Inf) whose ray crosses the band within the range limits keeps ``+Inf``
  in its bin, so costmaps can clear; an invalid pixel (NaN, or a float range <= 0) gives ``NaN``.

**Holes** (negative obstacles: a stair down, a drop, a pit), off by default, per slice
(``holes=True``): a pixel whose ray points down from above the floor plane ``z =
floor_height`` (target frame) and whose measurement lies at or below ``floor_height -
hole_depth`` (or, with ``hole_no_return``, got no return at all) reports an obstacle at the
*edge*: the point where its ray crosses the floor plane, at that point's planar range and bin,
when that range is ``<= hole_range_max`` (default: the slice's ``range_max``). The edge is a point
like any other for the REP 117 classes, the limits and the ties (it carries the pixel's tie key
and intensity); the height band does not apply to it. Exact rules: :mod:`converters.slices.holes`.
This is the cliff detection of the multi-laserscan toolbox's depth converter (its
``cliff_height`` is ``floor_height - hole_depth``), for any LidarScan: a lidar or a depth image
(:func:`converters.from_depth_image`).

Tables: with a fixed mount every pixel is a ray ``p = r*D + O`` whose direction ``D`` and
origin ``O`` in the target frame (float32 components, like the projector's tables; arithmetic in
float64) are computed once per LidarInfo version and column order (:func:`lidarscan.make_projector`,
then the extrinsics, :func:`converters.shared.frames.transform_rays`). What the slicer reads of a
scan besides binning and fusing -- checks, stamp, ranges, the intensity view, the geometry key,
the rays on a cache miss, a moving mount's poses -- it asks of its geometry service in one call
per scan (:class:`converters.shared.scan_rays.ScanGeometry`). Per distinct grid and pixel the
far-field bin and the range ``r_thr`` above which the point's bin *is* the far-field bin are
precomputed (:func:`converters.slices.spec.far_field`), so ``atan2`` runs only for in-band points
closer than their ``r_thr`` (a sensor far off the target's z axis makes most points need it:
prefer a target frame below the sensor); per slice, which pixels may report +Inf/NaN/-Inf.
Scans carrying ``column_azimuth_angles`` or a per-pixel ``azimuth`` channel
(:func:`lidarscan.geometry.pixel_azimuths`) rebuild the tables for every scan (correct, not fast).

**Moving mounts.** ``extrinsics`` may also be a :class:`converters.TransformTrack` (stamped
poses, interpolated: linear translation, shortest-arc slerp) or any callable ``stamp_ns (int) ->
4x4``: a lidar on a pan unit, an arm or a nodding mount that moves during its sweep. Every pixel's
ray is then moved by the mount's pose at *that pixel's* time: ``header.stamp +
column_time_offsets[c] + beam_time_offsets[u]`` (+ the per-pixel ``t`` channel when the scan has
one; :meth:`lidarscan.geometry.Projector.pixel_times`), so the sweep is de-skewed pixel by pixel
(with per-column times only, as most lidars, the pose is per column). The slicing that follows
is the same in every respect (grid, band, classes, ties, holes, backends); only the rays are
moved per scan (:meth:`SliceConverter._moving_tables_of`). What does not depend on the pose is kept:
the sensor-frame rays per geometry, the distinct pixel times and each pixel's one per column
timing (a scan with a ``t`` channel computes its own). A track computes the poses of the distinct
times in one batch; a callable is called once per distinct pixel time and its result checked (a
finite rigid 4x4, else :class:`lidarscan.errors.ValidationError`). With the compiled kernels
the rays are moved by a compiled loop (the bits of :func:`converters.shared.frames.transform_rays`;
with a track and pixel times that vary within a column -- per-beam offsets, a ``t`` channel
not constant along columns -- each ray's pose is interpolated in that loop instead of one pose
per distinct time being looked up and stored: the track's poses up to the last float64 bits,
so a ray component may differ from the per-time path's by one float32 ulp,
:meth:`converters._kernels.slices_numba.Compiled.track_rays`) and fused by the general
kernel with atan2 for every in-band point; far-field bins and +Inf/NaN/-Inf qualifiers are
computed for the pixels without a finite range only (:class:`_MovingRays`); the numpy backend
builds the full per-scan tables (the reference; the same slices bit for bit,
tests/test_moving_slices.py). A mount that holds still over a whole
scan gets the fixed-mount tables at that pose (every kernel), kept for the next scan. A pose
that cannot be found -- a time outside the track's span
(:class:`converters.shared.transforms.OutOfSpanError`, the track never extrapolates) or any
:class:`~converters.shared.transforms.TransformLookupError` the callable raises -- is raised by
:meth:`SliceConverter.convert`; nothing falls back to another pose. The fixed-mount path is
unchanged (same tables, same kernels).

Backends (:func:`converters._kernels.select`, table in :mod:`converters._kernels`): the numpy
reference here (:meth:`SliceConverter._fuse`, then :func:`converters.slices.spec.decode`); the numba
kernels of :mod:`converters._kernels.slices_numba` (bin-ordered when all slices share one grid
and their range limits; row-ordered, with exact per-row float32 band intervals, when that grid
is a full circle at the sensor's column resolution seen by an upright or upside-down sensor;
else the per-pixel passes); the C kernel of :mod:`converters._kernels.slices` for the
row-ordered case (streams the scan in pixel order). All give identical slices (up to points
within an ulp of a bin edge, where numpy's SIMD ``atan2`` may differ from libm's in the last
bit). Inputs reach the kernels in native byte order (:func:`lidarscan.channel`, ``native=True``).
With holes enabled in any slice the C kernel is not used: the numba row-ordered kernel adds the
hole edges in the same call (static per-pixel tables, :class:`converters.slices.holes.HolePlan`: only
the height test runs per scan); elsewhere the bands are fused by the other kernels (or numpy),
the holes are then added to the same reduction array by numpy
(:meth:`SliceConverter._add_holes`), and the result is decoded.

Time fields: ``header.stamp`` is the scan's stamp (measurement column 0), identical for all slices
of a scan; ``scan_time`` is ``W * column_time_increment`` (or from ``column_time_offsets``);
``time_increment`` is ``+-scan_time * angle_increment / 2pi``, positive for a counter-clockwise
sweep, negative for a clockwise one (Ouster). Since a grid generally does not start at column 0's
azimuth, the time of ray ``i`` is *not* ``stamp + i * time_increment``; it is the time of the
column that looked at that azimuth (use the LidarScan for per-point time).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, cast

import numpy as np

from converters import _kernels
from converters._kernels.slices_numba import Bands
from converters.shared import options
from converters.shared.converter_cache import ConverterCache
from converters.shared.frames import check_extrinsics, transform_rays
from converters.shared.options import IfPresent
from converters.shared.scan_rays import ChannelWant, RayRequest, ScanGeometry, ScanRays
from converters.shared.transforms import TransformTrack
from converters.slices import holes as _holes
from converters.slices import spec as _grid
from converters.slices.holes import HoleOptions
from converters.slices.spec import AngleGrid, OutputOptions
from converters.slices.tables import MovingPlan, _MovingRays, _Slice, _Tables
from lidarscan.errors import ConfigError, ConversionError
from lidarscan.geometry import info_key
from lidarscan.scan import as_array

__all__ = ["SliceConverter", "SliceSpec", "check_extrinsics", "to_laserscan"]

_NO_VALUES = np.zeros(0, np.float32)
_NO_KEYS = np.zeros(0, np.int64)
#: what :meth:`SliceConverter._tables_for` asks of the geometry service: the geometry alone
_GEOMETRY = RayRequest()
#: ... and with a moving mount's poses (:meth:`SliceConverter._mount_mode`)
_MOUNT = {mode: RayRequest(mount=mode) for mode in ("poses", "track")}


@dataclass(frozen=True)
class SliceSpec:
    """One slice: a height band plus optional overrides of the converter's common options.

    Attributes:
        min_height, max_height: inclusive band in metres, in the target frame (``-inf``/``inf``
            allowed for an open side; no default on purpose: pointcloud_to_laserscan's
            ``DBL_MIN`` default silently dropped everything at z <= 0).
        angle_min, angle_max, angle_increment, range_min, range_max, use_inf, inf_epsilon, fill,
        holes, floor_height, hole_depth, hole_range_max, hole_no_return:
            None = the converter's common value (see :class:`SliceConverter`).
    """

    min_height: float
    max_height: float
    angle_min: float | None = None
    angle_max: float | None = None
    angle_increment: float | None = None
    range_min: float | None = None
    range_max: float | None = None
    use_inf: bool | None = None
    inf_epsilon: float | None = None
    fill: float | None = None
    holes: bool | None = None
    floor_height: float | None = None
    hole_depth: float | None = None
    hole_range_max: float | None = None
    hole_no_return: bool | None = None


_OVERRIDES = ("angle_min", "angle_max", "angle_increment", "range_min", "range_max", "use_inf",
              "inf_epsilon", "fill", *options.HOLE_KEYS)


class SliceConverter:
    """Several height slices of one lidar, computed together from each LidarScan.

    Args:
        info: the LidarInfo (rclpy or dataclass) of the scans to convert.
        slices: name -> :class:`SliceSpec` (or a dict of its fields); order is kept.
        extrinsics: 4x4 pose of the scan's frame (``info.header.frame_id``) in the target frame;
            None = the scan's frame is the target frame. Heights and ranges are measured in the
            target frame, so a tilted or upside-down sensor works. A moving mount: a
            :class:`converters.TransformTrack` or a callable ``stamp_ns (int) -> 4x4``, looked
            up at every pixel's time (module docstring, **Moving mounts**).
        frame_id: header.frame_id of the slices (required with ``extrinsics``; default: the
            scan's frame).
        angle_min, angle_max, angle_increment: grid (radians); default full circle from -pi at
            2*pi/W.
        range_min, range_max: inclusive planar limits, metres; default the info's (0 / inf when
            unknown).
        intensity_channel: channel whose value at the winning pixel becomes the intensity (any
            dtype, cast to float32), or None for an empty ``intensities``. The default,
            ``IfPresent("intensity")``, uses the scan's ``intensity`` channel when it has one
            (empty ``intensities`` for a range-only scan); a plain name is required.
        use_inf, inf_epsilon, fill: output values (see :class:`converters.slices.spec.OutputOptions`).
        holes: report negative obstacles (module docstring, **Holes**); off by default.
        floor_height: z of the floor in the target frame, metres (0: a target frame on the
            floor, such as ``base_footprint``).
        hole_depth: metres (> 0): a measured point at or below ``floor_height - hole_depth``
            is in a hole (the tolerance for floor noise and a slightly tilted floor).
        hole_range_max: largest planar range of a reported hole edge, metres (inclusive; None =
            the slice's ``range_max``): beyond it the floor is seen too obliquely to judge.
        hole_no_return: a pixel with no return (+Inf) whose ray crosses the floor also reports
            a hole (nothing answered where the floor should be); set False for sensors that
            lose returns on dark or wet floors.
        range_channel: the range channel (float metres or integer with the info's multiplier).
        backend: ``"auto"``, ``"numba"`` or ``"numpy"``, as :func:`converters._kernels.select`
            chooses them (the C kernel where it applies, numba, numpy). All give the same
            slices (up to points within an ulp of a bin edge).

    Raises:
        ConfigError: a bad option (empty band set, inverted band, increment <= 0, ...).
    """

    def __init__(self, info: Any, slices: Mapping[str, SliceSpec | Mapping[str, Any]], *,
                 extrinsics: Any = None, frame_id: str | None = None,
                 angle_min: float | None = None, angle_max: float | None = None,
                 angle_increment: float | None = None, range_min: float | None = None,
                 range_max: float | None = None,
                 intensity_channel: str | None = IfPresent("intensity"),
                 use_inf: bool = True, inf_epsilon: float = 1.0, fill: float | None = None,
                 holes: bool = False, floor_height: float = 0.0, hole_depth: float = 0.05,
                 hole_range_max: float | None = None, hole_no_return: bool = True,
                 range_channel: str = "range", backend: str = "auto") -> None:
        if not isinstance(slices, Mapping):
            raise ConfigError("slices", slices, "a non-empty dict of name -> SliceSpec")
        specs = {name: _as_spec(name, spec) for name, spec in slices.items()}
        common = {"angle_min": angle_min, "angle_max": angle_max,
                  "angle_increment": angle_increment, "range_min": range_min,
                  "range_max": range_max, "use_inf": use_inf, "inf_epsilon": inf_epsilon,
                  "fill": fill, "holes": holes, "floor_height": floor_height,
                  "hole_depth": hole_depth, "hole_range_max": hole_range_max,
                  "hole_no_return": hole_no_return}
        #: a moving mount: TransformTrack or callable stamp_ns -> 4x4 (None: a fixed mount)
        self.moving: Any = extrinsics if callable(extrinsics) else None
        options.slice_options(specs, {
            **common, "extrinsics": _checkable(extrinsics), "frame_id": frame_id,
            "intensity_channel": intensity_channel, "range_channel": range_channel,
            "backend": backend})
        chosen = _kernels.select("slices", backend=backend)
        self._kernel = chosen.numba
        self._c_kernel = bool(chosen.c)
        self._common = common
        self._specs: dict[str, SliceSpec] = specs
        self.extrinsics = check_extrinsics(_checkable(extrinsics))
        self._frame_id = frame_id
        self.intensity_channel = intensity_channel
        self.range_channel = range_channel
        self._tables: dict[Any, _Tables] = {}
        self._moving_cache: tuple[Any, _Tables] | None = None
        #: moving mount: build the full per-scan tables even with the compiled kernels (the
        #: path before :class:`_MovingRays`; tests compare both)
        self._reference_tables = False
        #: track + compiled kernels + pixel times varying within a column: each ray's pose
        #: interpolated in the kernel (False: one pose per distinct time, the path before;
        #: the bench and the tests compare both)
        self._per_pixel = True
        self._set_info(info)

    # ------------------------------------------------------------------------- configuration
    def _set_info(self, info: Any) -> None:
        self.info = info
        #: the geometry service: checks, stamp, ranges, intensity view, rays (target frame)
        self._geometry = ScanGeometry(info, range_channel=self.range_channel,
                                      extrinsics=self.extrinsics, moving=self.moving,
                                      linkage_hint=(
                                          "the converter's LidarInfo; pass the new info to "
                                          "convert(scan, info)"))
        self.projector = self._geometry.projector
        self._info_key = info_key(info)
        wanted = self.intensity_channel
        self._request = RayRequest(metres=True, channels=() if wanted is None else (
            ChannelWant("intensity", (str(wanted),), required=not isinstance(wanted, IfPresent)),))
        #: ... with a moving mount's poses, by :meth:`_mount_mode`
        self._mount_requests = {mode: dataclasses.replace(self._request, mount=mode)
                                for mode in ("poses", "track")}
        self.frame_id = self._frame_id or info.header.frame_id
        self._tables.clear()
        self._moving_cache = None
        self._inf_thr: np.ndarray[Any, Any] | None = None
        width = int(info.width)
        self.slices = [self._build_slice(name, spec, info, width)
                       for name, spec in self._specs.items()]
        self._holes = any(s.holes is not None for s in self.slices)
        self._size, self._offsets, self._grids, self._slice_grid = _grid.output_layout(
            [s.grid for s in self.slices])
        self._near = max(float(info.range_min), 0.0)
        self._sweep = self._sweep_sign(info)
        self._bands = Bands.create([(s.min_z, s.max_z, s.options, g)
                                    for s, g in zip(self.slices, self._slice_grid)],
                                   self._grids)

    def _build_slice(self, name: str, spec: SliceSpec, info: Any, width: int) -> _Slice:
        opts = {k: getattr(spec, k) if getattr(spec, k) is not None else self._common[k]
                for k in _OVERRIDES}
        inc = opts["angle_increment"]
        if inc is None:
            inc = 2.0 * math.pi / max(width, 1)
        amin = -math.pi if opts["angle_min"] is None else opts["angle_min"]
        amax = amin + 2.0 * math.pi if opts["angle_max"] is None else opts["angle_max"]
        grid = AngleGrid.create(amin, amax, inc)
        rmin = opts["range_min"]
        if rmin is None:
            rmin = max(float(info.range_min), 0.0)
        rmax = opts["range_max"]
        if rmax is None:
            rmax = float(info.range_max) if float(info.range_max) > 0 else math.inf
        options = OutputOptions.create(rmin, rmax, bool(opts["use_inf"]), opts["inf_epsilon"],
                                       opts["fill"])
        holes = None
        if opts["holes"]:
            edge_max = opts["hole_range_max"]
            holes = HoleOptions(float(opts["floor_height"]), float(opts["hole_depth"]),
                                options.range_max if edge_max is None else float(edge_max),
                                bool(opts["hole_no_return"]))
        return _Slice(name, float(spec.min_height), float(spec.max_height), grid, options, holes)

    @staticmethod
    def _sweep_sign(info: Any) -> float:
        alpha = as_array(info.horizontal_angles, np.float64).astype(np.float64)
        if alpha.size < 2:
            return 0.0
        step = (np.diff(alpha) + math.pi) % (2.0 * math.pi) - math.pi
        mean = float(np.mean(step))
        return 0.0 if mean == 0 else math.copysign(1.0, mean)

    # ------------------------------------------------------------------------------ tables
    def _tie_keys(self, destaggered: bool) -> np.ndarray[Any, Any] | None:
        """Measurement-order tie key ``u*W + c`` per pixel of a destaggered scan (else None)."""
        return self._geometry.tie_keys(destaggered)

    def _tables_for(self, scan: Any) -> _Tables:
        """The fixed-mount tables of a scan's geometry (see :meth:`_tables_of`)."""
        return self._tables_of(self._geometry.prepare(scan, _GEOMETRY))

    def _tables_of(self, rays: ScanRays) -> _Tables:
        """The fixed-mount tables of a geometry (:attr:`ScanRays.key`), built from its rays in
        the target frame on first use and kept (a measured geometry: only the latest)."""
        key = rays.key
        tables = self._tables.get(key)
        if tables is None:
            if key[0] == "measured":     # per-scan geometry: keep only the latest such table
                for k in [k for k in self._tables if k[0] == "measured"]:
                    del self._tables[k]
            d, o = self._geometry.target_rays(rays)
            tables = _Tables(d, o, self._tie_keys(rays.destaggered), self.slices, self._grids,
                             self._slice_grid, self._near, self.projector.width)
            self._tables[key] = tables
        return tables

    def _pose_times(self, scan: Any, distinct: bool = True
                    ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any] | None]:
        """:meth:`converters.shared.scan_rays.ScanGeometry.pose_times` of this converter's
        geometry."""
        return self._geometry.pose_times(scan, distinct)

    def mount_poses(self, scan: Any) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
        """The moving mount's poses for a scan's pixels
        (:meth:`converters.shared.scan_rays.ScanGeometry.mount_poses`).

        Returns:
            (poses, index): (P, 4, 4) float64 target <- sensor at the P distinct pixel times,
            and (H*W,) int64 the pose of each pixel (scan column order, row-major).
        """
        return self._geometry.mount_poses(scan)

    @property
    def _time_cache(self) -> Any:
        """The pixel times kept for the next scan (the geometry service's)."""
        return self._geometry._time_cache

    def _mount_mode(self) -> str:
        """How the rays are moved: "track" (a track, the compiled kernels and
        :attr:`_per_pixel`: each ray's pose interpolated in the kernel when pixel times vary
        within a column) or "poses" (one pose per distinct pixel time)."""
        compiled = self._kernel is not None and not self._reference_tables
        return ("track" if compiled and self._per_pixel and isinstance(self.moving, TransformTrack)
                else "poses")

    def _moving_tables(self, scan: Any, r: np.ndarray[Any, Any]) -> _Tables | _MovingRays:
        """:meth:`_moving_tables_of` a scan and its flat float32 ranges ``r``."""
        rays = self._geometry.prepare(scan, _MOUNT[self._mount_mode()])
        return self._moving_tables_of(dataclasses.replace(rays, metres=r))

    def _moving_tables_of(self, rays: ScanRays) -> _Tables | _MovingRays:
        """Tables of one scan seen by a moving mount: every pixel's ray moved by the mount's
        pose at its time (:meth:`mount_poses`). A mount that holds one pose over the whole
        scan gets fixed-mount tables at that pose (every kernel; kept for the next scan at the
        same pose); else, with the compiled kernels, :class:`_MovingRays` (the rays only, for
        the general kernel), without them the full :class:`_Tables` of the scan (numpy: the
        reference). With a track, the compiled kernels and pixel times that vary within a
        column (per-beam offsets, an irregular ``t`` channel: up to one pose per pixel), each
        ray's pose is interpolated where it is used (the track's samples of
        :meth:`converters.shared.scan_rays.ScanGeometry.mount`, then
        :meth:`converters._kernels.slices_numba.Compiled.track_rays`) instead of
        looking up and storing one pose per distinct time."""
        r, mount = cast(np.ndarray, rays.metres), rays.mount
        if mount is None:                      # unreachable: convert() asks for the mount
            raise ConversionError("mount", None, "asked of the geometry service")
        if mount.held is not None:
            return self._still_tables(rays, mount.held)
        geometry = self._geometry
        if mount.samples is not None:          # a track, a time per pixel: the kernel's poses
            d32, o32 = geometry.sensor_rays(rays, columns=True)
            moved = self._kernel.track_rays(d32, o32, mount.relative, rays.stamp_ns,
                                            *mount.samples)
            return _MovingRays(moved, self._tie_keys(rays.destaggered), r, self._moving_plan())
        poses, index = cast(np.ndarray, mount.poses), cast(np.ndarray, mount.index)
        d32, o32 = geometry.sensor_rays(rays)
        if self._kernel is not None and not self._reference_tables:
            return _MovingRays(self._kernel.transform_rays(d32, o32, poses, index),
                               self._tie_keys(rays.destaggered), r, self._moving_plan())
        d, o = transform_rays(d32, o32, poses, index)
        return _Tables(d, o, self._tie_keys(rays.destaggered), self.slices, self._grids,
                       self._slice_grid, self._near, self.projector.width)

    def _still_tables(self, rays: ScanRays, pose: np.ndarray[Any, Any]) -> _Tables:
        """Fixed-mount tables at ``pose`` (kept for the next scan of this geometry and pose)."""
        geometry = rays.key
        key = (geometry, pose.tobytes())
        if self._moving_cache is not None and self._moving_cache[0] == key:
            return self._moving_cache[1]
        d32, o32 = self._geometry.sensor_rays(rays)
        d, o = transform_rays(d32, o32, pose[None], np.zeros(d32.shape[0], np.int64))
        tables = _Tables(d, o, self._tie_keys(geometry[1]), self.slices, self._grids,
                         self._slice_grid, self._near, self.projector.width)
        self._moving_cache = (key, tables)
        return tables

    def _moving_plan(self) -> MovingPlan:
        """What :class:`_MovingRays` reads of this slicer."""
        return MovingPlan(self._grids, self.slices, self._kernel, self._bands, self._near,
                          bool(self._holes), self._no_thresholds)

    def _no_thresholds(self, n: int) -> np.ndarray[Any, Any]:
        """(G, n) float32 +inf far-field thresholds (atan2 for every point; read only by the
        kernels, kept)."""
        if self._inf_thr is None or self._inf_thr.shape != (len(self._grids), n):
            self._inf_thr = np.full((len(self._grids), n), np.inf, np.float32)
        return self._inf_thr

    # ----------------------------------------------------------------------------- convert
    def convert(self, scan: Any, info: Any = None) -> dict[str, Any]:
        """All slices of one scan.

        Args:
            scan: a LidarScan (rclpy or dataclass) of this converter's LidarInfo.
            info: a new LidarInfo version to switch to (tables are rebuilt), or None.

        Returns:
            slice name -> ``sensor_msgs.msg.LaserScan`` (rclpy), in configuration order.

        Raises:
            LinkageError: ``scan.lidar_info_time`` does not name the converter's info.
            InfoMismatchError: grid size differs from the info.
            UnknownChannelError: the range or intensity channel is missing.
            TransformLookupError: a moving mount's pose is unknown at a pixel's time
                (:class:`converters.shared.transforms.OutOfSpanError` outside a track's span).
        """
        if info is not None and info_key(info) != self._info_key:
            self._set_info(info)
        rays = self._geometry.prepare(scan, self._request if self.moving is None else
                                      self._mount_requests[self._mount_mode()])
        r = cast(np.ndarray, rays.metres)
        tables = self._tables_of(rays) if self.moving is None else self._moving_tables_of(rays)
        values = rays.views.get("intensity")
        intensity = None if values is None else values.reshape(-1)
        decoded = self._row_convert(r, tables, intensity)
        if decoded is None:
            best = self._fuse(r, tables)
            if self._holes:
                self._add_holes(best, r, tables)
            decoded = self._decode_all(best, tables, intensity)
        stamp = rays.stamp_ns
        period = rays.period_ns
        out: dict[str, Any] = {}
        for s, off in zip(self.slices, self._offsets):
            if decoded is not None:
                ranges = decoded[0][off:off + s.grid.size]
                ints = None if intensity is None else decoded[1][off:off + s.grid.size]
            else:
                ranges, winners = _grid.decode(best[off:off + s.grid.size], s.options)
                ints = None
                if intensity is not None:
                    ints = np.zeros(s.grid.size, np.float32)
                    hit = winners >= 0
                    ints[hit] = intensity[tables.position(winners[hit])]
            time_inc = self._sweep * period * 1e-9 * s.grid.increment / (2.0 * math.pi)
            out[s.name] = _grid.make_laserscan(
                stamp_ns=stamp, frame_id=self.frame_id, grid=s.grid, ranges=ranges,
                intensities=ints, options=s.options, scan_time=period * 1e-9,
                time_increment=time_inc, stamp=rays.stamp)
        return out

    def _row_convert(self, r: np.ndarray[Any, Any], tables: _Tables,
                     intensity: np.ndarray[Any, Any] | None
                     ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]] | None:
        """Fusion and decoding in one compiled call (the row-ordered kernels)
        when the row-ordered kernel applies, else None."""
        t = tables.sorted
        if t is None or t.rows is None:
            return None
        if self._c_kernel and not tables.holes:
            plan = t.rows.c_plan(tables, self.slices)
            if plan is not None:
                ranges, ints, _ = plan.run(r, intensity)
                return ranges, ints
        if self._kernel is None:
            return None
        return self._kernel.convert_rows(  # type: ignore[no-any-return]
            np.ascontiguousarray(r, np.float32), t, t.rows, self._bands,
            *self._decode_inputs(tables, intensity), tables.hole_plan)

    @staticmethod
    def _decode_inputs(tables: _Tables, intensity: np.ndarray[Any, Any] | None
                       ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
        """(intensity image, key -> pixel map) as the compiled decoding takes them."""
        inten = _NO_VALUES if intensity is None else np.ascontiguousarray(intensity)
        key_to_pos = _NO_KEYS if tables.key_to_pos is None else tables.key_to_pos
        return inten, key_to_pos

    def _decode_all(self, best: np.ndarray[Any, Any], tables: _Tables,
                    intensity: np.ndarray[Any, Any] | None
                    ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]] | None:
        """Ranges and intensities (float32, slices back to back) of all slices in one compiled
        call; None without the compiled kernels."""
        if self._kernel is None:
            return None
        ranges = np.empty(self._size, np.float32)
        ints = np.empty(self._size if intensity is not None else 0, np.float32)
        b = self._bands
        self._kernel.decode_slices(best, b.offset, b.size, b.inf_value, b.fill_value,
                                   *self._decode_inputs(tables, intensity), ranges, ints)
        return ranges, ints

    def _add_holes(self, best: np.ndarray[Any, Any], r: np.ndarray[Any, Any],
                   tables: _Tables) -> None:
        """Fuse the hole edges of this scan into the reduction array ``best`` (in place; the
        same numpy code after every backend's band fusion)."""
        for i, edges in tables.holes:
            hit = _holes.hole_hits(r[edges.index], edges)
            pixels = edges.index[hit]
            _grid.merge_min(best, edges.bins[hit] + self._offsets[i], edges.codes[hit],
                            tables.key(pixels))

    def _fuse(self, r: np.ndarray[Any, Any], tables: _Tables) -> np.ndarray[Any, Any]:
        """One reduction array (all slices back to back) from the flat range image."""
        best = np.full(self._size, _grid.EMPTY, np.int64)
        kernel = self._kernel
        if kernel is not None:
            r32 = np.ascontiguousarray(r, np.float32)
            if tables.sorted is not None:
                kernel.fuse_sorted(r32, tables.sorted, self._bands, best)
            else:
                kernel.fuse(r32, tables.kernel_rays, self._bands, best)
            return best
        with np.errstate(invalid="ignore", over="ignore"):
            good = (r > 0) & (r < np.inf)
            r64 = r.astype(np.float64)
            z = r64 * tables.dz + tables.oz              # float64: f4 tables are upcast
        d64 = tables.rays[:, :3].astype(np.float64)
        o64 = tables.rays[:, 3:].astype(np.float64)
        special = np.flatnonzero(~good)
        r_special = r64[special]
        all_bins, all_codes, all_keys = [], [], []
        for i, (s, off, g) in enumerate(zip(self.slices, self._offsets, self._slice_grid)):
            idx = np.flatnonzero((z >= s.min_z) & (z <= s.max_z) & good)
            if idx.size:
                sel, bins, codes = _grid.point_codes(
                    r64[idx], d64[idx], o64[idx], s.min_z, s.max_z, s.options.range_min,
                    s.options.range_max, s.grid, tables.bin_far[g][idx], tables.r_thr[g][idx])
                all_bins.append(bins + off)
                all_codes.append(codes)
                all_keys.append(tables.key(idx[sel]))
            if special.size:
                codes = _grid.special_codes(r_special, tables.q_far[i][special],
                                            tables.q_near[i][special])
                qualified = special[codes >= 0]
                all_bins.append(tables.bin_far[g][qualified] + off)
                all_codes.append(codes[codes >= 0])
                all_keys.append(tables.key(qualified))
        if all_bins:
            best = _grid.reduce_min(self._size, np.concatenate(all_bins),
                                    np.concatenate(all_codes), np.concatenate(all_keys))
        return best


def _checkable(extrinsics: Any) -> Any:
    """What the fixed-mount checks see: identity for a moving mount (a track or callable is
    checked per pose), else the extrinsics themselves."""
    return np.eye(4) if callable(extrinsics) else extrinsics


def _as_spec(name: str, spec: SliceSpec | Mapping[str, Any]) -> SliceSpec:
    if isinstance(spec, SliceSpec):
        out = spec
    elif isinstance(spec, Mapping):
        known = {f.name for f in dataclasses.fields(SliceSpec)}
        unknown = set(spec) - known
        if unknown:
            raise ConfigError(f"slices[{name!r}]", sorted(unknown), f"keys among {sorted(known)}")
        if "min_height" not in spec or "max_height" not in spec:
            raise ConfigError(f"slices[{name!r}]", dict(spec),
                              "min_height and max_height (metres, target frame)")
        out = SliceSpec(**spec)
    else:
        raise ConfigError(f"slices[{name!r}]", spec, "a SliceSpec or a dict of its fields")
    return out


#: :func:`to_laserscan`'s converters (module docstring of converters.shared.converter_cache)
_CACHE = ConverterCache()


def _options_key(spec: SliceSpec, kwargs: dict[str, Any]) -> tuple[Any, ...] | None:
    """The options part of :func:`to_laserscan`'s cache key, or None when an option cannot be
    part of one (not a number, not hashable: :func:`converters.shared.options.slice_options`
    then says what is wrong)."""
    extrinsics = kwargs["extrinsics"]
    try:
        # a moving mount is cached by identity (the cached converter keeps it alive)
        ext = None if extrinsics is None else ("moving", id(extrinsics)) \
            if callable(extrinsics) else check_extrinsics(extrinsics).tobytes()
        # the type tells IfPresent("intensity") (the default) from a required "intensity"
        key = (float(spec.min_height), float(spec.max_height), ext,
               tuple((k, type(v), v) for k, v in kwargs.items() if k != "extrinsics"))
        hash(key)
    except (TypeError, ValueError):             # ConfigError, ValidationError included
        return None
    return key


def to_laserscan(scan: Any, info: Any, *, min_height: float, max_height: float,
                 extrinsics: Any = None, frame_id: str | None = None,
                 angle_min: float | None = None, angle_max: float | None = None,
                 angle_increment: float | None = None, range_min: float | None = None,
                 range_max: float | None = None,
                 intensity_channel: str | None = IfPresent("intensity"),
                 use_inf: bool = True, inf_epsilon: float = 1.0, fill: float | None = None,
                 holes: bool = False, floor_height: float = 0.0, hole_depth: float = 0.05,
                 hole_range_max: float | None = None, hole_no_return: bool = True,
                 range_channel: str = "range", backend: str = "auto") -> Any:
    """One height slice of a LidarScan as a ``sensor_msgs.msg.LaserScan``.

    Arguments are those of :class:`SliceConverter` with a single :class:`SliceSpec`
    ``(min_height, max_height)``. The converter (and its per-pixel tables) is cached per
    LidarInfo version and options, so calling this per scan is cheap; for several slices of the
    same scan use :class:`SliceConverter` (one pass).

    Returns:
        rclpy ``sensor_msgs.msg.LaserScan`` stamped with the scan's stamp, ``ranges`` and
        ``intensities`` as ``array.array('f')``.
    """
    kwargs = {"extrinsics": extrinsics, "frame_id": frame_id, "angle_min": angle_min,
              "angle_max": angle_max, "angle_increment": angle_increment,
              "range_min": range_min, "range_max": range_max,
              "intensity_channel": intensity_channel, "use_inf": use_inf,
              "inf_epsilon": inf_epsilon, "fill": fill, "holes": holes,
              "floor_height": floor_height, "hole_depth": hole_depth,
              "hole_range_max": hole_range_max, "hole_no_return": hole_no_return,
              "range_channel": range_channel, "backend": backend}
    spec = SliceSpec(min_height, max_height)
    wanted = _options_key(spec, kwargs)
    key, converter = None, None
    if wanted is not None:
        seen = _CACHE.keys.get((id(info), wanted))       # this info object, seen before
        key = (seen[2] if seen is not None and seen[0] is info and seen[1] == (
            info.header.stamp.sec, info.header.stamp.nanosec) else _CACHE.key(info, wanted))
        with _CACHE.lock:
            converter = _CACHE.idle.pop(key, None)
    if converter is None:
        # the options of a cached converter were checked when it was built (equal key: equal
        # values of the same types); the others are checked here, before anything is built
        options.slice_options({"slice": spec}, {**kwargs, "extrinsics": _checkable(extrinsics)})
        converter = SliceConverter(info, {"slice": spec}, **kwargs)
    try:
        return converter.convert(scan)["slice"]
    finally:
        if key is not None:
            _CACHE.give(key, converter)
