"""One place that prepares the geometry of a scan for the outputs (slices, clouds).

A converter holds one :class:`ScanGeometry` per LidarInfo version (and fixed mount) and asks it,
once per scan, for what it needs with a :class:`RayRequest` built from its configuration; it
gets one :class:`ScanRays` back and then does only its own job (bin and fuse, write fields).
Everything the outputs read of a scan besides that job comes from here: the linkage and size
checks, the stamp, the range image (native channel view or decoded metres), the channel views
they publish, the column and pixel times, the rays, and for a moving mount (a
:class:`converters.shared.transforms.TransformTrack` or a callable) the poses at the pixels'
times (:class:`MountPoses`; moving the rays by them is the output's backend's job).

Conventions: times are int64 ns, relative to ``scan.header.stamp`` unless named ``stamp``;
ranges float32 metres along the beam (REP 117: +Inf no return); rays ``p = r * D + O`` with
directions ``D`` and origins ``O`` float32 metres, in the LidarInfo's frame (the sensor) or,
with a fixed mount's extrinsics, in the target frame (:func:`converters.shared.frames.transform_rays`);
images in the scan's column order (``is_destaggered``) unless said otherwise.

Rays depend on the scan only through its *geometry key* (:attr:`ScanRays.key`):
``("info", destaggered)`` when the info's own angles apply (the rays are the same for every scan
of the info: converters keep what they derive from them per key), or ``("measured",
destaggered, has_azimuth_channel, digest)`` when the scan carries ``column_azimuth_angles`` or a
per-pixel azimuth channel (:func:`lidarscan.geometry.pixel_azimuths`; rebuilt when the digest
changes). So the per-pixel rays are computed on demand (:meth:`ScanGeometry.sensor_tables`,
:meth:`ScanGeometry.target_rays`) and only asked for when a converter's cache for that key is
empty; kept here are the factored beam model of the latest measured key (the info's is the
projector's), a moving mount's sensor-frame rays of the latest key (:meth:`ScanGeometry.sensor_rays`)
and its pixel times per column timing (:meth:`ScanGeometry.pose_times`).
"""

from __future__ import annotations

import dataclasses
import hashlib
from typing import Any, cast

import numpy as np

from converters.shared.frames import check_poses, transform_rays
from converters.shared.transforms import OutOfSpanError, TransformTrack, segment_rotvecs
from lidarscan.errors import InfoMismatchError, LinkageError, ValidationError
from lidarscan.geometry import make_projector
from lidarscan.scan import ChannelWant, channel, read_views
from lidarscan.stamps import split_ns, to_ns

__all__ = ["ChannelWant", "MountPoses", "RayRequest", "ScanGeometry", "ScanRays"]


@dataclasses.dataclass(frozen=True)
class RayRequest:
    """What an output needs of each scan (build it once per configuration).

    Attributes:
        raw: the range channel as a native (H, W) view (first element of a count > 1 channel).
        metres: the range channel decoded to float32 metres, flat (H*W,) C-contiguous.
        channels: the channel images to publish (:class:`ChannelWant`).
        column_times: (W,) int64 ns of each measurement column.
        factors: the factored beam model for this scan's geometry, or None where it does not
            factor (per-pixel angles in the info, a per-pixel azimuth channel).
        mount: a moving mount's poses (:class:`MountPoses`): "poses" (one pose per distinct
            pixel time), "track" (a :class:`TransformTrack` whose pixel times vary within a
            column: the track's samples for a kernel that interpolates each ray's pose), or
            None.
    """

    raw: bool = False
    metres: bool = False
    channels: tuple[ChannelWant, ...] = ()
    column_times: bool = False
    factors: bool = False
    mount: str | None = None


@dataclasses.dataclass
class MountPoses:
    """Where a moving mount was while the scan was measured (target <- sensor poses).

    Attributes:
        relative: int64 ns since the stamp: the (P,) distinct pixel times (sorted) with
            ``index``, else every pixel's time (H*W,) (scan column order, row-major).
        index: (H*W,) int64, the distinct time (and pose) of each pixel, or None.
        poses: (P, 4, 4) float64 poses at the distinct times, or None (``samples`` instead).
        samples: (times (S,) int64 ns, poses (S, 4, 4) float64, rotation vectors (S-1, 3)) of
            the track around the scan, for a kernel interpolating each ray's pose, or None.
        held: the (4, 4) pose when the mount held still over the whole scan (then the rays
            are those of a fixed mount at that pose), else None.
    """

    relative: np.ndarray[Any, Any]
    index: np.ndarray[Any, Any] | None
    poses: np.ndarray[Any, Any] | None
    samples: tuple[np.ndarray[Any, Any], ...] | None
    held: np.ndarray[Any, Any] | None


@dataclasses.dataclass
class ScanRays:
    """The geometry of one scan, as :meth:`ScanGeometry.prepare` found it.

    Attributes:
        scan: the scan (for :meth:`ScanGeometry.sensor_tables` and friends).
        stamp_ns: ``header.stamp`` in int64 ns.
        stamp: the same as (sec, nanosec), for the headers of the outputs.
        destaggered: the scan's columns are destaggered *and* the info has pixel shifts (the
            column order of every image and table here).
        key: the geometry key (module docstring).
        raw: the native range channel view (H, W) or None (not requested).
        metres: (H*W,) float32 metres or None (not requested).
        views: :attr:`ChannelWant.key` -> native view (None: missing, not required).
        column_times: (W,) int64 ns since the stamp of each measurement column (asked for, or
            a moving mount's), or None.
        factors: the factored beam model (float32 rows (H, 6), columns (6, W), constant (6,))
            of this geometry, or None (not requested, or it does not factor).
        period_ns: the scan period (``W * column_time_increment``, or from the column times).
        mount: a moving mount's poses (:attr:`RayRequest.mount`), or None.
    """

    scan: Any
    stamp_ns: int
    stamp: tuple[int, int]
    destaggered: bool
    key: tuple[Any, ...]
    raw: np.ndarray[Any, Any] | None
    metres: np.ndarray[Any, Any] | None
    views: dict[str, np.ndarray[Any, Any] | None]
    column_times: np.ndarray[Any, Any] | None
    factors: tuple[np.ndarray[Any, Any], ...] | None
    period_ns: float
    mount: MountPoses | None = None


class ScanGeometry:
    """The geometry service of one LidarInfo version (and fixed mount).

    Args:
        info: the LidarInfo (rclpy message or dataclass).
        range_channel: the range channel ("range", "range2", ...): its return number selects
            the per-pixel azimuth channel and the channels of :attr:`ChannelWant.per_return`.
        extrinsics: 4x4 float64 pose of the info's frame in the target frame (checked by the
            caller), or None: the rays of :meth:`target_rays` are then the sensor's.
        moving: a moving mount: a :class:`TransformTrack` or a callable ``stamp_ns (int) ->
            4x4`` (each result checked), looked up at the pixels' times; or None.
        linkage_hint: what the linkage error says the expected stamp is.

    Raises (:meth:`prepare`):
        InfoMismatchError: the scan's size differs from the info's, or an integer range channel
            with an info multiplier that cannot decode it.
        LinkageError: ``scan.lidar_info_time`` does not name this info.
        UnknownChannelError: the range channel or a required channel is missing.
        ValidationError: column azimuths (or, when asked for, column times) of the wrong length.
    """

    def __init__(self, info: Any, *, range_channel: str = "range",
                 extrinsics: np.ndarray[Any, Any] | None = None,
                 moving: Any = None,
                 linkage_hint: str = "the LidarInfo's header.stamp, in ns") -> None:
        self.info = info
        self.projector = make_projector(info)
        self.height, self.width = self.projector.height, self.projector.width
        self.info_stamp_ns = self.projector.info_stamp_ns
        self.has_shift = bool(np.any(self.projector.shifts))
        self.range_channel = range_channel
        self.extrinsics = extrinsics
        self._linkage_hint = linkage_hint
        self._mult = float(info.range_multiplier)
        self._increment = self.projector.column_time_increment
        self._factors: tuple[Any, tuple[np.ndarray[Any, Any], ...] | None] | None = None
        self.moving = moving
        #: pixel times kept per column timing (see :meth:`pose_times`)
        self._time_cache: tuple[Any, tuple[np.ndarray[Any, Any],
                                           np.ndarray[Any, Any] | None]] | None = None
        #: sensor-frame rays of the latest geometry (see :meth:`sensor_rays`)
        self._rays_cache: tuple[Any, tuple[np.ndarray[Any, Any], ...]] | None = None

    # ------------------------------------------------------------------------------ per scan
    def prepare(self, scan: Any, request: RayRequest) -> ScanRays:
        """The geometry of one scan (see :class:`ScanRays`), what ``request`` asks for.

        The scan is read by one call of the core (:func:`lidarscan.scan.read_views`) after
        the linkage and size checks; the geometry then comes from the projector."""
        height, width = int(scan.height), int(scan.width)
        if (height, width) != (self.height, self.width):
            raise InfoMismatchError("LidarScan.height x width", f"{height}x{width}",
                                    f"{self.height}x{self.width} from the LidarInfo")
        link = to_ns(scan.lidar_info_time, field="LidarScan.lidar_info_time")
        if link != self.info_stamp_ns:
            raise LinkageError("LidarScan.lidar_info_time", link,
                               f"{self.info_stamp_ns} ({self._linkage_hint})")
        stamp_ns = to_ns(scan.header.stamp, field="LidarScan.header.stamp")
        stamp = split_ns(stamp_ns, field="LidarScan.header.stamp")
        read = read_views(scan, request.channels, range_channel=self.range_channel,
                          info=self.info, raw=request.raw, metres=request.metres)
        raw = read.raw
        if (raw is not None and raw.dtype.kind != "f"
                and not (self._mult > 0 and np.isfinite(self._mult))):
            raise InfoMismatchError(
                "LidarInfo.range_multiplier", self._mult,
                f"> 0 to decode the integer channel {self.range_channel!r}")
        measured, offsets = read.column_azimuth_angles, read.column_time_offsets
        if measured.size and measured.size != width:
            raise ValidationError("LidarScan.column_azimuth_angles", f"length {measured.size}",
                                  f"length {width} or 0")
        destaggered = bool(scan.is_destaggered) and self.has_shift
        measured_key = measured.size or read.azimuth is not None
        key = (self._key(scan, measured, read.azimuth, destaggered) if measured_key
               else ("info", destaggered))
        factors = None
        if request.factors:
            factors = (self._factors_of(key, measured) if measured_key
                       else self.projector.factors())
        column_times = (self.projector.column_times(offsets=offsets)
                        if request.column_times or request.mount is not None else None)
        period = (float(width * self._increment) if self._increment > 0
                  else self._period_ns(offsets))
        rays = ScanRays(scan=scan, stamp_ns=stamp_ns, stamp=stamp, destaggered=destaggered,
                        key=key, raw=raw, metres=read.metres, views=read.channels,
                        column_times=column_times, factors=factors, period_ns=period)
        if request.mount is not None:
            rays.mount = self.mount(rays, request.mount)
        return rays

    def _key(self, scan: Any, measured: np.ndarray[Any, Any], azimuths: str | None,
             destaggered: bool) -> tuple[Any, ...]:
        """The geometry key of a scan (module docstring)."""
        if not measured.size and azimuths is None:
            return ("info", destaggered)
        digest = hashlib.blake2b(np.ascontiguousarray(measured).tobytes(), digest_size=16)
        if azimuths is not None:
            digest.update(b"azimuths")
            digest.update(np.ascontiguousarray(channel(scan, azimuths)).tobytes())
        return ("measured", destaggered, azimuths is not None, digest.digest())

    def _period_ns(self, offsets: np.ndarray[Any, Any]) -> float:
        """The scan period from its column times (the info has no column time increment)."""
        width = self.width
        if width >= 2 and offsets.size == width:
            return float(offsets[-1] - offsets[0]) * width / (width - 1)
        return 0.0

    # ------------------------------------------------------------------------------- rays
    def _factors_of(self, key: tuple[Any, ...], measured: np.ndarray[Any, Any]
                    ) -> tuple[np.ndarray[Any, Any], ...] | None:
        """The factored beam model of a measured geometry (kept for the latest key), or None."""
        if key[2]:                      # a per-pixel azimuth channel: does not factor
            return None
        cached = self._factors
        if cached is None or cached[0] != key[3]:
            cached = (key[3], self.projector.factors(measured))
            self._factors = cached
        return cached[1]

    def sensor_tables(self, rays: ScanRays, destaggered: bool | None = None
                      ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any], bool]:
        """(D, O, tables_destaggered): (H, W, 3) float32 directions and origins in the info's
        frame. The info's own geometry comes in the order ``destaggered`` asks for (default:
        the scan's; the projector keeps both), a measured one in the scan's column order (the
        returned flag says which)."""
        if rays.key[0] == "info":
            order = rays.destaggered if destaggered is None else bool(destaggered)
            d, o = self.projector.tables(order)
            return d, o, order and self.has_shift
        d, o = self.projector.tables_for(rays.scan, self.range_channel)
        return d, o, rays.destaggered

    def target_rays(self, rays: ScanRays) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
        """(H*W, 3) float32 directions and origins in the target frame (the fixed mount's
        extrinsics applied; the sensor's when there are none), the scan's column order."""
        d, o, _ = self.sensor_tables(rays)
        d, o = d.reshape(-1, 3), o.reshape(-1, 3)
        if self.extrinsics is None:
            return d, o
        return transform_rays(d, o, self.extrinsics)

    def tie_keys(self, destaggered: bool) -> np.ndarray[Any, Any] | None:
        """Measurement-order key ``u*W + c`` of each pixel of a destaggered scan (H*W,) int64
        (ties between equal ranges go to the first pixel in measurement order), else None."""
        if not destaggered:
            return None
        src = self.projector.destagger_index
        return (np.arange(self.height)[:, None] * self.width + src).reshape(-1).astype(np.int64)

    def sensor_rays(self, rays: ScanRays, columns: bool = False
                    ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
        """(n, 3) float32 C-contiguous sensor-frame directions and origins of a scan, or with
        ``columns`` the same as (3, n) (one row per component; kept for the next scan of the
        same geometry)."""
        geometry = rays.key
        if self._rays_cache is None or self._rays_cache[0] != geometry:
            d32, o32, _ = self.sensor_tables(rays)
            d32 = np.ascontiguousarray(d32.reshape(-1, 3), np.float32)
            o32 = np.ascontiguousarray(o32.reshape(-1, 3), np.float32)
            self._rays_cache = (geometry, (d32, o32, np.ascontiguousarray(d32.T),
                                           np.ascontiguousarray(o32.T)))
        kept = self._rays_cache[1]
        return (kept[2], kept[3]) if columns else (kept[0], kept[1])

    # ----------------------------------------------------------------------- moving mounts
    def mount(self, rays: ScanRays, mode: str) -> MountPoses:
        """The moving mount's poses for a scan (:class:`MountPoses`; ``mode`` as
        :attr:`RayRequest.mount`). With "track", pixel times that vary within a column give the
        track's samples around the scan and their segments' rotation vectors
        (:func:`converters.shared.transforms.segment_rotvecs`) instead of a pose per time.

        Raises:
            OutOfSpanError: a pixel time outside the track's span.
            TransformLookupError: raised by the callable.
            ValidationError: the callable returned something other than a finite rigid 4x4.
        """
        relative, index = self.pose_times(rays.scan, distinct=mode != "track",
                                          columns=rays.column_times)
        stamp = np.int64(rays.stamp_ns)
        if index is None:
            track = self.moving
            try:
                times, poses = track.samples(stamp + relative.min(), stamp + relative.max())
            except OutOfSpanError:
                self.mount_poses(rays.scan)     # raises what the per-time lookup names
                raise
            if np.all(poses == poses[0]):       # one pose held over the scan
                return MountPoses(relative, None, None, None,
                                  track.lookup_many(stamp + relative[:1])[0])
            return MountPoses(relative, None, None,
                              (times, poses, segment_rotvecs(poses[:-1], poses[1:])), None)
        poses = self.poses_at(stamp + relative)
        held = poses[0] if np.all(poses == poses[0]) else None
        return MountPoses(relative, index, poses, None, held)

    def pose_times(self, scan: Any, distinct: bool = True,
                   columns: np.ndarray[Any, Any] | None = None
                   ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any] | None]:
        """The distinct pixel times of a scan relative to its stamp and each pixel's one.

        When every pixel of a measurement column has its column's time (no per-beam offsets, a
        ``t`` channel constant along each column: tested exactly) the distinct times are those
        of the W columns; otherwise those of all pixels (``np.unique`` of H*W times), or, with
        ``distinct=False``, none are computed.

        ``columns``: the scan's (W,) int64 column times when already known
        (:attr:`ScanRays.column_times`).

        Returns:
            (times, index): (P,) int64 ns sorted, and (H*W,) int64 the time of each pixel
            (scan column order, row-major); with ``distinct=False`` and times varying within a
            column, (H*W,) int64 ns every pixel's time and None. Kept for the next scan when it
            has no ``t`` channel (then they depend only on the column times and the column
            order).
        """
        key = None
        if not any(c.name == "t" for c in scan.channels):   # pixel_delays(scan) is None
            if columns is None:
                columns = self.projector.column_times(scan)
            key = (columns.tobytes(), bool(scan.is_destaggered))
            if self._time_cache is not None and self._time_cache[0] == key:
                kept = self._time_cache[1]
                if kept[1] is None and distinct:     # kept per pixel: not kept again
                    unique, index = np.unique(kept[0], return_inverse=True)
                    return unique, index.reshape(-1).astype(np.int64)
                return kept
        times = self.projector.pixel_times(scan)
        height, width = times.shape
        # the measurement column of each stored pixel
        column = (self.projector.destagger_index
                  if bool(scan.is_destaggered) and self.has_shift
                  else np.broadcast_to(np.arange(width), (height, width)))
        per_column = np.empty(width, np.int64)
        per_column[column[0]] = times[0]
        found: tuple[np.ndarray[Any, Any], np.ndarray[Any, Any] | None]
        if np.array_equal(times, per_column[column]):       # one time per column
            unique, index = np.unique(per_column, return_inverse=True)
            found = (unique, index.reshape(-1)[column].reshape(-1).astype(np.int64))
        elif distinct:
            unique, index = np.unique(times.reshape(-1), return_inverse=True)
            found = (unique, index.reshape(-1).astype(np.int64))
        else:
            found = (times.reshape(-1), None)
        self._time_cache = None if key is None else (key, found)
        return found

    def mount_poses(self, scan: Any) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
        """The moving mount's poses for a scan's pixels.

        Returns:
            (poses, index): (P, 4, 4) float64 target <- sensor at the P distinct pixel times,
            and (H*W,) int64 the pose of each pixel (scan column order, row-major).

        Raises:
            OutOfSpanError: a pixel time outside the track's span.
            TransformLookupError: raised by the callable.
            ValidationError: the callable returned something other than a finite rigid 4x4.
        """
        relative, index = self.pose_times(scan)       # (distinct: index is not None)
        stamp = np.int64(to_ns(scan.header.stamp, field="LidarScan.header.stamp"))
        return self.poses_at(stamp + relative), cast(np.ndarray, index)

    def poses_at(self, stamps: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
        """(P, 4, 4) float64 poses of the mount at the (P,) int64 ns stamps."""
        if isinstance(self.moving, TransformTrack):
            return self.moving.lookup_many(stamps)
        return check_poses([self.moving(int(t)) for t in stamps], "extrinsics(stamp_ns)")
