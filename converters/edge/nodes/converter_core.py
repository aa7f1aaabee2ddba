"""The converter node's logic without rclpy: :class:`ConverterCore` (linkage, converters and
their caches, the moving mount's held scans) and its counters :class:`ConverterStats`.

:mod:`converters.edge.nodes.converter_node` wraps it in the ``lidarscan-converter`` node and
documents the behaviour (parameters, moving mounts, drops); tests drive the core directly.
"""

from __future__ import annotations

from collections import OrderedDict, deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from converters.edge.nodes.params import SliceConfig
from converters.edge.nodes.tf import extend_track
from lidarscan.errors import ConfigError, LidarScanError

__all__ = ["ConverterCore", "ConverterStats"]


@dataclass
class ConverterStats:
    """Counters of a converter (read them in tests or expose them in diagnostics)."""

    scans_received: int = 0
    infos_received: int = 0
    scans_converted: int = 0
    scans_idle: int = 0          # skipped because nobody subscribed
    bad_messages: int = 0        # undecodable / invalid input
    scans_dropped: int = 0       # dropped by the linkage resolver (no/ambiguous/mismatching info)
    conversion_errors: int = 0   # a pair that failed to convert (e.g. no transform)
    clouds_published: int = 0
    slices_published: int = 0
    dropped_no_pose: int = 0     # moving mount: /tf never covered the scan's sweep
    reasons: dict[str, int] = field(default_factory=dict)

    def count(self, reason: str) -> None:
        """Count a drop reason (bounded: at most 64 distinct reasons kept)."""
        key = reason.split(":", 1)[0][:80]
        if key in self.reasons or len(self.reasons) < 64:
            self.reasons[key] = self.reasons.get(key, 0) + 1


class ConverterCore:
    """The node's logic without rclpy: link scans to infos, convert pairs to output messages.

    Args:
        cloud_options: keyword options of :class:`converters.pointcloud2.converter.PointCloud2Converter`.
        slices: the LaserScan slices.
        target_frame: frame of the slices ("" = the LidarInfo's frame); then :meth:`convert`
            needs the extrinsics ``target_frame <- sensor frame``.
        slice_options: common keyword options of :class:`converters.slices.converter.SliceConverter`
            (e.g. ``intensity_channel``).
        max_pending, max_wait_ns, max_infos: bounds of the linkage resolver
            (:class:`lidarscan.linkage.InfoResolver`); ``max_pending`` also bounds the pairs
            held for a moving mount's poses.
        on_event: one line per notable event (drops, info changes).
        moving: the sensor's mount moves (module docstring, **Moving mount**): linked pairs
            go through :meth:`hold` and are converted with :meth:`track` as extrinsics.
        tf_samples: ``(target frame, sensor frame, after_ns) -> [(stamp_ns, 4x4), ...]``
            (:meth:`converters.edge.nodes.tf.TransformBuffer.samples`) that fills the tracks;
            None: fill :attr:`tracks` yourself.
        tf_wait_ns: how long (data time: the newest scan or pose stamp seen) a pair waits for
            the poses of its whole sweep.
        tf_tolerance_ns: how long after the newest pose its pose is held (the tracks'
            ``tolerance_ns``: a pixel time up to that far past the newest pose gets the newest
            pose, never an extrapolated one; 0 = strict, as tf2). A sweep that ends later than
            that waits ``tf_wait_ns`` for more poses, then is dropped and counted.

    Raises:
        ConfigError: ``moving`` without a ``target_frame``.
    """

    def __init__(self, *, cloud_options: Mapping[str, Any] | None = None,
                 slices: Sequence[SliceConfig] = (), target_frame: str = "",
                 slice_options: Mapping[str, Any] | None = None, max_pending: int = 16,
                 max_wait_ns: int | None = 2_000_000_000, max_infos: int = 8,
                 on_event: Any = None, moving: bool = False,
                 tf_samples: Callable[[str, str, int | None], Any] | None = None,
                 tf_wait_ns: int = 100_000_000, tf_tolerance_ns: int = 0) -> None:
        from lidarscan.linkage import InfoResolver

        if moving and not target_frame:
            raise ConfigError("moving", True, "a target_frame (the frame the mount moves in)")
        self.stats = ConverterStats()
        self.cloud_options = dict(cloud_options or {})
        self.slices = list(slices)
        self.target_frame = target_frame
        self.slice_options = dict(slice_options or {})
        self._on_event = on_event or (lambda line: None)
        self.resolver = InfoResolver(max_pending=max_pending, max_wait_ns=max_wait_ns,
                                     max_infos=max_infos, on_event=self._resolver_event)
        self._clouds: OrderedDict[Any, Any] = OrderedDict()
        self._slicers: OrderedDict[Any, Any] = OrderedDict()
        #: the last LidarInfo added (decoded), for :meth:`prepare`
        self.last_info: Any = None
        self.moving = bool(moving)
        self.tf_samples = tf_samples
        self.tf_wait_ns = int(tf_wait_ns)
        if isinstance(tf_tolerance_ns, bool) or not isinstance(tf_tolerance_ns, (int, np.integer)) \
                or tf_tolerance_ns < 0:
            raise ConfigError("tf_tolerance_ns", tf_tolerance_ns, "an int >= 0 (ns)")
        self.tf_tolerance_ns = int(tf_tolerance_ns)
        #: moving mount: sensor frame -> TransformTrack ``target_frame <- sensor frame``
        self.tracks: dict[str, Any] = {}
        #: moving mount: (scan, info, first pixel time, last pixel time) waiting for poses
        self.held: deque[tuple[Any, Any, int, int]] = deque()
        self._data_clock: int | None = None

    def reconfigure(self, *, cloud_options: Mapping[str, Any], slices: Sequence[SliceConfig],
                    slice_options: Mapping[str, Any], max_pending: int,
                    max_wait_ns: int | None, max_infos: int) -> None:
        """New options, effective from the next scan (converter caches dropped; the resolver
        keeps its infos and held scans, only its bounds change; a smaller ``max_infos``
        evicts on the next LidarInfo). The slice names must stay those of the start (their
        publishers exist). Validate first with :meth:`check` on a fresh core."""
        if [s.name for s in slices] != [s.name for s in self.slices]:
            raise ConfigError("slice_names", [s.name for s in slices],
                              f"the slices of the start {[s.name for s in self.slices]}")
        self.cloud_options = dict(cloud_options)
        self.slices = list(slices)
        self.slice_options = dict(slice_options)
        self.resolver.max_pending = max_pending
        self.resolver.max_wait_ns = max_wait_ns
        self.resolver.max_infos = max_infos
        self._clouds.clear()
        self._slicers.clear()

    def check(self, info: Any, extrinsics: np.ndarray[Any, Any] | None = None) -> None:
        """Build the PointCloud2 converter and the slice converter for ``info`` (a probe or the
        sensor's): the library validates every option.

        Raises:
            LidarScanError: an option the converters refuse (the reason names it).
        """
        self._make_cloud(info)
        if self.slices:
            self._make_slicer(info, self.slices, extrinsics,
                              self.slice_options.get("intensity_channel"))

    def warm(self, cloud: bool = True) -> dict[str, float]:
        """Compile or load every kernel this configuration will call
        (:func:`converters._kernels.warm_up`); call before reporting ready.

        Returns:
            task -> seconds.
        """
        from converters._kernels import warm_up

        tasks = ["cloud"] if cloud else []
        if self.slices:
            tasks.append("slices")
        return warm_up(tasks, slices={s.name: s.spec() for s in self.slices},
                       slice_options=self.slice_options, cloud_options=self.cloud_options)

    def prepare(self, info: Any, extrinsics: np.ndarray[Any, Any] | None = None, *,
                cloud: bool = True, intensity: bool = True) -> None:
        """Build the converters of a new LidarInfo version and their per-pixel tables (both
        column orders when the sensor is staggered) by converting a synthetic scan of it, so
        that its first real scan does not pay for them. Counts nothing.

        Args:
            info: the LidarInfo.
            extrinsics: 4x4 ``target_frame <- sensor`` the scans will use (None: as
                :meth:`convert`); slices are not prepared when the target frame needs one.
            cloud: prepare the PointCloud2 converter.
            intensity: the scans will carry the configured intensity channel.
        """
        from converters._kernels.warm import probe_scan
        from lidarscan.geometry import info_key
        from lidarscan.stamps import to_ns

        key = info_key(info)
        channel = self.slice_options.get("intensity_channel", "intensity")
        stamp = to_ns(info.header.stamp)
        scans = [probe_scan(info, stamp_ns=stamp, intensity_dtype=np.uint16 if intensity
                            else None, intensity_name=channel or "intensity",
                            destaggered=d)
                 for d in ((False, True) if np.any(info.pixel_shift_by_row) else (False,))]
        if cloud:
            converter = self._cached(self._clouds, key, lambda: self._make_cloud(info))
            for scan in scans:
                converter.convert(scan)
        frame = self.target_frame or info.header.frame_id
        if not self.slices or (extrinsics is None and frame != info.header.frame_id):
            return
        matrix = None if extrinsics is None else np.asarray(extrinsics, np.float64)
        names = tuple(s.name for s in self.slices)
        wanted = channel if intensity and channel else None
        slicer = self._cached(
            self._slicers, (key, names, None if matrix is None else matrix.tobytes(), wanted),
            lambda: self._make_slicer(info, self.slices, matrix, wanted))
        for scan in scans:
            slicer.convert(scan)

    def _resolver_event(self, line: str) -> None:
        self._on_event(line)

    def _collect_drops(self) -> None:
        for drop in self.resolver.take_dropped():
            self.stats.scans_dropped += 1
            self.stats.count(drop.reason)

    # ---------------------------------------------------------------------------- input
    def add_info(self, message: Any) -> list[tuple[Any, Any]]:
        """Add a LidarInfo (CDR bytes or a message); returns the scans it releases.

        Raises:
            LidarScanError: undecodable or invalid info (counted as a bad message).
        """
        from lidarscan import decode_info

        self.stats.infos_received += 1
        try:
            info = decode_info(message) if isinstance(message, (bytes, bytearray, memoryview)) \
                else message
            ready = self.resolver.add_info(info)
            self.last_info = info
        except LidarScanError as err:
            self.stats.bad_messages += 1
            self.stats.count(f"bad LidarInfo: {err}")
            raise
        self._collect_drops()
        return ready

    def add_scan(self, message: Any) -> list[tuple[Any, Any]]:
        """Add a LidarScan (CDR bytes, decoded zero-copy, or a message); returns ready pairs.

        Raises:
            LidarScanError: undecodable scan (counted as a bad message).
        """
        from lidarscan import decode_scan

        self.stats.scans_received += 1
        try:
            scan = decode_scan(message) if isinstance(message, (bytes, bytearray, memoryview)) \
                else message
            ready = self.resolver.add_scan(scan)
        except LidarScanError as err:
            self.stats.bad_messages += 1
            self.stats.count(f"bad LidarScan: {err}")
            raise
        self._collect_drops()
        return ready

    def expire(self) -> None:
        """Drop scans that waited too long for their info (call periodically)."""
        self.resolver.expire()
        self._collect_drops()

    # --------------------------------------------------------------------- moving mount
    def track(self, frame: str) -> Any:
        """The :class:`converters.TransformTrack` ``target_frame <- frame`` of a moving mount
        (created, and filled from ``tf_samples``, on first use)."""
        from converters.shared.transforms import TransformTrack

        frame = str(frame).lstrip("/")
        found = self.tracks.get(frame)
        if found is None:
            if len(self.tracks) >= 8:                   # bounded: frames seen lately
                self.tracks.pop(next(iter(self.tracks)))
            found = self.tracks[frame] = TransformTrack(name=f"{self.target_frame} <- {frame}",
                                                        tolerance_ns=self.tf_tolerance_ns)
            self._fill(frame)
        return found

    def _fill(self, frame: str) -> None:
        """Extend a track with the chained /tf samples newer than it holds."""
        if self.tf_samples is None:
            return
        extend_track(self.tracks[frame], self.tf_samples, self.target_frame, frame, self._tick)

    def _tick(self, stamp: int) -> None:
        if self._data_clock is None or stamp > self._data_clock:
            self._data_clock = stamp

    def hold(self, pairs: Iterable[tuple[Any, Any]]) -> list[tuple[Any, Any]]:
        """Moving mount: queue linked pairs until the track covers each scan's sweep (every
        pixel's time, :meth:`lidarscan.geometry.Projector.pixel_times`, up to
        ``tf_tolerance_ns`` past the newest pose); returns the pairs now ready for their
        slices, oldest first (see :meth:`update_tracks`). Without ``moving`` or without
        slices: ``pairs``. Only the slices need the poses: convert the clouds at once
        (``convert(..., slices=[], count=False)``, as the node does), so that a dropped pair
        loses its slices only."""
        if not self.moving or not self.slices:
            return list(pairs)
        from lidarscan.geometry import make_projector
        from lidarscan.stamps import to_ns

        for scan, info in pairs:
            stamp = to_ns(scan.header.stamp)
            times = make_projector(info).pixel_times(scan)
            self.held.append((scan, info, stamp + int(times.min()), stamp + int(times.max())))
            self._tick(stamp)
            self.track(info.header.frame_id)
        return self._release()

    def update_tracks(self, cleared: bool = False) -> list[tuple[Any, Any]]:
        """New /tf arrived (``cleared``: its time jumped back and the buffer was cleared):
        extend the tracks, then return the held pairs now covered, oldest first. A held pair
        that can never be covered (its sweep starts before the track), that waited
        ``tf_wait_ns`` of data time past its last pixel, or that overflows ``max_pending``
        and is not covered is dropped: counted in ``stats.dropped_no_pose`` and in
        ``stats.reasons`` ("no pose"), and reported to ``on_event``."""
        if cleared:
            self._data_clock = None                  # a new timeline: wait afresh
        for frame, track in self.tracks.items():
            if cleared:
                track.clear()
            self._fill(frame)
        return self._release()

    def _release(self) -> list[tuple[Any, Any]]:
        out = []
        while self.held:
            scan, info, lo, hi = self.held[0]
            track = self.track(info.header.frame_id)
            span = track.span
            covered = span is not None and span[0] <= lo and hi <= span[1] + track.tolerance_ns
            never = span is not None and lo < span[0]
            waited = self._data_clock is not None and self._data_clock - hi > self.tf_wait_ns
            full = len(self.held) > max(self.resolver.max_pending, 1)
            if not (covered or never or waited or full):
                break
            self.held.popleft()
            if covered:
                out.append((scan, info))
                continue
            why = "its sweep starts before the oldest pose" if never else \
                "held too long" if waited else "too many scans held"
            self.stats.dropped_no_pose += 1
            self.stats.count("no pose: /tf does not cover the sweep")
            self._on_event(f"moving mount: slices of scan {lo} dropped: /tf does not cover "
                           f"its sweep [{lo}, {hi}] ns ({track.name}: poses "
                           f"{'none' if span is None else list(span)}; {why}; tf_wait "
                           f"{self.tf_wait_ns / 1e9:g} s)")
        return out

    # -------------------------------------------------------------------------- convert
    def convert(self, scan: Any, info: Any, *, cloud: bool = True,
                slices: Iterable[str] | None = None,
                extrinsics: np.ndarray[Any, Any] | None = None,
                count: bool = True) -> tuple[Any, dict[str, Any]]:
        """Convert one linked pair.

        Args:
            scan, info: a pair released by :meth:`add_scan` / :meth:`add_info`.
            cloud: produce the PointCloud2.
            slices: names of the slices to produce (default all).
            extrinsics: 4x4 ``target_frame <- sensor`` for the slices, or a moving mount's
                :class:`converters.TransformTrack` / callable ``stamp_ns -> 4x4`` (looked up
                at every pixel's time, e.g. :meth:`track`); None: the slices are in the info's
                frame (only allowed when ``target_frame`` is "" or that frame).
            count: count the pair in ``stats.scans_converted`` (False: a moving mount's
                cloud converted at arrival, its slices later count it).

        Returns:
            (PointCloud2 or None, {slice name: LaserScan}).

        Raises:
            LidarScanError: the converters refused the pair (a moving mount's pose missing at
                a pixel's time: :class:`converters.shared.transforms.TransformLookupError`).
        """
        from lidarscan import channel_names
        from lidarscan.geometry import info_key

        key = info_key(info)
        out_cloud = None
        if cloud:
            converter = self._cached(self._clouds, key, lambda: self._make_cloud(info))
            out_cloud = converter.convert(scan)
        wanted = [s for s in self.slices if slices is None or s.name in set(slices)]
        out_slices: dict[str, Any] = {}
        if wanted:
            if callable(extrinsics):            # a moving mount: keyed by the track itself
                matrix, mount = extrinsics, extrinsics
            else:
                matrix = None if extrinsics is None else np.asarray(extrinsics, np.float64)
                mount = None if matrix is None else matrix.tobytes()
            names = tuple(s.name for s in wanted)
            intensity = self.slice_options.get("intensity_channel", "intensity")
            if intensity and intensity not in channel_names(scan):
                intensity = None  # e.g. a range-only scan: empty intensities, not an error
            slicer = self._cached(self._slicers, (key, names, mount, intensity),
                                  lambda: self._make_slicer(info, wanted, matrix, intensity))
            out_slices = dict(slicer.convert(scan))
        self.stats.scans_converted += count
        return out_cloud, out_slices

    @staticmethod
    def _cached(cache: OrderedDict[Any, Any], key: Any, build: Any, size: int = 4) -> Any:
        value = cache.get(key)
        if value is None:
            value = build()
            cache[key] = value
            while len(cache) > size:
                cache.popitem(last=False)
        else:
            cache.move_to_end(key)
        return value

    def _make_cloud(self, info: Any) -> Any:
        from converters.pointcloud2.converter import PointCloud2Converter

        return PointCloud2Converter(info, **self.cloud_options)

    def _make_slicer(self, info: Any, specs: Sequence[SliceConfig], extrinsics: Any,
                     intensity: str | None) -> Any:
        from converters.slices.converter import SliceConverter

        frame = self.target_frame or info.header.frame_id
        if extrinsics is None and frame != info.header.frame_id:
            raise ConfigError("extrinsics", None,
                              f"the pose of '{info.header.frame_id}' in '{frame}'")
        return SliceConverter(info, {s.name: s.spec() for s in specs},
                              extrinsics=extrinsics,
                              frame_id=frame if extrinsics is not None else None,
                              **{**self.slice_options, "intensity_channel": intensity})


# ------------------------------------------------------------------------------ parameters
