"""Warm-up: compile (or load from numba's on-disk cache) every kernel specialisation a converter
will call, and load the C kernels, before the first message.

numba compiles a kernel at its first call for the argument types of that call, and caches the
machine code on disk (``__pycache__`` next to the source, or ``NUMBA_CACHE_DIR``). Without a
warm-up, a node's first scan pays the compilation (seconds) or the cache load (a large part of
a second). The per-scan arrays enter the kernels through
:func:`converters._kernels.slices_numba.frozen_f32`, so each kernel has exactly one
specialisation whatever the scan's channel dtypes and writeability; which kernels run
depends on the configuration and the geometry:

=====================  ==============================================================
kernel                 runs when
=====================  ==============================================================
transform rays         a moving mount (then the general kernel)
track rays             a moving mount on a track, pixel times varying along a column
row-ordered            one grid, full circle at the sensor's column resolution, upright
                       mount (the C kernel instead where its AVX-512 path runs)
bin-ordered            one grid and shared range limits, any other mount
general (large)        several grids or range limits, >= 32768 rays
general (small)        the same below 32768 rays, and every merger input
mask dtype             uint8 bit masks up to 8 slices, uint64 above
=====================  ==============================================================

so :func:`warm` converts small synthetic scans through the converters themselves, with the
caller's slice configuration, on three geometries: an upright sensor of 32 x 1024 rays, the
same tilted, and a small one of 8 x 64 (and a moving mount's paths when ``moving``). A kernel a
configuration cannot reach is not compiled. Nothing here is needed for correctness; it only
moves the cost to start-up.

No compiler on a node's start (:func:`prepare`): a node first loads its kernels from numba's
cache only (``compile=False``: a kernel that would be compiled raises :class:`NotCached`
instead). When one is missing (a plain ``pip install``, a new CPU, a cleared cache) the node
runs ``backend="c"`` (the C kernels built at install where they apply, numpy elsewhere:
nothing compiles) and fills the cache for its configuration in a background process
(``lidarscan-warmup --config JSON``), so its next start runs numba; it says which backend runs
in its log and its ``startup`` diagnostics (:func:`describe`).

Where the cache lives: numba's, ``__pycache__`` next to the kernels' sources, or its user-wide
cache directory when the install is read-only, or ``NUMBA_CACHE_DIR``. ``lidarscan-warmup``
(``python -m converters.warmup``; run it once after ``pip install``, as ``make install`` does)
fills it for every specialisation the library has (both mask dtypes, every path), or with
``--config JSON`` (:func:`prepare`'s keyword arguments) for one configuration.
"""

from __future__ import annotations

import contextlib
import dataclasses
import importlib.util
import json
import math
import os
import subprocess
import sys
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from lidarscan._backends import numba_enabled

__all__ = ["TASKS", "NotCached", "Prepared", "describe", "prepare", "probe_cloud", "probe_info",
           "probe_scan", "specialisations", "warm"]

#: What :func:`warm` can prepare.
TASKS = ("cloud", "slices", "merger", "codec")

#: (height, width, tilt about y in radians) of the synthetic sensors: >= 32768 rays upright,
#: the same tilted, and a small one (the general kernel's one-call path).
_GEOMETRIES = ((32, 1024, 0.0), (32, 1024, 0.3), (8, 64, 0.0))


def probe_info(height: int = 32, width: int = 1024, *, stamp_ns: int = 1,
               frame_id: str = "warm") -> Any:
    """A synthetic LidarInfo dataclass: ``height`` beams from +15 to -15 degrees, ``width``
    columns over a full clockwise turn, 0.1 to 120 m, millimetre integer ranges."""
    from lidarscan import make_info

    return make_info(stamp_ns=stamp_ns, frame_id=frame_id,
                     vertical_angles=np.radians(np.linspace(15.0, -15.0, height)),
                     horizontal_angles=2 * np.pi * (1 - np.arange(width) / width),
                     range_min=0.1, range_max=120.0, range_multiplier=0.001,
                     column_time_increment=100_000_000 // width, as_dataclass=True)


def probe_scan(info: Any, *, stamp_ns: int = 2, range_dtype: Any = np.float32,
               intensity_dtype: Any = np.uint16, intensity_name: str = "intensity",
               destaggered: bool = False, seed: int = 0) -> Any:
    """A LidarScan dataclass of ``info`` decoded from CDR bytes (read-only views, as a node
    receives it): ranges 0.05 to 60 m with no-return (+Inf), too-close (-Inf) and invalid
    (NaN) pixels so that every kernel pass runs; ``range_dtype`` float32 (metres) or an
    integer type (millimetres, 0 = no return); an intensity channel ``intensity_name`` of
    ``intensity_dtype`` (None: a range-only scan); ``destaggered``: its ``is_destaggered``."""
    import lidarscan

    height, width = int(info.height), int(info.width)
    rng = np.random.default_rng(seed)
    metres = rng.uniform(0.05, 60.0, (height, width)).astype(np.float32)
    metres.reshape(-1)[::7] = np.inf
    if np.dtype(range_dtype).kind == "f":
        metres.reshape(-1)[3::11] = np.nan
        metres.reshape(-1)[5::13] = -np.inf
        ranges: np.ndarray[Any, Any] = metres.astype(range_dtype)
    else:
        ranges = np.where(np.isfinite(metres), np.round(metres * 1000.0), 0).astype(range_dtype)
    channels = {"range": ranges}
    if intensity_dtype is not None:
        channels[intensity_name] = rng.integers(0, 100, (height, width)).astype(intensity_dtype)
    scan = lidarscan.make_scan(info, channels, stamp_ns=stamp_ns, is_destaggered=destaggered,
                               as_dataclass=True)
    return lidarscan.decode_scan(lidarscan.encode(scan))


def probe_cloud(frame_id: str = "warm") -> Any:
    """A synthetic unorganized PointCloud2 (x, y, z float32 + intensity, as drivers publish
    them) of :func:`probe_scan`'s 32 x 1024 sensor: what warms the kernels of
    :class:`converters.slices.cloud.CloudSliceConverter` (its C kernel loads at the first
    call; the per-layout validation is kept per field layout, so a cloud of another layout
    pays only that check)."""
    from converters.pointcloud2.converter import to_pointcloud2

    info = probe_info(32, 1024, frame_id=frame_id)
    return to_pointcloud2(probe_scan(info), info, fields=("x", "y", "z", "intensity"),
                          organized=False)


def _tilt(angle: float) -> np.ndarray[Any, Any]:
    """4x4 pose: rotated by ``angle`` about y, 0.4 m up."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s, 0.0], [0.0, 1.0, 0.0, 0.0], [-s, 0.0, c, 0.4],
                     [0.0, 0.0, 0.0, 1.0]])


class NotCached(RuntimeError):
    """A warm-up with ``compile=False`` reached a numba kernel that its cache does not hold
    for this CPU and these argument types (numba would compile it)."""


@contextlib.contextmanager
def _cache_only() -> Any:
    """Within: a numba compilation raises :class:`NotCached` (a load from the cache does not
    compile). Without numba: nothing to refuse."""
    try:
        from numba.core import event
    except ImportError:
        yield
        return

    class Refuse(event.Listener):  # type: ignore[misc]
        def on_start(self, ev: Any) -> None:
            fn = getattr(ev.data.get("dispatcher"), "py_func", None)
            raise NotCached(f"numba's cache has no {getattr(fn, '__name__', 'kernel')} for "
                            "this CPU and these argument types")

        def on_end(self, ev: Any) -> None:
            pass

    with event.install_listener("numba:compile", Refuse()):
        yield


def _warm_slices(slices: Mapping[str, Any] | None, options: Mapping[str, Any],
                 moving: bool = True) -> None:
    from converters.slices.converter import SliceConverter

    specs = dict(slices) if slices else {"warm": {"min_height": -0.5, "max_height": 0.5}}
    opts = {k: v for k, v in options.items() if k not in ("extrinsics", "frame_id")}
    for height, width, tilt in _GEOMETRIES:
        info = probe_info(height, width)
        converter = SliceConverter(info, specs, extrinsics=_tilt(tilt), frame_id="warm_target",
                                   **opts)
        converter.convert(probe_scan(info))
    if not moving:
        return
    # a moving mount (per-scan rays: the transform kernel, then the general kernel's passes)
    from converters.shared.transforms import TransformTrack

    info = probe_info(*_GEOMETRIES[0][:2])
    track = TransformTrack()
    track.add(0, _tilt(0.0))
    track.add(1_000_000_000, _tilt(0.3))
    SliceConverter(info, specs, extrinsics=track, frame_id="warm_target", **opts).convert(
        probe_scan(info))
    # per-beam time offsets: a pose per pixel (the track kernel, then the general kernel)
    info = dataclasses.replace(info, beam_time_offsets=np.arange(info.height, dtype=np.int64))
    SliceConverter(info, specs, extrinsics=track, frame_id="warm_target", **opts).convert(
        probe_scan(info))


def _warm_cloud(options: Mapping[str, Any]) -> None:
    from converters.pointcloud2.converter import PointCloud2Converter

    info = probe_info(8, 64)
    PointCloud2Converter(info, **options).convert(probe_scan(info))


def _warm_merger(backend: str = "auto") -> None:
    from converters.merger import LaserScanMerger, MergerInput
    from converters.slices.converter import SliceConverter

    info = probe_info(8, 64)
    laser = SliceConverter(info, {"s": {"min_height": -100.0, "max_height": 100.0}},
                           backend="numpy").convert(probe_scan(info))["s"]
    merger = LaserScanMerger({"a": MergerInput(),
                              "b": MergerInput(extrinsics=_tilt(0.0), frame_id="warm")},
                             frame_id="warm", backend=backend)
    merger.merge({"a": laser, "b": laser})


def _warm_codec() -> None:
    from converters._kernels import select
    from lidarscan import codec

    coder = select("codec").numba
    if coder is not None:
        scan = probe_scan(probe_info(8, 64))
        codec.decompress_scan(codec.compress_scan(scan, coder=coder), coder=coder)
        # format version 3's XPREDICT (converters._kernels.codec3) on Ouster's channel types:
        # reflectivity uint8 from intensity uint16 and range float32 m or uint32 mm
        import lidarscan
        for range_dtype in (np.float32, np.uint32):
            probe = probe_scan(probe_info(8, 64), range_dtype=range_dtype)
            chans = {name: lidarscan.channel(probe, name) for name in ("range", "intensity")}
            chans["reflectivity"] = (chans["intensity"] // 4).astype(np.uint8)
            scan = lidarscan.make_scan(probe_info(8, 64), chans, 2, as_dataclass=True)
            codec.decompress_scan(codec.compress_scan(scan, coder=coder, version=3),
                                  coder=coder)


def warm(tasks: Iterable[str] = TASKS, *, slices: Mapping[str, Any] | None = None,
         slice_options: Mapping[str, Any] | None = None,
         cloud_options: Mapping[str, Any] | None = None, moving: bool = True,
         compile: bool = True, seconds: dict[str, float] | None = None) -> dict[str, float]:
    """Prepare the compiled kernels of ``tasks`` (a subset of :data:`TASKS`).

    Args:
        tasks: "cloud" (LidarScan -> PointCloud2: the C kernel), "slices" (height slices: the
            numba kernels the configuration can reach), "merger" (the merger's kernels),
            "codec" (the residual coder of :mod:`lidarscan.codec`).
        slices: the slice configuration a node will use (name -> SliceSpec or dict), as
            :class:`converters.slices.converter.SliceConverter` takes it; None = one slice.
        slice_options, cloud_options: keyword options of the slice / PointCloud2 converters
            (e.g. ``intensity_channel``, ``backend``; ``preset``, ``fields``); the merger
            takes ``slice_options["backend"]``.
        moving: also the kernels of a moving mount (False: a fixed mount's only).
        compile: False: load numba's kernels from its cache only (nothing is compiled).
        seconds: the dict to fill (the tasks done so far stay in it when one raises).

    Returns:
        task -> seconds it took (milliseconds when the cache is warm; seconds when numba
        compiles).

    Raises:
        ConfigError: an unknown task, or options the converters refuse.
        NotCached: ``compile=False`` and a kernel is not in numba's cache.
    """
    from lidarscan.errors import ConfigError

    backend = (slice_options or {}).get("backend", "auto")
    steps: dict[str, Callable[[], None]] = {
        "cloud": lambda: _warm_cloud(cloud_options or {}),
        "slices": lambda: _warm_slices(slices, slice_options or {}, moving),
        "merger": lambda: _warm_merger(backend), "codec": _warm_codec}
    chosen = list(tasks)
    for task in chosen:
        if task not in steps:
            raise ConfigError("warm task", task, f"one of {', '.join(TASKS)}")
    seconds = {} if seconds is None else seconds
    with contextlib.nullcontext() if compile else _cache_only():
        for task in chosen:
            start = time.perf_counter()
            steps[task]()
            seconds[task] = time.perf_counter() - start
    return seconds


def describe(tasks: Iterable[str], backend: str = "auto") -> dict[str, str]:
    """Which code runs each of ``tasks`` ("cloud", "slices", "merger", "cloud_slices") with
    ``backend`` (:func:`converters._kernels.select`), for a node's log and diagnostics: e.g.
    ``{"cloud": "C", "slices": "C AVX-512 (row-ordered), numba (other cases)"}``."""
    from converters._kernels import select

    out = {}
    for task in tasks:
        if task == "cloud":
            out[task] = "C" if select("cloud").c is not None else "numpy"
            continue
        chosen = select(task, backend=backend)
        parts = []
        if chosen.c and task == "slices":
            from converters._kernels import slices as c_slices

            vector = "AVX-512" if c_slices.vectorised() else "scalar"
            parts.append(f"C {vector} (row-ordered)")
        elif chosen.c:
            parts.append("C")
        if chosen.numba is not None:
            parts.append("numba")
        elif not parts or task == "slices":
            parts.append("numpy")
        if len(parts) == 2:
            parts[1] += " (other cases)"
        out[task] = ", ".join(parts)
    return out


@dataclasses.dataclass
class Prepared:
    """What :func:`prepare` did.

    Attributes:
        backend: the ``backend`` the node's converters must use ("auto", or "c" while numba's
            cache lacks their kernels, or the caller's).
        seconds: task -> seconds of the warm-up.
        runs: :func:`describe` of ``backend``.
        missing: why numba is not used (its cache lacks a kernel), or "".
        filler: the background process filling the cache (None: none started).
    """

    backend: str
    seconds: dict[str, float]
    runs: dict[str, str]
    missing: str = ""
    filler: Any = None

    def summary(self) -> str:
        """One line for the log: the backends, and the cache fill when one started."""
        line = "kernels: " + "; ".join(f"{k} {v}" for k, v in self.runs.items())
        if self.missing:
            line += (f" (numba not used: {self.missing}; compiling this configuration's "
                     "kernels into the cache in the background"
                     + (f", pid {self.filler.pid}" if self.filler is not None else "")
                     + ": the next start uses them; `lidarscan-warmup` after install avoids "
                     "this)")
        return line


def prepare(tasks: Sequence[str], *, slices: Mapping[str, Any] | None = None,
            slice_options: Mapping[str, Any] | None = None,
            cloud_options: Mapping[str, Any] | None = None, moving: bool = True,
            background: bool = True) -> Prepared:
    """A node's warm-up with no compiler on its critical path: load every kernel of this
    configuration (:func:`warm` arguments) from numba's cache; when a kernel is not cached,
    use ``backend="c"`` instead (C kernels where they apply, numpy elsewhere: milliseconds;
    the codec's kernels, which no node uses, are then left out) and, with ``background``, start a low-priority process that compiles this configuration's
    kernels into the cache for the next start. A ``backend`` other than "auto" in
    ``slice_options`` is kept (``"numba"`` compiles here: the caller asked for it).

    Raises:
        ConfigError: options the converters refuse.
    """
    options = dict(slice_options or {})
    backend = options.get("backend", "auto")
    config = {"tasks": list(tasks), "slices": _plain(slices), "slice_options": dict(options),
              "cloud_options": dict(cloud_options or {}), "moving": moving}
    missing, filler = "", None
    done: dict[str, float] = {}
    try:
        seconds = warm(tasks, slices=slices, slice_options=options,
                       cloud_options=cloud_options, moving=moving,
                       compile=backend != "auto", seconds=done)
    except NotCached as err:
        missing, backend = str(err), "c"
        # the C kernels load (ms); numpy, where they do not apply, needs no warm-up; the
        # cloud's kernel (C only) is kept when it was warmed before the miss
        from converters._kernels import select

        seconds = {t: s for t, s in done.items() if t == "cloud"}
        if "cloud" in tasks and "cloud" not in seconds:
            seconds.update(warm(["cloud"], cloud_options=cloud_options))
        for task in tasks:
            if task in ("slices", "merger"):
                start = time.perf_counter()
                select(task, backend="c")
                seconds[task] = time.perf_counter() - start
        if background:
            filler = _fill_in_background(config)
    return Prepared(backend, seconds, describe([t for t in tasks if t != "codec"], backend),
                    missing, filler)


def _plain(slices: Mapping[str, Any] | None) -> dict[str, Any] | None:
    """A slice configuration as JSON-able dicts (SliceSpec dataclasses become dicts)."""
    if slices is None:
        return None
    return {name: dataclasses.asdict(spec) if dataclasses.is_dataclass(spec) else dict(spec)
            for name, spec in slices.items()}


#: config JSON -> the background fill this process started for it (one at a time)
_FILLERS: dict[str, Any] = {}


def _fill_in_background(config: Mapping[str, Any]) -> Any:
    """Start ``python -m converters.warmup --config JSON`` at low priority, detached (its own
    session: a Ctrl-C to the node does not stop it), output discarded; the one already running
    for this configuration if any (and across processes, :func:`main` runs one per
    configuration and cache at a time); None if it cannot start."""
    text = json.dumps(config, sort_keys=True, default=str)
    running = _FILLERS.get(text)
    if running is not None and running.poll() is None:
        return running
    try:
        _FILLERS[text] = subprocess.Popen(
            [sys.executable, "-m", "converters.warmup", "--nice", "--config", text],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            start_new_session=True)
    except OSError:
        return None
    return _FILLERS[text]


@contextlib.contextmanager
def _only_one(config_text: str) -> Any:
    """Yields True in the one process filling this configuration into this cache (an
    exclusive lock in the temporary directory), False in any other at the same time."""
    try:
        import fcntl
    except ImportError:                       # not POSIX: no lock
        yield True
        return
    import hashlib
    import tempfile

    key = hashlib.sha1((config_text + os.environ.get("NUMBA_CACHE_DIR", "") + sys.executable)
                       .encode()).hexdigest()[:16]
    with open(os.path.join(tempfile.gettempdir(), f"lidarscan-warmup-{key}.lock"), "w") as fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            yield False
            return
        yield True


def specialisations() -> dict[str, int]:
    """Compiled specialisations of each numba slice / merger kernel loaded in this process
    (empty without numba): what a warm-up made ready, and what a later call must not add."""
    from converters._kernels import slices_numba

    compiled = slices_numba.kernels()
    if compiled is None:
        return {}
    return {name: len(d.signatures) for name, d in compiled.dispatchers().items()}


def main(argv: Sequence[str] | None = None) -> int:
    """``lidarscan-warmup`` (``python -m converters.warmup``): fill numba's cache for every
    specialisation; ``--config JSON``: for one configuration (:func:`prepare`'s keywords);
    ``--nice``: at low priority (a node's background fill)."""
    args = list(sys.argv[1:] if argv is None else argv)
    if "--nice" in args:
        args.remove("--nice")
        with contextlib.suppress(OSError):
            os.nice(10)
    if args[:1] == ["--config"] and len(args) == 2:
        config = json.loads(args[1])
        with _only_one(json.dumps(config, sort_keys=True)) as mine:
            if not mine:
                print("another process is filling the cache for this configuration")
                return 0
            took = warm(config.pop("tasks"), **config)
        print("kernels ready: " + ", ".join(f"{k} {v:.2f} s" for k, v in took.items()))
        return 0
    if args:
        print("usage: lidarscan-warmup [--nice] [--config JSON]", file=sys.stderr)
        return 2
    one = {"a": {"min_height": -0.5, "max_height": 0.5}}
    nine = {f"s{i}": {"min_height": -0.5 + 0.1 * i, "max_height": 0.5} for i in range(9)}
    two_grids = {"a": {"min_height": -0.5, "max_height": 0.5},
                 "b": {"min_height": 0.0, "max_height": 1.0, "angle_increment": 0.01}}
    nine_grids = {**nine, "b": two_grids["b"]}
    total = time.perf_counter()
    if importlib.util.find_spec("numba") is not None and numba_enabled():
        print("compiling the numba kernels once into numba's on-disk cache (about a minute "
              "on a new machine, a few seconds when cached): later runs and nodes start "
              "without compiling", flush=True)
    else:
        print("loading the C kernels (numba not installed or disabled: nothing to compile)",
              flush=True)
    for label, config in (("1 slice", one), ("9 slices", nine), ("2 grids", two_grids),
                          ("10 slices, 2 grids", nine_grids)):
        took = warm(("slices",), slices=config)
        print(f"  slices ({label}): {took['slices']:.1f} s", flush=True)
    for task, took in warm(("cloud", "merger", "codec")).items():
        print(f"  {task}: {took:.1f} s", flush=True)
    compiled = specialisations()
    print(f"kernels ready in {time.perf_counter() - total:.1f} s: "
          + (", ".join(f"{k} {v}" for k, v in compiled.items()) if compiled else
             "numba not installed or disabled (nothing to compile)"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
