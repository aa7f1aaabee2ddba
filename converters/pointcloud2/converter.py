"""LidarScan -> sensor_msgs/PointCloud2, with driver presets and deskew.

LidarScan -> PointCloud2
========================
:func:`to_pointcloud2` (or a reusable :class:`PointCloud2Converter`) projects a scan with the
cached :func:`lidarscan.make_projector` tables (``P = rho * D + O``) and writes every field
straight into one structured numpy buffer (names / offsets / itemsize = ``point_step``), little
endian, ``row_step = point_step * width``. Points of pixels without a return (range +Inf, NaN,
<= 0, raw 0) are NaN in organized clouds (``is_dense`` false) and dropped in unorganized ones.

Fields (``fields=``, when no preset is given; x, y, z are required):

==============  =========  ==================================================================
name            datatype   value
==============  =========  ==================================================================
x, y, z         FLOAT32    metres in the info's frame (REP 103)
ring            UINT16     beam index (row, 0 = top beam)
t               UINT32     ns since the cloud's header stamp
time            FLOAT32    s since the cloud's header stamp
timestamp       FLOAT64    absolute s (sensor clock of the scan stamp)
range           FLOAT32    metres along the beam (NaN without return)
intensity       FLOAT32    the ``intensity`` channel (alias ``signal``) as float32
any other       native     the scan channel of that name (aliases: ambient = near_ir/nearir,
                           reflectivity = reflec), its own datatype and count
==============  =========  ==================================================================

Generic layouts place fields in the order given at their natural alignment (x, y, z, intensity
-> the 16-byte XYZI layout). Per-point time = ``column_time_offsets[c] + beam_time_offsets[u]``
(:meth:`lidarscan.Projector.pixel_times`), so it follows destaggering.

Presets (``preset=``) reproduce what the drivers publish (layouts and sources:
:mod:`converters.shared.cloud_layout`), so consumers work unchanged.

Presets choose their defaults for ``organized`` / ``destagger`` / ``time_reference`` (ouster:
organized, destaggered, "stamp"; velodyne: unorganized, firing order, "last"; hesai/robosense:
unorganized, firing order, "first"); explicit arguments override them. ``time_reference``:
"stamp" (cloud stamp = scan stamp, time of measurement column 0), "first" (earliest pixel time),
"last" (latest pixel time). Preset channel fields missing from a scan are zero-filled.

Deskew: ``motion=`` (:mod:`converters.shared.deskew`) moves every point to the pose at the cloud's header
stamp (or ``motion.reference_ns``) using each pixel's own time.

Compiled path: the hot loop (validity of each range, x, y, z, one channel field such as
intensity, destaggering, dropping invalid points for unorganized row-order clouds) runs in the
optional C kernel of :mod:`converters._kernels.cloud` (:func:`kernel_available`; chosen by
:func:`converters._kernels.select`: ``kernel=False``, ``LIDARSCAN_NO_KERNEL=1`` or building
inside :func:`numpy_reference` turn it off);
every other field, and everything without the kernel, is numpy, the reference. The kernel
projects from the factored beam model (:func:`lidarscan.geometry.beam_factors`), the numpy path
from the projector's float32 tables ``r * D + O``: both are float32 evaluations of the same
model, a few ulps apart (< 0.05 mm on a real OS-2 frame against the float64 model). Every other
byte is identical, including the canonical quiet NaN (0x7fc00000) of every point without a
return. Infos with per-pixel angles do not factor; the kernel then reads the tables,
byte-identical to numpy; so do scans with a per-pixel azimuth channel (``azimuth``,
:func:`lidarscan.geometry.pixel_azimuths`; tables rebuilt per scan). Layouts without padding
reuse the buffer of the converter's previous message once that message was dropped. Rows can be split over threads (``threads=``).
The numpy field writers and row rolling live in :mod:`converters.pointcloud2.fields`, the kernel's
plan and call arguments in :mod:`converters.pointcloud2.kernel`.
Everything the converter reads of a scan besides writing fields -- checks, stamp, range and
channel images, times, beam factors or tables -- it asks of its geometry service in one call
per scan (:class:`converters.shared.scan_rays.ScanGeometry`).
Reading clouds (:func:`read_points`) and estimating a LidarScan from one
(:func:`from_pointcloud2`, :func:`estimation_error`) live in :mod:`converters.shared.cloud_layout` and
:mod:`converters.sources.clouds.importer`; they are re-exported here.
"""

from __future__ import annotations

import array
import contextlib
import contextvars
import itertools
import sys
from collections.abc import Iterator, Sequence
from typing import Any, cast

import numpy as np

from converters import _kernels
from converters._kernels import cloud as _ck
from converters.pointcloud2.fields import (
    FieldWriter,
    _Block,
    _Job,
    _Planes,
    _roll_into,
    _shift_groups,
    _xy_pair,
)
from converters.pointcloud2.kernel import KernelJobs, kernel_plan
from converters.shared.cloud_layout import (
    CHANNEL_ALIASES,
    COMPUTED_TYPES,
    DEFAULT_FIELDS,
    PRESETS,
    FieldSpec,
    Preset,
    cloud_dtype,
    find_channel,
    generic_layout,
    read_points,
    structured,
)
from converters.shared.converter_cache import ConverterCache
from converters.shared.scan_rays import ChannelWant, RayRequest, ScanGeometry, ScanRays
from converters.sources.clouds.importer import ReprojectionError, estimation_error, from_pointcloud2
from lidarscan.datatypes import dtype_of
from lidarscan.errors import ConfigError, ConversionError, UnknownChannelError
from lidarscan.geometry import pixel_delays
from lidarscan.rosmsg import bare_message
from lidarscan.scan import as_array
from lidarscan.stamps import split_ns

__all__ = [
    "CHANNEL_ALIASES",
    "PRESETS",
    "FieldSpec",
    "PointCloud2Converter",
    "Preset",
    "ReprojectionError",
    "cloud_dtype",
    "estimation_error",
    "from_pointcloud2",
    "kernel_available",
    "read_points",
    "to_pointcloud2",
]

_TIME_REFERENCES = ("stamp", "first", "last")
#: Output buffers a converter keeps for reuse (the caller may hold the previous messages).
_POOL = 3

#: set by :func:`numpy_reference`: converters built without ``kernel=`` use numpy
_NUMPY_REFERENCE: contextvars.ContextVar[bool] = contextvars.ContextVar(
    "lidarscan_pointcloud2_numpy_reference", default=False)


@contextlib.contextmanager
def numpy_reference() -> Iterator[None]:
    """Inside: converters built without ``kernel=`` (and :func:`to_pointcloud2`) use the numpy
    reference path, even where the compiled kernel is built, so their clouds are the same bytes
    on every machine (what ``python -m converters.edge.evidence`` needs for its deterministic
    tables). ``LIDARSCAN_NO_KERNEL`` is read once per process; this is per context."""
    token = _NUMPY_REFERENCE.set(True)
    try:
        yield
    finally:
        _NUMPY_REFERENCE.reset(token)


def kernel_available() -> bool:
    """Whether LidarScan -> PointCloud2 uses the compiled kernel (:mod:`converters._kernels.cloud`).

    The kernel is optional; it is built by ``pip install [-e] .`` when a C compiler is
    available. ``LIDARSCAN_NO_KERNEL=1`` disables it. It projects from the factored beam model
    (:func:`lidarscan.geometry.beam_factors`) where the info has no per-pixel angles, and from
    the same per-pixel tables as the numpy path otherwise (then bit-identical to it); the two
    forms are float32 evaluations of one model, a few ulps apart (both well within 0.1 mm).
    """
    return _ck.available()


# ================================================================================= converter

class PointCloud2Converter:
    """Reusable LidarScan -> PointCloud2 converter for one LidarInfo.

    Holds the projector tables split into contiguous float32 planes in the output column order,
    the output layouts and preallocated scratch images, so a conversion allocates only the
    message's own byte buffer, which the fields are written into directly and which the message
    then takes over without a copy. Not thread-safe: use one converter per thread.

    Args:
        info: the LidarInfo (rclpy message or dataclass) of the scans to convert.
        preset: a name in :data:`PRESETS`, or None for a generic layout from ``fields``.
        fields: field names (see the module docstring); default x, y, z, intensity (x, y, z
            when the scan has no intensity channel). Not allowed together with a preset.
        organized: keep the H x W grid with NaN points (True) or drop points without a return
            (False); default: the preset's (True without preset).
        destagger: columns in azimuth order (True) or measurement order; default: the preset's.
        time_reference: "stamp", "first" or "last" (see the module docstring); default: the
            preset's ("stamp" without preset).
        motion: default motion for deskew (:func:`converters.shared.deskew.as_motion` forms), or None.
        range_channel: the channel holding the ranges ("range", "range2", ...). For the N-th
            return's range, channel fields read that return's channel (``intensity2``) where
            the scan has one, else the shared channel (``ambient``).
        frame_id: header.frame_id of the clouds; default the scan's.
        threads: split the rows over this many threads (numpy and the kernel release the
            GIL); 1 = no thread pool.
        kernel: use the optional compiled kernel for x, y, z (+ one float32 channel field and
            the validity test): None = when available (:func:`kernel_available`) unless built
            inside :func:`numpy_reference`, False = numpy only, True = required. Both paths
            give the same clouds up to float32 rounding of x, y, z (see
            :func:`kernel_available`); every other byte is identical.

    Raises:
        ConfigError: unknown preset / time reference, fields with a preset, no x/y/z, kernel
            required but not available.
    """

    def __init__(self, info: Any, *, preset: str | None = None,
                 fields: Sequence[str] | None = None, organized: bool | None = None,
                 destagger: bool | None = None, time_reference: str | None = None,
                 motion: Any = None, range_channel: str = "range",
                 frame_id: str | None = None, threads: int = 1,
                 kernel: bool | None = None) -> None:
        if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
            raise ConfigError("threads", threads, "an int >= 1")
        if kernel is None and _NUMPY_REFERENCE.get():
            kernel = False
        kernels = _kernels.select("cloud", kernel=kernel).c
        if preset is not None:
            if preset not in PRESETS:
                raise ConfigError("preset", preset, f"one of {sorted(PRESETS)} or None")
            if fields is not None:
                raise ConfigError("fields", list(fields), "None when a preset is given "
                                  "(a preset fixes the fields)")
        self.preset: Preset | None = PRESETS[preset] if preset is not None else None
        if fields is not None:
            names = tuple(fields)
            if isinstance(fields, str) or not all(isinstance(n, str) and n for n in names):
                raise ConfigError("fields", fields, "a sequence of non-empty field names")
            if len(set(names)) != len(names):
                raise ConfigError("fields", names, "unique field names")
        else:
            names = DEFAULT_FIELDS
        self._default_fields = fields is None
        if self.preset is None and not {"x", "y", "z"} <= set(names):
            raise ConfigError("fields", names, "x, y and z among the fields")
        self.field_names = names
        p = self.preset
        self.organized = bool(p.organized if p and organized is None else
                              (True if organized is None else organized))
        self.time_reference = time_reference if time_reference is not None else (
            p.time_reference if p else "stamp")
        if self.time_reference not in _TIME_REFERENCES:
            raise ConfigError("time_reference", self.time_reference, f"one of {_TIME_REFERENCES}")
        if motion is not None:
            from converters.shared.deskew import as_motion
            motion = as_motion(motion)
        self.motion = motion
        self.range_channel = range_channel
        self.frame_id = frame_id
        self.order = p.order if p else "rows"
        self.ring_mode = p.ring if p else "row"

        self.info = info
        #: the geometry service: checks, stamp, range image, channel views, times, rays
        self._geometry = ScanGeometry(info, range_channel=range_channel)
        self.projector = self._geometry.projector
        proj = self.projector
        self.height, self.width = proj.height, proj.width
        self._has_shift = bool(np.any(proj.shifts % max(self.width, 1)))
        want = p.destagger if p and destagger is None else (True if destagger is None
                                                            else destagger)
        self.destagger = bool(want)
        self._grid_destaggered = self.destagger and self._has_shift
        self._groups = _shift_groups(proj.shifts, self.width) if self._has_shift else None
        bounds = np.linspace(0, self.height, min(threads, max(self.height, 1)) + 1).astype(int)
        self._blocks = [
            _Block(slice(int(a), int(b)),
                   _shift_groups(proj.shifts[a:b], self.width) if self._has_shift else None)
            for a, b in itertools.pairwise(bounds) if b > a]
        self._pool = None
        if len(self._blocks) > 1:
            from concurrent.futures import ThreadPoolExecutor
            self._pool = ThreadPoolExecutor(len(self._blocks), "pointcloud2")
        self._mult = float(info.range_multiplier)
        self._offset = float(info.range_offset)
        self._kfn = kernels                  # the compiled kernel's calls: self._jobs
        self._ring_values = self._rings(info)
        self._planes: _Planes | None = None
        self._scan_planes: tuple[tuple[Any, ...], _Planes] | None = None   # measured geometry
        self._requests: dict[tuple[int, bool, bool], RayRequest] = {}
        self._times_cache: tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]] | None = None
        self._layouts: dict[Any, tuple[tuple[FieldSpec, ...], int, np.dtype[Any]]] = {}
        #: the numpy field writers, with the scratch images (``r``: the decoded ranges)
        self._writer = FieldWriter(self.height, self.width, self._mult, self._offset,
                                   has_shift=self._has_shift,
                                   grid_destaggered=self._grid_destaggered)
        self._rolls: dict[bool | str, np.ndarray[Any, Any]] = {}
        self._grid: np.ndarray[Any, Any] | None = None
        self._spares: list[array.array[int]] = []            # see _output
        self._coverage: dict[tuple[int, int], bool] = {}
        self._order_index: np.ndarray[Any, Any] | None = None

    @property
    def _kfn(self) -> _ck.Kernels | None:
        """The compiled kernel's entry points this converter calls, or None (numpy only)."""
        return None if self._jobs is None else self._jobs.kernels

    @_kfn.setter
    def _kfn(self, kernels: _ck.Kernels | None) -> None:
        #: the compiled kernel's calls (None: numpy only)
        self._jobs = (None if kernels is None
                      else KernelJobs(kernels, self.width, self._mult, self._offset))

    # ---------------------------------------------------------------------------- helpers
    def _roll(self, scan_dest: bool) -> np.ndarray[Any, Any] | None:
        """Per-row right rotation (0..W-1, int64) taking scan columns to grid columns, or None
        when both are in the same order."""
        if not self._has_shift or scan_dest == self._grid_destaggered:
            return None
        if scan_dest not in self._rolls:
            sign = 1 if self._grid_destaggered else -1
            shifts = np.asarray(self.projector.shifts, np.int64)
            self._rolls[scan_dest] = np.ascontiguousarray((sign * shifts) % self.width)
        return self._rolls[scan_dest]

    def _colshift(self) -> np.ndarray[Any, Any] | None:
        """Per-row right rotation (0..W-1, int64) from measurement columns to grid columns, or
        None when the grid is in measurement order (the factored kernel's ``colshift``)."""
        if not self._grid_destaggered:
            return None
        if "colshift" not in self._rolls:
            shifts = np.asarray(self.projector.shifts, np.int64)
            self._rolls["colshift"] = np.ascontiguousarray(shifts % self.width)
        return self._rolls["colshift"]

    def _rings(self, info: Any) -> np.ndarray[Any, Any]:
        height = self.height
        ids = as_array(info.beam_ids, np.uint16)
        rows = np.arange(height)
        if self.ring_mode == "low":            # elevation rank from the bottom beam
            values = height - 1 - rows
        elif self.ring_mode == "ids" and ids.size:
            values = ids.astype(np.int64)
        else:
            values = rows
        return np.asarray(values, dtype=np.uint16)

    def _layout(self, scan: Any) -> tuple[tuple[FieldSpec, ...], int, np.dtype[Any]]:
        if self.preset is not None:
            key: Any = None
        else:
            key = tuple((d.name, int(d.datatype), int(d.count)) for d in scan.channels
                        if d.name not in COMPUTED_TYPES)
        layout = self._layouts.get(key)
        if layout is None:
            if self.preset is not None:
                specs, step = self.preset.fields, self.preset.point_step
            else:
                names = self.field_names
                if self._default_fields and find_channel(
                        scan, CHANNEL_ALIASES["intensity"]) is None:
                    names = ("x", "y", "z")                  # default fields, no intensity
                specs, step = generic_layout(names, scan)
            layout = (specs, step, structured(specs, step))
            self._layouts[key] = layout
        return layout

    def _request(self, specs: tuple[FieldSpec, ...], times: bool, factors: bool
                 ) -> RayRequest:
        """What this layout needs of each scan (one request per layout and path, kept)."""
        key = (id(specs), times, factors)
        request = self._requests.get(key)
        if request is None:
            wants = tuple(ChannelWant(s.name, tuple(s.channels), per_return=True,
                                      first=s.count == 1)
                          for s in specs if s.source == "channel")
            request = RayRequest(raw=True, channels=wants, column_times=times, factors=factors)
            self._requests[key] = request
        return request

    def _tables(self, rays: ScanRays) -> _Planes:
        """Projection tables as contiguous float32 planes in grid order (cached per geometry:
        the info's, or the latest measured one)."""
        if rays.key[0] == "info":
            if self._planes is None:
                d, o, dest = self._geometry.sensor_tables(rays, self._grid_destaggered)
                self._planes = self._split(d, o, dest)
            return self._planes
        cached = self._scan_planes
        if cached is None or cached[0] != rays.key:
            d, o, dest = self._geometry.sensor_tables(rays)
            cached = (rays.key, self._split(d, o, dest))
            self._scan_planes = cached
        return cached[1]

    def _split(self, d: np.ndarray[Any, Any], o: np.ndarray[Any, Any], tables_destaggered: bool
               ) -> _Planes:
        planes = []
        for table in (d, o):
            for k in range(3):
                plane = np.empty((self.height, self.width), np.float32)
                src = table[..., k]
                if tables_destaggered == self._grid_destaggered or not self._has_shift:
                    plane[...] = src
                else:
                    _roll_into(plane, src, self._groups,
                               1 if self._grid_destaggered else -1)
                planes.append(plane)
        for plane in planes[3:]:
            # -0 offsets -> +0: x = r * D + O then has the same sign of zero whether computed
            # per axis (compiled kernel) or as the complex x + iy product below
            np.add(plane, np.float32(0), out=plane)
        return _Planes(planes[:3], planes[3:])

    def _pixel_times(self, rays: ScanRays) -> np.ndarray[Any, Any]:
        """(H, W) int64 ns since the scan stamp, grid order (cached per column times), plus the
        scan's per-pixel ``t`` delays where it has them (:func:`lidarscan.geometry.pixel_delays`,
        moved from the scan's column order to the grid's). ``rays`` has the column times."""
        cols = rays.column_times
        if cols is None:                                  # unreachable: see convert()
            raise ConversionError("column times", None, "asked of the geometry service")
        cached = self._times_cache
        if cached is not None and np.array_equal(cached[0], cols):
            times = cached[1]
        else:
            times = cols[None, :] + self.projector.beam_time_offsets[:, None]
            if self._grid_destaggered:
                grid = np.empty_like(times)
                _roll_into(grid, times, self._groups, 1)
                times = grid
            self._times_cache = (cols.copy(), times)
        delays = pixel_delays(rays.scan)
        if delays is None:
            return np.asarray(times, dtype=np.int64)
        roll = self._roll(rays.destaggered)
        if roll is not None:                # grid[u, (c + r_u) % W] = delays[u, c]
            cols_idx = (np.arange(self.width)[None, :] - roll[:, None]) % self.width
            delays = np.take_along_axis(delays, cols_idx, axis=1)
        return np.asarray(times, dtype=np.int64) + delays

    def _output(self, dtype: np.dtype[Any], points: int, recycle: bool = False
                ) -> tuple[array.array[int], np.ndarray[Any, Any]]:
        """A byte buffer for ``points`` points and its structured view.

        The message takes the buffer over without a copy, so every message gets its own: a new
        zero-filled one, or with ``recycle`` (layouts whose every byte is written each time)
        the buffer of one of this converter's last ``_POOL`` messages that nothing else
        references any more (the message was dropped, e.g. after publishing: CPython reference
        count), which saves the allocation, page faults and zero-fill of a fresh buffer."""
        size = points * dtype.itemsize
        if not recycle:
            self._spares.clear()
            buf = self._output_buffer(size)
        else:
            for spare in self._spares:  # a plain list iteration holds no extra reference
                if len(spare) == size and sys.getrefcount(spare) == 3:  # list, `spare`, argument
                    buf = spare
                    break
            else:
                # every recent buffer is still in use (the caller keeps the last message, a
                # publisher queues it): a fresh one, keeping at most _POOL candidates
                buf = self._output_buffer(size)
                self._spares.append(buf)
                del self._spares[:-_POOL]
        return buf, np.frombuffer(buf, dtype=dtype)

    def _full_coverage(self, specs: Sequence[FieldSpec], step: int) -> bool:
        """Whether the fields cover every byte of a point (no padding); cached per layout (the
        layouts live as long as the converter, so their ids are stable)."""
        key = (id(specs), step)
        if key not in self._coverage:
            covered = np.zeros(step, bool)
            for s in specs:
                covered[s.offset:s.offset + dtype_of(s.datatype).itemsize * s.count] = True
            self._coverage[key] = bool(covered.all())
        return self._coverage[key]

    @staticmethod
    def _output_buffer(size: int) -> array.array[int]:
        return array.array("B", b"\0") * size

    def _scratch(self, dtype: np.dtype[Any]) -> np.ndarray[Any, Any]:
        """Reused (H, W) structured grid for clouds that are reordered or filtered after."""
        if self._grid is None or self._grid.dtype != dtype:
            self._grid = np.zeros((self.height, self.width), dtype)
            self._order_index = None
        return self._grid

    def _firing_order(self) -> np.ndarray[Any, Any]:
        """Flat grid indices in firing order: column by column, beams by ring ascending."""
        if self._order_index is None:
            rows = np.argsort(self._ring_values, kind="stable")
            cols = np.arange(self.width)
            self._order_index = (rows[None, :] * self.width + cols[:, None]).reshape(-1)
        return self._order_index

    # ----------------------------------------------------------------------------- convert
    def convert(self, scan: Any, *, motion: Any = None) -> Any:
        """Convert one scan.

        Args:
            scan: a LidarScan of this converter's info (rclpy message or dataclass).
            motion: deskew motion for this scan (overrides the converter's), or None.

        Returns:
            ``sensor_msgs.msg.PointCloud2`` (see the module docstring for the layout).

        Raises:
            InfoMismatchError / LinkageError: the scan does not belong to the info.
            UnknownChannelError: a requested channel is missing (preset channels zero-fill).
            ConversionError: a time that does not fit the requested time field.
        """
        specs, step, dtype = self._layout(scan)
        motion = motion if motion is not None else self.motion
        needs_times = motion is not None or any(
            s.source in ("t", "time", "timestamp") for s in specs)
        jobs = self._jobs if motion is None else None
        rays = self._geometry.prepare(scan, self._request(
            specs, needs_times or self.time_reference != "stamp", jobs is not None))
        raw = cast(np.ndarray, rays.raw)
        stamp_ns = rays.stamp_ns
        ref = 0
        if self.time_reference != "stamp":
            cols = cast(np.ndarray, rays.column_times)
            beams = self.projector.beam_time_offsets
            pick = np.min if self.time_reference == "first" else np.max
            ref = (int(pick(cols)) if cols.size else 0) + (int(pick(beams)) if beams.size else 0)
        header_ns = stamp_ns + ref
        scan_dest = bool(scan.is_destaggered)
        images = self._images(rays, specs)
        plan = kernel_plan(specs, raw, images) if jobs is not None else None
        factors = rays.factors if plan is not None else None
        # the per-pixel tables: only for the numpy path and the kernel's table form
        tables = self._tables(rays) if factors is None else None
        pixels = self.height * self.width
        roll = self._roll(scan_dest)
        colshift = self._colshift() if factors is not None else None

        if (jobs is not None and plan is not None and plan.covers_all and not self.organized
                and self.order == "rows"):
            # the kernel writes every field: valid points straight into the message, compacted
            buf = self._output_buffer(pixels * step)
            djob = jobs.job(plan, buf, step, tables=tables, factors=factors, roll=roll,
                            colshift=colshift, r_out=None)
            count = djob.run(0, pixels, dense=True)
            del buf[count * step:]
            return self._message(scan, specs, step, (1, count), buf, True, header_ns, rays)

        direct = self.organized and self.order == "rows"
        if direct:                                    # fields go straight into the message
            buf, flat = self._output(dtype, pixels, recycle=self._full_coverage(specs, step))
            grid = flat.reshape(self.height, self.width)
        else:
            grid = self._scratch(dtype)
        kjob = None
        if jobs is not None and plan is not None:
            needs_r = not direct or any(s.source == "range" for s in specs)
            kjob = jobs.job(plan, grid, step, tables=tables, factors=factors, roll=roll,
                            colshift=colshift, r_out=self._writer.r if needs_r else None)
        job = _Job(rays=rays, raw=raw, grid=grid,
                   pair=_xy_pair(grid, specs) if kjob is None else None, specs=specs,
                   tables=tables, images=images,
                   times=self._pixel_times(rays) if needs_times else None,
                   ref=ref, stamp_ns=stamp_ns, scan_dest=scan_dest, kernel=kjob)
        if job.pair is not None and job.tables is not None:
            job.tables.pair()                        # built once, before any worker thread
        if motion is not None:
            self._fill(job, _Block(slice(0, self.height), self._groups), xyz=False)
            self._writer.deskew(job, job.times if job.times is not None
                                else self._pixel_times(rays), motion, header_ns)
            counts: list[int | None] = [None]
        elif self._pool is not None:
            counts = list(self._pool.map(lambda block: self._fill(job, block), self._blocks))
        else:
            counts = [self._fill(job, block) for block in self._blocks]

        r = self._writer.r
        if direct:
            if kjob is not None:
                dense = sum(c or 0 for c in counts) == pixels
            else:
                dense = not bool(np.isnan(r).any())
            return self._message(scan, specs, step, (self.height, self.width), buf,
                                 dense, header_ns, rays)
        valid = ~np.isnan(r).reshape(-1)
        if self.order == "rows":
            index = np.flatnonzero(valid)
        else:
            index = self._firing_order()
            if not self.organized:
                index = index[valid[index]]
        buf, flat = self._output(dtype, index.size)
        np.take(grid.reshape(-1), index, out=flat)
        if self.organized:
            shape = (self.width, self.height)                       # firings x beams
            dense = bool(valid.all())
        else:
            shape, dense = (1, int(index.size)), True
        return self._message(scan, specs, step, shape, buf, dense, header_ns, rays)

    def _images(self, rays: ScanRays, specs: Sequence[FieldSpec]) -> dict[str, Any]:
        """The scan channel (view) feeding each channel field; None: zero-fill (presets). The
        geometry service found them: a field of the N-th return's cloud reads that return's
        channel (intensity2 beside range2) where the scan has one; a channel measured once per
        pixel (ambient) is shared by every return."""
        images = rays.views
        if self.preset is None:
            for spec in specs:
                if spec.source == "channel" and images.get(spec.name) is None:
                    raise UnknownChannelError("fields", spec.name,
                                              f"a channel named one of {spec.channels}")
        return images

    def _fill(self, job: _Job, block: _Block, xyz: bool = True) -> int | None:
        """Write every field of the rows ``block.rows`` (independent of the other rows, so
        blocks can run on several threads: numpy and the kernel release the GIL).

        Returns the number of valid pixels when the compiled kernel ran, else None."""
        rows = block.rows
        writer = self._writer
        r, mask, tmp = writer.scratch(rows)
        kjob = job.kernel
        if kjob is not None and xyz:
            # x, y, z, the extra channel field and (if asked) r in one pass
            valid: int | None = kjob.run(rows.start * self.width,
                                         (rows.stop - rows.start) * self.width)
            done = kjob.done
        else:
            writer.ranges(job, block, r, mask, tmp)
            if xyz:
                writer.write_xyz(job.grid[rows], job.specs, r, job.tables, rows, job.pair)
            valid, done = None, frozenset()
        grid = job.grid[rows]
        for spec in job.specs:
            src = spec.source
            if src in ("x", "y", "z") or spec.name in done:
                continue
            field = grid[spec.name]
            if src == "channel":
                image = job.images[spec.name]
                if image is None:
                    field[...] = 0
                elif field.dtype == np.float32 and image.dtype != np.float32:
                    # a contiguous cast plus a strided float copy beats a strided cast
                    writer.place_rows(tmp, image, block, job.scan_dest)
                    field[...] = tmp
                else:
                    writer.place_rows(field, image, block, job.scan_dest)
            elif src == "ring":
                field[...] = self._ring_values[rows, None]
            elif src == "range":
                writer.range_field(field, spec, r, job.raw, block, job.scan_dest)
            else:
                times = job.times if job.times is not None else self._pixel_times(job.rays)
                writer.time_field(field, spec, times[rows], job.ref, job.stamp_ns)
        return valid

    def _message(self, scan: Any, specs: Sequence[FieldSpec], step: int,
                 shape: tuple[int, int], buf: array.array[int], dense: bool,
                 header_ns: int, rays: ScanRays) -> Any:
        from builtin_interfaces.msg import Time
        from sensor_msgs.msg import PointCloud2, PointField
        from std_msgs.msg import Header

        # the scan's own stamp (time_reference "stamp") comes split with the geometry
        sec, nanosec = rays.stamp if header_ns == rays.stamp_ns else split_ns(header_ns)
        frame = self.frame_id if self.frame_id is not None else scan.header.frame_id
        header = Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=frame)
        fields = [PointField(name=s.name, offset=s.offset, datatype=s.datatype, count=s.count)
                  for s in specs]
        return bare_message(PointCloud2, header=header, height=int(shape[0]),
                            width=int(shape[1]), fields=fields, is_bigendian=False,
                            point_step=int(step), row_step=int(step) * int(shape[1]),
                            data=buf, is_dense=bool(dense))


#: :func:`to_pointcloud2`'s converters (module docstring of converters.shared.converter_cache)
_CACHE = ConverterCache()


def to_pointcloud2(scan: Any, info: Any, *, preset: str | None = None,
                   fields: Sequence[str] | None = None, organized: bool | None = None,
                   destagger: bool | None = None, time_reference: str | None = None,
                   motion: Any = None, range_channel: str = "range",
                   frame_id: str | None = None) -> Any:
    """LidarScan -> ``sensor_msgs.msg.PointCloud2``.

    One-call form of :class:`PointCloud2Converter` (same arguments; converters are cached per
    info version and options, and apart inside :func:`numpy_reference`, so repeated calls
    reuse tables and buffers). Fields default to
    x, y, z, intensity (float32, 16 bytes per point), organized H x W in destaggered column order.

    Args:
        scan: the LidarScan (rclpy message or dataclass).
        info: its LidarInfo (``scan.lidar_info_time`` must equal ``info.header.stamp``).
        preset, fields, organized, destagger, time_reference, range_channel, frame_id: see
            :class:`PointCloud2Converter`.
        motion: deskew motion (see :mod:`converters.shared.deskew`), or None.

    Returns:
        A new ``sensor_msgs.msg.PointCloud2``; points in ``info.header.frame_id`` metres.
    """
    wanted = (preset, None if fields is None else tuple(fields), organized, destagger,
              time_reference, range_channel, frame_id, _NUMPY_REFERENCE.get())
    seen = _CACHE.keys.get((id(info), wanted))           # this info object, seen before
    key = (seen[2] if seen is not None and seen[0] is info and seen[1] == (
        info.header.stamp.sec, info.header.stamp.nanosec) else _CACHE.key(info, wanted))
    with _CACHE.lock:
        conv = None if key is None else _CACHE.idle.pop(key, None)
    if conv is None:
        conv = PointCloud2Converter(info, preset=preset, fields=fields, organized=organized,
                                    destagger=destagger, time_reference=time_reference,
                                    range_channel=range_channel, frame_id=frame_id)
    try:
        return conv.convert(scan, motion=motion)
    finally:
        # checked out while converting: a concurrent call builds its own converter
        if key is not None:
            _CACHE.give(key, conv)
