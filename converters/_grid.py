"""The angle grid, ray binning and min-fusion shared by LaserScan slices and the merger.

Everything a user could argue about is decided here, once:

**Grid.** A LaserScan grid is ``angle_min`` + ``k * inc`` for ``k = 0 .. N-1`` (float64 internally).
``inc`` must be > 0 (CCW). A window ``[angle_min, angle_max]`` is a *full circle* when its bins
would cover the circle, i.e. when ``round(span / inc) + 1 >= round(2*pi / inc)`` (so both
``angle_max = angle_min + 2*pi`` and the published header of a full circle,
``angle_max = angle_min + (N-1)*inc``, configure a full circle). A full circle has
``N = round(2*pi / inc)`` bins and its increment is snapped to ``2*pi / N`` so the grid closes
(half-open ``[angle_min, angle_min + N*inc)``). A sector has ``N = round(span / inc) + 1``. Spans
above ``2*pi`` (beyond 1e-6 rad of float32 slack) and ``angle_min > angle_max`` are errors. The
published ``angle_max`` is always ``angle_min + (N-1)*inc``; header fields are float32.

**Binning** (float64). ``t = (theta - angle_min) / inc`` and ``k = ceil(t - 1/2)``: the nearest
bin, an exact half-bin going to the bin of *smaller angle* (the lower index; at the seam of a full
circle that is ``N-1``). Full circle: ``k mod N`` (so +pi and -pi share a bin). Sector: ``theta`` is
first wrapped into ``[angle_min - inc/2, angle_min - inc/2 + 2*pi)``; ``k`` outside ``0..N-1`` is
discarded. Bin ``k`` thus covers ``(angle_min + (k - 1/2) inc, angle_min + (k + 1/2) inc]``.

**Rays.** Every input element (a LidarScan pixel, a LaserScan ray) is a ray ``p(r) = r*D + O`` in
the output frame (D, O: float32 for slices, float64 for merger inputs; all arithmetic in float64;
D need not be unit length). For a range ``r``:

* finite ``r > 0``: the point ``p``. It takes part iff ``min_z <= z <= max_z`` (inclusive). Its
  planar range is ``rho = sqrt(x*x + y*y)`` and its bin that of ``atan2(y, x)``. Then
  ``range_min <= rho <= range_max`` (inclusive) gives a *finite* value ``rho``; ``rho < range_min``
  gives ``-Inf`` (too close); ``rho > range_max`` gives ``+Inf`` (nothing within range).
  A point outside the band contributes nothing.
* ``+Inf`` (no return): ``+Inf`` in the bin of the ray's far-field direction ``atan2(Dy, Dx)`` iff
  the ray crosses the band at some planar range inside ``[range_min, range_max]`` (free space was
  observed in the band), else nothing.
* ``NaN``, ``0`` or negative (invalid): ``NaN`` under the same condition as ``+Inf``.
* ``-Inf`` (too close): ``-Inf`` in the far-field bin iff the ray is inside the band somewhere in
  ``0 <= r <= near`` (``near`` = the sensor's minimum range).

**Fusion** per bin: a finite value beats ``-Inf``, which beats ``+Inf``, which beats ``NaN``, which
beats an empty bin (``fill``). Among finite values the smallest float32 ``rho`` wins and carries
its intensity; equal values go to the smaller *tie key* (the first input / first pixel). All of it
is one integer minimum per bin over ``code << 32 | key``, where ``code`` is the float32 bit
pattern of ``rho`` (monotone for non-negative floats) or one of the codes above it for -Inf, +Inf,
NaN. Fusing a scan with itself is therefore idempotent.

**Output values.** ``+Inf`` (a class or the default fill) becomes ``range_max + inf_epsilon`` when
``use_inf`` is false; ``fill`` (default: the same as ``+Inf``) is what an empty bin gets, e.g.
``float('nan')`` to tell "no data" from "free". Empty bins get intensity 0.

**Far field** (slices): the bin of a point depends on ``r`` when ``O`` has a planar component. Along
a ray the point's azimuth moves monotonically towards the far-field azimuth, with offset
``delta(r) = atan2(c, r*|Dxy|^2 + Dxy.Oxy)``, ``c = Dx*Oy - Dy*Ox``. So each ray has a threshold
``r_thr`` (solved from ``delta(r_thr) = margin to the bin edge on that side`` minus 1e-9 rad) above
which its bin is the far-field bin, precomputed once. Only points with ``r < r_thr`` call atan2.
"""

from __future__ import annotations

import array
import functools
import math
import struct
from dataclasses import dataclass
from typing import Any

import numpy as np

from converters._rosmsg import bare_message
from lidarscan.errors import ConfigError

__all__ = [
    "CODE_NAN",
    "CODE_NEG_INF",
    "CODE_POS_INF",
    "EMPTY",
    "AngleGrid",
    "OutputOptions",
    "aligned_rows",
    "band_intervals_f32",
    "decode",
    "far_field",
    "make_laserscan",
    "numba_kernel",
    "point_codes",
    "qualify",
    "ray_interval",
    "reduce_min",
    "round_up_f32",
    "special_codes",
]

TWO_PI = 2.0 * math.pi
#: Codes of the non-finite classes, just above every finite non-negative float32 bit pattern.
CODE_NEG_INF = 0x7F800000
CODE_POS_INF = 0x7F800001
CODE_NAN = 0x7F800002
#: An empty bin in the reduction array.
EMPTY = np.iinfo(np.int64).max
_KEY_MASK = 0xFFFFFFFF
_SPAN_SLACK = 1e-6      # rad: float32 +-pi lie just outside +-pi
_EDGE_MARGIN = 1e-9     # rad kept from a bin edge by the far-field threshold
_MAX_BINS = 1 << 24


def _finite(name: str, value: Any) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError) as err:
        raise ConfigError(name, value, "a number") from err
    if not math.isfinite(out):
        raise ConfigError(name, value, "a finite number")
    return out


@dataclass(frozen=True)
class AngleGrid:
    """An output angle grid (see the module docstring for every convention).

    Attributes:
        angle_min: angle of bin 0, radians (float64, as configured).
        increment: bin spacing, radians, > 0 (snapped to 2*pi/size on a full circle).
        size: number of bins N >= 1.
        full_circle: whether bins wrap (angle_min + N*increment == angle_min + 2*pi).
    """

    angle_min: float
    increment: float
    size: int
    full_circle: bool

    @classmethod
    def create(cls, angle_min: float, angle_max: float, angle_increment: float) -> AngleGrid:
        """Grid for a window ``[angle_min, angle_max]`` at ``angle_increment`` (radians).

        Raises:
            ConfigError: non-finite values, ``angle_increment <= 0``, ``angle_min > angle_max``,
                a span above 2*pi, or more than 2**24 bins.
        """
        a = _finite("angle_min", angle_min)
        b = _finite("angle_max", angle_max)
        inc = _finite("angle_increment", angle_increment)
        if not inc > 0.0:
            raise ConfigError("angle_increment", angle_increment,
                              "> 0 (output grids run counter-clockwise)")
        if a > b:
            raise ConfigError("angle_max", angle_max,
                              f">= angle_min ({angle_min}); a window across +-pi is written "
                              "with angle_max = angle_min + span, e.g. 2.5 .. 3.8")
        span = b - a
        if span > TWO_PI + _SPAN_SLACK:
            raise ConfigError("angle_max - angle_min", span, "<= 2*pi")
        n_full = round(TWO_PI / inc)
        n_sector = round(span / inc) + 1
        if n_full >= 1 and n_sector >= n_full:
            size, inc, full = n_full, TWO_PI / n_full, True
        else:
            size, full = n_sector, False
        if size > _MAX_BINS:
            raise ConfigError("angle_increment", angle_increment,
                              f"a grid of at most {_MAX_BINS} bins (got {size})")
        return cls(a, inc, int(size), full)

    @property
    def angle_max(self) -> float:
        """Angle of the last bin: angle_min + (N-1)*increment (float64)."""
        return self.angle_min + (self.size - 1) * self.increment

    def angles(self) -> np.ndarray[Any, np.dtype[np.float64]]:
        """(N,) float64 centre angle of every bin."""
        out: np.ndarray[Any, np.dtype[np.float64]] = (
            self.angle_min + np.arange(self.size, dtype=np.float64) * self.increment)
        return out

    def locate(self, theta: np.ndarray[Any, Any]) -> tuple[np.ndarray[Any, Any],
                                                          np.ndarray[Any, Any]]:
        """Fractional bin position ``t`` and unwrapped nearest bin ``k = ceil(t - 1/2)``.

        Sectors wrap ``theta`` into ``[angle_min - inc/2, angle_min - inc/2 + 2*pi)`` first, so
        ``t`` lies in ``[-1/2, 2*pi/inc - 1/2)``. Both arrays are float64.
        """
        theta = np.asarray(theta, np.float64)
        d = theta - self.angle_min
        if not self.full_circle:
            half = 0.5 * self.increment
            d = d - TWO_PI * np.floor((d + half) / TWO_PI)
        t = d / self.increment
        return t, np.ceil(t - 0.5)

    def bins(self, theta: np.ndarray[Any, Any]) -> np.ndarray[Any, np.dtype[np.int64]]:
        """(n,) int64 bin of each finite angle (radians); -1 outside a sector."""
        _, k = self.locate(theta)
        ki = k.astype(np.int64)
        if self.full_circle:
            return ki % self.size
        return np.where((ki >= 0) & (ki < self.size), ki, -1)

    def header(self) -> tuple[float, float, float]:
        """(angle_min, angle_max, angle_increment) as published (values of float32)."""
        f = np.float32
        return (float(f(self.angle_min)), float(f(self.angle_max)), float(f(self.increment)))


# --------------------------------------------------------------------------- static ray geometry

def ray_interval(dz: np.ndarray[Any, Any], oz: np.ndarray[Any, Any], min_z: Any, max_z: Any
                 ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
    """Range interval ``[lo, hi]`` (``lo >= 0``) where ``r*dz + oz`` lies in the band.

    Empty intervals have ``lo > hi``. Arrays broadcast; float64 out. A horizontal ray (``dz == 0``)
    is in the band for every ``r`` or for none.
    """
    dz = np.asarray(dz, np.float64)
    oz = np.asarray(oz, np.float64)
    zmin = np.asarray(min_z, np.float64)
    zmax = np.asarray(max_z, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        a = (zmin - oz) / dz
        b = (zmax - oz) / dz
    lo = np.where(dz > 0, a, b)
    hi = np.where(dz > 0, b, a)
    inside = (oz >= zmin) & (oz <= zmax)
    flat = dz == 0
    lo = np.where(flat, np.where(inside, 0.0, np.inf), lo)
    hi = np.where(flat, np.where(inside, np.inf, -np.inf), hi)
    lo = np.maximum(lo, 0.0)
    return lo, hi


def _rho(dx: Any, dy: Any, ox: Any, oy: Any, r: Any) -> np.ndarray[Any, Any]:
    with np.errstate(invalid="ignore", over="ignore"):
        x = r * dx + ox
        y = r * dy + oy
        out = np.sqrt(x * x + y * y)
    planar = (dx != 0) | (dy != 0)
    at_inf = np.isinf(r)
    return np.where(at_inf, np.where(planar, np.inf, np.sqrt(ox * ox + oy * oy)), out)


def qualify(d: np.ndarray[Any, Any], o: np.ndarray[Any, Any], min_z: Any, max_z: Any,
            range_min: Any, range_max: Any, near: Any
            ) -> tuple[np.ndarray[Any, np.dtype[np.bool_]], np.ndarray[Any, np.dtype[np.bool_]]]:
    """Which rays may report ``+Inf``/``NaN`` (``q_far``) and ``-Inf`` (``q_near``) in the band.

    Args:
        d, o: (n, 3) float64 ray directions and origins in the output frame.
        min_z, max_z: band (scalars or (n,)).
        range_min, range_max: planar limits (scalars or (n,)).
        near: (scalar or (n,)) the sensor's minimum range along the ray.

    Returns:
        q_far: the ray is in the band at some planar range inside [range_min, range_max].
        q_near: the ray is in the band somewhere in 0 <= r <= near.
    """
    dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
    ox, oy, oz = o[:, 0], o[:, 1], o[:, 2]
    lo, hi = ray_interval(dz, oz, min_z, max_z)
    nonempty = lo <= hi
    a2 = dx * dx + dy * dy
    with np.errstate(divide="ignore", invalid="ignore"):
        r_star = np.where(a2 > 0, -(dx * ox + dy * oy) / a2, 0.0)
    r_star = np.clip(r_star, lo, np.maximum(hi, lo))
    rho_lo = _rho(dx, dy, ox, oy, lo)
    rho_hi = _rho(dx, dy, ox, oy, hi)
    rho_min = _rho(dx, dy, ox, oy, r_star)
    rho_max = np.maximum(rho_lo, rho_hi)
    q_far = nonempty & (rho_min <= range_max) & (rho_max >= range_min)
    q_near = nonempty & (lo <= np.asarray(near, np.float64))
    return q_far, q_near


def far_field(d: np.ndarray[Any, Any], o: np.ndarray[Any, Any], grid: AngleGrid
              ) -> tuple[np.ndarray[Any, np.dtype[np.int64]], np.ndarray[Any, np.dtype[np.float64]]]:
    """Far-field bin of each ray and the range above which a point's bin equals it.

    Args:
        d, o: (n, 3) float64 ray directions and origins in the output frame.
        grid: the output grid.

    Returns:
        bin_far: (n,) int64 bin of ``atan2(Dy, Dx)``; -1 outside a sector or for a vertical ray.
        r_thr: (n,) float64; for ``r >= r_thr`` the exact bin of ``r*D + O`` is ``bin_far``
            (also when it is -1: the point stays outside the sector). ``inf`` = always exact.
    """
    dx, dy = d[:, 0], d[:, 1]
    ox, oy = o[:, 0], o[:, 1]
    a2 = dx * dx + dy * dy
    planar = a2 > 0
    theta = np.arctan2(dy, dx)
    t, k = grid.locate(theta)
    if grid.full_circle:
        bin_far = k.astype(np.int64) % grid.size
        e_lo, e_hi = k - 0.5, k + 0.5
    else:
        ki = k.astype(np.int64)
        inside = (ki >= 0) & (ki < grid.size)
        bin_far = np.where(inside, ki, -1)
        # outside the sector the "bin" is the gap between its last and its first bin
        e_lo = np.where(inside, k - 0.5, grid.size - 0.5)
        e_hi = np.where(inside, k + 0.5, TWO_PI / grid.increment - 0.5)
    bin_far = np.where(planar, bin_far, -1)
    cross = dx * oy - dy * ox
    dot = dx * ox + dy * oy
    psi = np.where(cross > 0, e_hi - t, t - e_lo) * grid.increment - _EDGE_MARGIN
    psi = np.minimum(psi, math.pi / 4)
    with np.errstate(divide="ignore", invalid="ignore"):
        r_thr = (np.abs(cross) / np.tan(np.maximum(psi, 1e-300)) - dot) / a2
        r_zero = -dot / a2
    # beyond 2*r_zero the point is at least |O.D|/|D| from the origin: rounding of x, y cannot
    # move its azimuth by the margin; before it the ray passes close to the origin.
    r_thr = np.where(psi > 0, np.maximum(np.where(cross == 0, 0.0, r_thr), 2.0 * r_zero), np.inf)
    r_thr = np.maximum(r_thr, 0.0) * (1.0 + 1e-9) + 1e-9
    r_thr = np.where(planar, r_thr, np.inf)
    return bin_far, r_thr


# ----------------------------------------------------------------------------- per-scan codes

def point_codes(r: np.ndarray[Any, Any], d: np.ndarray[Any, Any], o: np.ndarray[Any, Any],
                min_z: Any, max_z: Any, range_min: Any, range_max: Any, grid: AngleGrid,
                bin_far: np.ndarray[Any, Any] | None = None,
                r_thr: np.ndarray[Any, Any] | None = None
                ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any], np.ndarray[Any, Any]]:
    """Bin and code of finite points, exactly as the module docstring states.

    Args:
        r: (m,) float64 ranges, finite and > 0.
        d, o: (m, 3) float64 directions and origins of those rays.
        min_z, max_z, range_min, range_max: scalars or (m,) arrays.
        grid: output grid.
        bin_far, r_thr: (m,) far-field tables from :func:`far_field`, or None for atan2 on all.

    Returns:
        (sel, bins, codes): indices into ``r`` of the contributing points, their int64 bins and
        int64 codes.
    """
    x = r * d[:, 0] + o[:, 0]
    y = r * d[:, 1] + o[:, 1]
    z = r * d[:, 2] + o[:, 2]
    keep = (z >= min_z) & (z <= max_z)
    if bin_far is None or r_thr is None:
        bins = np.full(r.shape, -1, np.int64)
        exact = keep
    else:
        bins = bin_far.astype(np.int64, copy=True)
        exact = keep & (r < r_thr)
    if exact.any():
        bins[exact] = grid.bins(np.arctan2(y[exact], x[exact]))
    keep &= bins >= 0
    sel = np.flatnonzero(keep)
    xs, ys = x[sel], y[sel]
    rho = np.sqrt(xs * xs + ys * ys)
    rmin = range_min[sel] if np.ndim(range_min) else range_min
    rmax = range_max[sel] if np.ndim(range_max) else range_max
    codes = rho.astype(np.float32).view(np.int32).astype(np.int64)
    codes[rho < rmin] = CODE_NEG_INF
    codes[rho > rmax] = CODE_POS_INF
    return sel, bins[sel], codes


def special_codes(r: np.ndarray[Any, Any], q_far: np.ndarray[Any, Any],
                  q_near: np.ndarray[Any, Any]) -> np.ndarray[Any, np.dtype[np.int64]]:
    """Codes of non-point ranges (+Inf, -Inf, NaN, <= 0); -1 where the ray does not qualify.

    Args:
        r: (m,) ranges that are not finite-and-positive.
        q_far, q_near: (m,) bool qualifiers from :func:`qualify`.
    """
    codes = np.full(r.shape, -1, np.int64)
    pos = r == np.inf
    neg = r == -np.inf
    bad = ~(pos | neg)
    codes[pos & q_far] = CODE_POS_INF
    codes[neg & q_near] = CODE_NEG_INF
    codes[bad & q_far] = CODE_NAN
    return codes


def reduce_min(size: int, bins: np.ndarray[Any, Any], codes: np.ndarray[Any, Any],
               keys: np.ndarray[Any, Any]) -> np.ndarray[Any, np.dtype[np.int64]]:
    """(size,) int64: per bin the minimum of ``code << 32 | key`` (``EMPTY`` where none).

    ``keys`` must be unique non-negative ints < 2**32 ordered by priority (first input first).
    """
    best = np.full(size, EMPTY, np.int64)
    if bins.size:
        combined = (np.asarray(codes, np.int64) << 32) | np.asarray(keys, np.int64)
        np.minimum.at(best, np.asarray(bins, np.intp), combined)
    return best


@dataclass(frozen=True)
class OutputOptions:
    """How fused codes become published float32 values.

    Attributes:
        range_min, range_max: planar limits, metres (published as float32).
        use_inf: publish +Inf; if false, +Inf becomes ``range_max + inf_epsilon``.
        inf_epsilon: see ``use_inf``.
        fill: value of an empty bin; None = the value +Inf gets (p2l behaviour).
    """

    range_min: float = 0.0
    range_max: float = math.inf
    use_inf: bool = True
    inf_epsilon: float = 1.0
    fill: float | None = None

    @classmethod
    def create(cls, range_min: Any, range_max: Any, use_inf: bool, inf_epsilon: Any,
               fill: Any) -> OutputOptions:
        """Validated options.

        Raises:
            ConfigError: NaN or negative range_min, range_max < range_min, non-finite epsilon.
        """
        rmin = float(range_min)
        rmax = float(range_max)
        if math.isnan(rmin) or rmin < 0 or math.isinf(rmin):
            raise ConfigError("range_min", range_min, "a finite number >= 0")
        if math.isnan(rmax) or rmax < rmin:
            raise ConfigError("range_max", range_max, f">= range_min ({rmin}), may be inf")
        eps = _finite("inf_epsilon", inf_epsilon)
        fill_value = None if fill is None else float(fill)
        return cls(rmin, rmax, bool(use_inf), eps, fill_value)

    @property
    def inf_value(self) -> float:
        """What a +Inf class is published as."""
        return math.inf if self.use_inf else self.range_max + self.inf_epsilon

    @property
    def fill_value(self) -> float:
        """What an empty bin is published as."""
        return self.inf_value if self.fill is None else self.fill


def decode(best: np.ndarray[Any, Any], options: OutputOptions, kernels: Any = None
           ) -> tuple[np.ndarray[Any, np.dtype[np.float32]], np.ndarray[Any, np.dtype[np.int64]]]:
    """Published ranges and winner keys of a reduction array (``kernels``: the compiled
    kernels of :func:`numba_kernel` to use, or None for numpy).

    Returns:
        ranges: (N,) float32 metres (REP 117 values, fill in empty bins).
        winners: (N,) int64 tie key of the winning element, -1 for empty bins.
    """
    if kernels is not None:
        ranges = np.empty(best.shape[0], np.float32)
        winners = np.empty(best.shape[0], np.int64)
        kernels.decode(best, np.float32(options.inf_value), np.float32(options.fill_value),
                       ranges, winners)
        return ranges, winners
    empty = best == EMPTY
    code = best >> 32
    winners = np.where(empty, -1, best & _KEY_MASK)
    finite = code < CODE_NEG_INF
    ranges = np.where(finite, code, 0).astype(np.int32).view(np.float32)
    ranges = np.where(finite, ranges, np.float32(np.nan))
    ranges[code == CODE_NEG_INF] = -np.inf
    ranges[code == CODE_POS_INF] = np.float32(options.inf_value)
    ranges[empty] = np.float32(options.fill_value)
    return ranges.astype(np.float32, copy=False), winners


def make_laserscan(*, stamp_ns: int, frame_id: str, grid: AngleGrid,
                   ranges: np.ndarray[Any, Any], intensities: np.ndarray[Any, Any] | None,
                   options: OutputOptions, scan_time: float = 0.0,
                   time_increment: float = 0.0) -> Any:
    """An rclpy ``sensor_msgs.msg.LaserScan`` with array.array fields (the fast path).

    Args:
        stamp_ns: header.stamp, int ns.
        frame_id: header.frame_id.
        grid: the grid (angle fields are the float32 of its values).
        ranges: (N,) float32 metres.
        intensities: (N,) float32 or None for an empty field.
        options: range limits published.
        scan_time, time_increment: seconds.
    """
    laser_scan, header, time, split_ns = _message_types()
    sec, nanosec = split_ns(stamp_ns)
    amin, amax, inc = _header_of(grid)
    range_min, range_max = _limits_of(options)
    return bare_message(
        laser_scan, header=header(stamp=time(sec=sec, nanosec=nanosec), frame_id=frame_id),
        angle_min=amin, angle_max=amax, angle_increment=inc,
        time_increment=_f32(time_increment), scan_time=_f32(scan_time),
        range_min=range_min, range_max=range_max, ranges=_f32_array(ranges),
        intensities=array.array("f") if intensities is None else _f32_array(intensities))


def _f32_array(values: np.ndarray[Any, Any]) -> array.array[float]:
    """array.array('f') of a float32 array (one copy)."""
    out = array.array("f")
    out.frombytes(np.ascontiguousarray(values, np.float32).data.cast("B"))
    return out


@functools.lru_cache(maxsize=64)
def _limits_of(options: OutputOptions) -> tuple[float, float]:
    """(range_min, range_max) as published (float32 values), cached (options are frozen)."""
    return _f32(options.range_min), _f32(options.range_max)


_MESSAGE_TYPES: Any = None
_F32 = struct.Struct("f")


def _message_types() -> Any:
    """(LaserScan, Header, Time, split_ns), imported on first use (no rclpy import)."""
    global _MESSAGE_TYPES
    if _MESSAGE_TYPES is None:
        from builtin_interfaces.msg import Time
        from sensor_msgs.msg import LaserScan
        from std_msgs.msg import Header

        from lidarscan.stamps import split_ns
        _MESSAGE_TYPES = (LaserScan, Header, Time, split_ns)
    return _MESSAGE_TYPES


def _f32(value: float) -> float:
    """The float32 nearest to ``value``, as a Python float (inf beyond the float32 range)."""
    try:
        return float(_F32.unpack(_F32.pack(value))[0])
    except OverflowError:
        return float(np.float32(value))


@functools.lru_cache(maxsize=64)
def _header_of(grid: AngleGrid) -> tuple[float, float, float]:
    """:meth:`AngleGrid.header`, cached (grids are frozen)."""
    return grid.header()


# ------------------------------------------------------------------------ compiled kernels
#
# Optional numba kernels doing, in one pass over the rays, exactly what point_codes,
# special_codes and reduce_min do for several slices at once. They are used when numba is
# importable (set LIDARSCAN_NUMBA=0 to disable). Results equal the numpy path except for points
# within one ulp of a bin edge (numpy's SIMD atan2 and libm's may differ in the last bit).
# Pass 1 (band bits per ray) is written as loops the compiler vectorises; numpy's flatnonzero
# compacts; passes 2 and 3 visit only the rays that can contribute.

_KERNELS: Any = None
_KERNELS_TRIED = False


def numba_kernel() -> Any:
    """A callable ``fuse(**arrays)`` running the compiled kernels, or None without numba."""
    global _KERNELS, _KERNELS_TRIED
    if _KERNELS_TRIED:
        return _KERNELS
    _KERNELS_TRIED = True
    import os
    if os.environ.get("LIDARSCAN_NUMBA", "1") == "0":
        return None
    try:
        import numba
    except ImportError:
        return None
    global _J_BANDS, _J_POINTS, _J_OTHERS, _J_ROW, _J_DECODE_SLICES, _J_NEAR, _J_VALUE
    jit = numba.njit(cache=True, nogil=True, error_model="numpy")
    # called by the kernels below, so compiled first; inlined into them (a call per point
    # measured ~15 % slower where most points are near, e.g. an offset mount)
    _J_NEAR = numba.njit(nogil=True, error_model="numpy", inline="always")(_near_point)
    _J_VALUE = numba.njit(nogil=True, error_model="numpy", inline="always")(_value)
    _J_BANDS, _J_POINTS, _J_OTHERS = jit(_pass_bands), jit(_pass_points), jit(_pass_others)
    _J_ROW, _J_DECODE_SLICES = jit(_row_fuse), jit(_decode_slices)
    _KERNELS = _Compiled(_J_BANDS, _J_POINTS, _J_OTHERS, jit(_fuse_small), jit(_decode_kernel),
                         jit(_pass_rows))
    _KERNELS.sorted_fuse = jit(_sorted_fuse)
    _KERNELS.row_fuse = _J_ROW
    _KERNELS.row_convert = jit(_row_convert)
    _KERNELS.decode_slices = _J_DECODE_SLICES
    return _KERNELS


_J_BANDS: Any = None     # the compiled passes, referenced by _fuse_small and _row_convert
_J_ROW: Any = None
_J_DECODE_SLICES: Any = None
_J_NEAR: Any = None
_J_VALUE: Any = None
_J_POINTS: Any = None
_J_OTHERS: Any = None


def _fuse_small(r: Any, keep: Any, limits: Any, dx: Any, dy: Any, dz: Any, ox: Any, oy: Any,
                oz: Any, keys: Any, key_base: Any, zmin: Any, zmax: Any, rmin: Any, rmax: Any,
                slice_grid: Any, offset: Any, qual: Any, g_min: Any, g_inc: Any, g_size: Any,
                g_full: Any, bin_far: Any, r_thr: Any, best: Any) -> None:  # pragma: no cover
    """The three passes in one compiled call (small inputs: less call overhead)."""
    n = r.shape[0]
    masks = np.zeros(n, np.uint64)
    good = np.empty(n, np.bool_)
    _J_BANDS(r, keep, limits, dz, oz, zmin, zmax, masks, good)
    hits = np.empty(n, np.int64)
    rest = np.empty(n, np.int64)
    n_hits = 0
    n_rest = 0
    for i in range(n):
        hits[n_hits] = i
        n_hits += masks[i] != 0
        rest[n_rest] = i
        n_rest += not good[i]
    _J_POINTS(hits[:n_hits], masks, r, dx, dy, ox, oy, keys, key_base, rmin, rmax, slice_grid,
              offset, g_min, g_inc, g_size, g_full, bin_far, r_thr, best)
    _J_OTHERS(rest[:n_rest], r, keep, limits, keys, key_base, slice_grid, offset, qual,
              bin_far, best)


_NO_KEEP = np.zeros(0, np.uint8)
_NO_LIMITS = np.array([0.0, np.inf, 0.0])

#: Below this many rays the three passes run in one compiled call (less call overhead).
_SMALL = 32768


class _Compiled:
    """The compiled passes behind one call."""

    def __init__(self, bands: Any, points: Any, others: Any, small: Any, decode: Any,
                 rows: Any) -> None:
        self._bands, self._points, self._others = bands, points, others
        self._small = small
        self._rows = rows
        self.decode = decode

    def rows(self, r: Any, dx: Any, dy: Any, dz: Any, ox: Any, oy: Any, oz: Any, keys: Any,
             width: int, row_start: Any, row_step: Any, n_bins: int, zmin: Any, zmax: Any,
             rmin: Any, rmax: Any, slice_grid: Any, offset: Any, qual: Any, g_min: Any,
             g_inc: Any, g_size: Any, g_full: Any, bin_far: Any, r_thr: Any,
             best: Any) -> None:
        """The sensor-aligned fast path (:func:`_pass_rows`) plus passes 2 and 3."""
        n = r.shape[0]
        ok = np.empty(n, np.bool_)
        self._rows(r, dx, dy, dz, ox, oy, oz, keys, width, row_start, row_step, n_bins, zmin,
                   zmax, rmin, rmax, offset, r_thr[0], ok, best)
        point = (r > 0) & (r < np.inf)
        near = np.flatnonzero(point & ~ok)
        if near.size:
            masks = np.zeros(n, np.uint64)
            zn = r[near].astype(np.float64) * dz[near] + oz[near]
            for s in range(zmin.shape[0]):
                masks[near] |= (((zn >= zmin[s]) & (zn <= zmax[s])).astype(np.uint64)
                                << np.uint64(s))
            near = near[masks[near] != 0]
            self._points(near, masks, r, dx, dy, ox, oy, keys, 0, rmin, rmax, slice_grid,
                         offset, g_min, g_inc, g_size, g_full, bin_far, r_thr, best)
        others = np.flatnonzero(~point)
        if others.size:
            self._others(others, r, _NO_KEEP, _NO_LIMITS, keys, 0, slice_grid, offset, qual,
                         bin_far, best)


    def __call__(self, r: Any, keep: Any, limits: Any, dx: Any, dy: Any, dz: Any, ox: Any,
                 oy: Any, oz: Any, keys: Any, key_base: int, zmin: Any, zmax: Any, rmin: Any,
                 rmax: Any, slice_grid: Any, offset: Any, qual: Any, g_min: Any, g_inc: Any,
                 g_size: Any, g_full: Any, bin_far: Any, r_thr: Any, best: Any) -> None:
        """Fuse rays into ``best`` (arguments as in :func:`_pass_points` and friends)."""
        n = r.shape[0]
        if n < _SMALL:
            self._small(r, keep, limits, dx, dy, dz, ox, oy, oz, keys, key_base, zmin, zmax,
                        rmin, rmax, slice_grid, offset, qual, g_min, g_inc, g_size, g_full,
                        bin_far, r_thr, best)
            return
        masks = np.zeros(n, np.uint8 if zmin.shape[0] <= 8 else np.uint64)
        good = np.empty(n, np.bool_)
        self._bands(r, keep, limits, dz, oz, zmin, zmax, masks, good)
        hits = np.flatnonzero(masks)
        if hits.size:
            self._points(hits, masks, r, dx, dy, ox, oy, keys, key_base, rmin, rmax,
                         slice_grid, offset, g_min, g_inc, g_size, g_full, bin_far, r_thr, best)
        others = np.flatnonzero(~good)
        if others.size:
            self._others(others, r, keep, limits, keys, key_base, slice_grid, offset, qual,
                         bin_far, best)


def _decode_kernel(best: Any, inf_value: Any, fill_value: Any, ranges: Any,
                   winners: Any) -> None:  # pragma: no cover - compiled
    """Compiled :func:`decode` into preallocated (N,) float32 ranges and int64 winners."""
    values = best.view(np.int64)
    bits = np.empty(1, np.int32)
    as_float = bits.view(np.float32)
    for k in range(values.shape[0]):
        v = values[k]
        if v == EMPTY:
            ranges[k] = fill_value
            winners[k] = -1
            continue
        code = v >> 32
        winners[k] = v & 0xFFFFFFFF
        if code < CODE_NEG_INF:
            bits[0] = np.int32(code)
            ranges[k] = as_float[0]
        elif code == CODE_NEG_INF:
            ranges[k] = -np.inf
        elif code == CODE_POS_INF:
            ranges[k] = inf_value
        else:
            ranges[k] = np.nan


def _decode_slices(best: Any, offset: Any, size: Any, inf_value: Any, fill_value: Any,
                   intensity: Any, key_to_pos: Any, ranges: Any,
                   ints: Any) -> None:  # pragma: no cover - compiled
    """:func:`decode` of every slice (``best[offset[s]:offset[s] + size[s]]``) into ``ranges``
    (float32, same layout) plus, when ``intensity`` is not empty, the winner's intensity cast to
    float32 into ``ints`` (0 for empty bins); ``key_to_pos`` maps tie keys to pixels (empty:
    identity)."""
    use_int = intensity.shape[0] > 0
    use_map = key_to_pos.shape[0] > 0
    for s in range(offset.shape[0]):
        inf_v = inf_value[s]
        fill_v = fill_value[s]
        for k in range(size[s]):
            j = offset[s] + k
            v = best[j]
            if v == EMPTY:
                ranges[j] = fill_v
                if use_int:
                    ints[j] = 0.0
                continue
            code = v >> 32
            if code < CODE_NEG_INF:
                ranges[j] = np.int32(code).view(np.float32)
            elif code == CODE_NEG_INF:
                ranges[j] = -np.inf
            elif code == CODE_POS_INF:
                ranges[j] = inf_v
            else:
                ranges[j] = np.nan
            if use_int:
                key = v & 0xFFFFFFFF
                ints[j] = np.float32(intensity[key_to_pos[key] if use_map else key])


def _pass_bands(r: Any, keep: Any, limits: Any, dz: Any, oz: Any, zmin: Any, zmax: Any,
                masks: Any, good: Any) -> None:  # pragma: no cover - compiled
    """Pass 1: ``good[i]``: a point candidate (finite, > 0, inside the limits, kept);
    ``masks[i]`` bit s: the point's height is inside slice s's band (0 unless good)."""
    n = r.shape[0]
    lim0 = limits[0]
    lim1 = limits[1]
    lim2 = limits[2]
    for i in range(n):
        rv = r[i]
        good[i] = (rv > 0.0) & (rv >= lim0) & (rv < np.inf) & (rv <= lim1) & (rv >= lim2)
    if keep.shape[0] == n:
        for i in range(n):
            good[i] &= keep[i] != 0
    z = np.empty(n)
    for i in range(n):
        z[i] = np.float64(r[i]) * dz[i] + oz[i]
    one = masks.dtype.type(1)
    for s in range(zmin.shape[0]):
        lo_z = zmin[s]
        hi_z = zmax[s]
        bit = one << s
        for i in range(n):
            masks[i] |= masks.dtype.type((z[i] >= lo_z) & (z[i] <= hi_z) & good[i]) * bit


def _pass_points(hits: Any, masks: Any, r: Any, dx: Any, dy: Any, ox: Any, oy: Any, keys: Any,
                 key_base: Any, rmin: Any, rmax: Any, slice_grid: Any, offset: Any, g_min: Any,
                 g_inc: Any, g_size: Any, g_full: Any, bin_far: Any, r_thr: Any,
                 best: Any) -> None:  # pragma: no cover - compiled
    """Pass 2: points inside at least one band. Bins from the far-field tables, or atan2 for
    rays closer than ``r_thr``; codes from the float32 bit pattern of rho."""
    two_pi = 2.0 * math.pi
    bits = np.empty(1, np.float32)
    bits_i = bits.view(np.int32)
    n_grids = g_min.shape[0]
    use_keys = keys.shape[0] == r.shape[0]
    grid_bin = np.empty(n_grids, np.int64)
    for h in range(hits.shape[0]):
        i = hits[h]
        m = np.int64(masks[i])
        rv = r[i]
        rd = np.float64(rv)
        x = rd * dx[i] + ox[i]
        y = rd * dy[i] + oy[i]
        rho = math.sqrt(x * x + y * y)
        bits[0] = rho
        code_f = np.int64(bits_i[0])
        key = np.int64(keys[i]) + key_base if use_keys else np.int64(key_base + i)
        for g in range(n_grids):
            if rv < r_thr[g, i]:
                d = math.atan2(y, x) - g_min[g]
                inc = g_inc[g]
                if g_full[g]:
                    grid_bin[g] = np.int64(math.ceil(d / inc - 0.5)) % g_size[g]
                else:
                    d = d - two_pi * math.floor((d + 0.5 * inc) / two_pi)
                    k = np.int64(math.ceil(d / inc - 0.5))
                    grid_bin[g] = k if 0 <= k < g_size[g] else -1
            else:
                grid_bin[g] = bin_far[g, i]
        s = 0
        while m:
            if m & 1:
                b = grid_bin[slice_grid[s]]
                if b >= 0:
                    code = code_f
                    if rho < rmin[s]:
                        code = np.int64(CODE_NEG_INF)
                    elif rho > rmax[s]:
                        code = np.int64(CODE_POS_INF)
                    comb = (code << 32) | key
                    j = offset[s] + b
                    best[j] = min(best[j], comb)
            m >>= 1
            s += 1


def _pass_others(others: Any, r: Any, keep: Any, limits: Any, keys: Any, key_base: Any,
                 slice_grid: Any, offset: Any, qual: Any, bin_far: Any,
                 best: Any) -> None:  # pragma: no cover - compiled
    """Pass 3: no return (+Inf), too close (-Inf), invalid (NaN, <= 0, below limits[0]),
    beyond limits[1] (+Inf); below limits[2] or outside ``keep``: dropped."""
    n_slices = slice_grid.shape[0]
    use_keep = keep.shape[0] == r.shape[0]
    use_keys = keys.shape[0] == r.shape[0]
    for h in range(others.shape[0]):
        i = others[h]
        if use_keep and keep[i] == 0:
            continue
        rv = r[i]
        need = 1
        if rv == np.inf:
            special = CODE_POS_INF
        elif rv == -np.inf:
            special, need = CODE_NEG_INF, 2
        elif math.isnan(rv) or rv <= 0.0 or rv < limits[0]:
            special = CODE_NAN
        elif rv > limits[1]:
            special = CODE_POS_INF
        else:                     # below the user's range filter: dropped
            continue
        key = np.int64(keys[i]) + key_base if use_keys else np.int64(key_base + i)
        comb = (np.int64(special) << 32) | key
        for s in range(n_slices):
            b = bin_far[slice_grid[s], i]
            if b >= 0 and (qual[s, i] & need):
                j = offset[s] + b
                best[j] = min(best[j], comb)


def _pass_rows(r: Any, dx: Any, dy: Any, dz: Any, ox: Any, oy: Any, oz: Any, keys: Any,
               width: Any, row_start: Any, row_step: Any, n_bins: Any, zmin: Any, zmax: Any,
               rmin: Any, rmax: Any, offset: Any, r_thr: Any, ok: Any,
               best: Any) -> None:  # pragma: no cover - compiled
    """Sensor-aligned fast path: every row's far-field bins run ``row_start[u] + step*c``
    (mod ``n_bins``, step +-1) on one grid shared by all slices, so a row's far points fuse
    into consecutive bins without scattered lookups. Sets ``ok[i]`` for the far points it
    handled; near points and non-points are left to passes 2 and 3."""
    n = r.shape[0]
    height = n // width
    n_slices = zmin.shape[0]
    use_keys = keys.shape[0] == n
    zz = np.empty(width)
    rho = np.empty(width)
    rho32 = np.empty(width, np.float32)
    rho_bits = rho32.view(np.int32)
    comb = np.empty(width, np.int64)
    empty = np.int64(EMPTY)
    for u in range(height):
        base = u * width
        for c in range(width):
            i = base + c
            rv = r[i]
            rd = np.float64(rv)
            x = rd * dx[i] + ox[i]
            y = rd * dy[i] + oy[i]
            zz[c] = rd * dz[i] + oz[i]
            rho[c] = math.sqrt(x * x + y * y)
            rho32[c] = rho[c]
            ok[i] = (rv > 0.0) & (rv < np.inf) & (rv >= r_thr[i])
        start = row_start[u]
        step = row_step[u]
        for s in range(n_slices):
            lo_z, hi_z, lo_r, hi_r = zmin[s], zmax[s], rmin[s], rmax[s]
            for c in range(width):
                code = np.int64(rho_bits[c])
                code = np.int64(CODE_NEG_INF) if rho[c] < lo_r else code
                code = np.int64(CODE_POS_INF) if rho[c] > hi_r else code
                key = np.int64(keys[base + c]) if use_keys else np.int64(base + c)
                inside = ok[base + c] & (zz[c] >= lo_z) & (zz[c] <= hi_z)
                comb[c] = ((code << 32) | key) if inside else empty
            # bins run start, start + step, ... (mod n_bins): two contiguous runs
            off = offset[s]
            if step == 1:
                split = min(n_bins - start, width)
                j0 = off + start
                for c in range(split):
                    best[j0 + c] = min(best[j0 + c], comb[c])
                j0 = off - split
                for c in range(split, width):
                    best[j0 + c] = min(best[j0 + c], comb[c])
            else:
                split = min(start + 1, width)
                j0 = off + start
                for c in range(split):
                    best[j0 - c] = min(best[j0 - c], comb[c])
                j0 = off + start + n_bins
                for c in range(split, width):
                    best[j0 - c] = min(best[j0 - c], comb[c])


# ------------------------------------------------- bin-ordered kernel (slices, one shared grid)
#
# Per LidarInfo version the pixel tables are permuted once into the order of the far-field bins
# (``src[j]`` = pixel at position ``j``; ``bin_start[b]:bin_start[b+1]`` = the positions of bin
# ``b``; pixels without a far-field bin at the end). Per scan, bin by bin: the ranges of the bin
# are gathered once (shared by all slices), one branch-free loop the compiler vectorises gives
# every position its code (``code << 32 | key``) and its slice bits (height band for points,
# the precomputed +Inf/NaN/-Inf qualifiers otherwise), and a running minimum per slice over the
# bin's positions replaces the scatter; only points closer than their far-field threshold (rare
# for a sensor on the target's z axis) take a scalar path with atan2. The per-pixel thresholds
# are read only for runs of bins whose smallest positive range is below the run's largest
# threshold (``bin_thr``), so a centred sensor does not stream them at all. Used when all slices
# share one grid and their planar range limits (so a point's class is decided once).


def _sorted_fuse(r: Any, src: Any, keys: Any, dz: Any, oz: Any, dx: Any, dy: Any, ox: Any,
                 oy: Any, r_thr: Any, qf: Any, qn: Any, zmin: Any, zmax: Any, n_slices: Any,
                 lim_lo: Any, lim_hi: Any, bin_start: Any, bin_thr: Any, max_width: Any,
                 offset: Any, g_min: Any, g_inc: Any, g_size: Any, g_full: Any,
                 best: Any) -> None:  # pragma: no cover - compiled
    """Fuse one scan into ``best`` for slices ``0 .. n_slices-1`` on one grid.

    Args:
        r: (n,) float32 ranges in pixel order.
        src, keys: (n,) int32 pixel and tie key of each position (bin order).
        dz, oz, dx, dy, ox, oy, r_thr: (n,) float32 ray tables and far-field threshold, bin order.
        qf, qn: (n,) bit s: slice s may report +Inf/NaN (qf) or -Inf (qn), bin order.
        zmin, zmax: bands padded to a multiple of four slices with empty ones (inf, -inf).
        lim_lo, lim_hi: the shared planar range limits.
        bin_start: (size + 2,) int64 position of each bin's first pixel (last: the pixels
            without a far-field bin, only their near points can contribute).
        bin_thr: (size + 1,) float32 the largest ``r_thr`` of each bin's pixels: a run of
            bins whose smallest positive range reaches it has no near point, and its
            ``r_thr`` values are not read at all (less memory traffic).
        max_width: positions per chunk of whole bins (>= the largest bin; scratch size).
        offset: (n_slices,) int64 first element of each slice in ``best``.
        g_min, g_inc, g_size, g_full: the grid.
        best: reduction array, updated in place.
    """
    empty = np.int64(EMPTY)
    chunk = max_width
    rp = np.empty(chunk, np.float32)
    no_thr = np.zeros(chunk, np.float32)          # stands for r_thr when no point is near
    cm = np.empty(chunk, np.int64)
    mm = np.empty(chunk, np.int64)
    n_blocks = zmin.shape[0] // 4
    b_end = 0
    while b_end < g_size + 1:
        # a run of whole bins, at most ``chunk`` positions (at least one bin)
        b_first = b_end
        j0 = bin_start[b_first]
        b_end = b_first + 1
        while b_end < g_size + 1 and bin_start[b_end + 1] - j0 <= chunk:
            b_end += 1
        j1 = bin_start[b_end]
        w = j1 - j0
        if w == 0:
            continue
        vsrc = src[j0:j1]
        lowest = np.float32(np.inf)         # smallest positive range of the run
        for k in range(w):
            rv = r[vsrc[k]]
            rp[k] = rv
            lowest = min(lowest, rv if rv > 0.0 else np.float32(np.inf))   # branch-free
        thr_max = bin_thr[b_first]
        for b in range(b_first + 1, b_end):
            thr_max = max(thr_max, bin_thr[b])
        vthr = r_thr[j0:j1] if lowest < thr_max else no_thr[:w]
        vkeys, vqf, vqn = keys[j0:j1], qf[j0:j1], qn[j0:j1]
        vdz, voz, vdx, vdy, vox, voy = (dz[j0:j1], oz[j0:j1], dx[j0:j1], dy[j0:j1],
                                        ox[j0:j1], oy[j0:j1])
        for blk in range(n_blocks):
            s0 = 4 * blk
            lo0, hi0 = zmin[s0], zmax[s0]
            lo1, hi1 = zmin[s0 + 1], zmax[s0 + 1]
            lo2, hi2 = zmin[s0 + 2], zmax[s0 + 2]
            lo3, hi3 = zmin[s0 + 3], zmax[s0 + 3]
            count = np.int64(0)
            for k in range(w):
                rv = rp[k]
                z = np.float64(rv) * vdz[k] + voz[k]
                point = (rv > 0.0) & (rv < np.inf)
                near = point & (rv < vthr[k])
                count += np.int64(near)
                value = _J_VALUE(rv, vdx[k], vdy[k], vox[k], voy[k], vkeys[k], lim_lo, lim_hi)
                cm[k] = empty if near else value
                m = np.int64((z >= lo0) & (z <= hi0))
                m |= np.int64((z >= lo1) & (z <= hi1)) << 1
                m |= np.int64((z >= lo2) & (z <= hi2)) << 2
                m |= np.int64((z >= lo3) & (z <= hi3)) << 3
                # both qualifiers loaded, one picked arithmetically: a conditional load would
                # keep the compiler from vectorising this loop (about 1.5x slower)
                sel = np.int64(rv == -np.inf)
                q = (np.int64(vqn[k]) * sel) | (np.int64(vqf[k]) * (1 - sel))
                mm[k] = m if point else (q >> s0) & 15
            for b in range(b_first, min(b_end, g_size)):
                vm = mm[bin_start[b] - j0:bin_start[b + 1] - j0]
                vc = cm[bin_start[b] - j0:bin_start[b + 1] - j0]
                r0 = empty
                r1 = empty
                r2 = empty
                r3 = empty
                for k in range(vm.shape[0]):
                    m = vm[k]
                    v = vc[k]
                    r0 = min(r0, v if m & 1 else empty)
                    r1 = min(r1, v if m & 2 else empty)
                    r2 = min(r2, v if m & 4 else empty)
                    r3 = min(r3, v if m & 8 else empty)
                for t, run in enumerate((r0, r1, r2, r3)):
                    if s0 + t < n_slices:
                        jj = offset[s0 + t] + b
                        best[jj] = min(best[jj], run)
            if count == 0:
                continue
            # points closer than their far-field threshold: exact bin from atan2
            for k in range(w):
                rv = rp[k]
                if not ((rv > 0.0) & (rv < np.inf) & (rv < vthr[k]) & (mm[k] != 0)):
                    continue
                _J_NEAR(rv, vdx[k], vdy[k], vox[k], voy[k], vkeys[k], mm[k], s0, n_slices,
                        lim_lo, lim_hi, g_min, g_inc, g_size, g_full, offset, best)


def _value(rv: Any, dx: Any, dy: Any, ox: Any, oy: Any, key: Any, lim_lo: Any,
           lim_hi: Any) -> Any:  # pragma: no cover - compiled
    """``code << 32 | key`` of one range on its ray (module docstring): the float32 bits of
    the planar range of a point (or -Inf / +Inf outside the planar limits), the class code of a
    non-point. Branch-free, inlined into the kernels' vectorised loops."""
    rd = np.float64(rv)
    x = rd * dx + ox
    y = rd * dy + oy
    rho = math.sqrt(x * x + y * y)
    point = (rv > 0.0) & (rv < np.inf)
    code = np.int64(np.float32(rho).view(np.int32))
    code = np.int64(CODE_NEG_INF) if rho < lim_lo else code
    code = np.int64(CODE_POS_INF) if rho > lim_hi else code
    special = np.int64(CODE_NAN)
    special = np.int64(CODE_POS_INF) if rv == np.inf else special
    special = np.int64(CODE_NEG_INF) if rv == -np.inf else special
    return ((code if point else special) << 32) | np.int64(key)


def _near_point(rv: Any, dx: Any, dy: Any, ox: Any, oy: Any, key: Any, m: Any, s0: Any,
                n_slices: Any, lim_lo: Any, lim_hi: Any, g_min: Any, g_inc: Any, g_size: Any,
                g_full: Any, offset: Any, best: Any) -> None:  # pragma: no cover - compiled
    """One point closer than its far-field threshold (range ``rv``, ray ``dx, dy, ox, oy``):
    its exact bin from atan2, then its value into slices ``s0 + t`` for the bits t of ``m``
    (shared by the bin-ordered and row-ordered kernels)."""
    rd = np.float64(rv)
    x = rd * dx + ox
    y = rd * dy + oy
    rho = math.sqrt(x * x + y * y)
    code = np.int64(np.float32(rho).view(np.int32))
    if rho < lim_lo:
        code = np.int64(CODE_NEG_INF)
    elif rho > lim_hi:
        code = np.int64(CODE_POS_INF)
    d = math.atan2(y, x) - g_min
    if g_full:
        bn = np.int64(math.ceil(d / g_inc - 0.5))
        if bn < 0 or bn >= g_size:        # (a modulo only when needed: slow)
            bn %= g_size
    else:
        two_pi = 2.0 * math.pi
        d = d - two_pi * math.floor((d + 0.5 * g_inc) / two_pi)
        bn = np.int64(math.ceil(d / g_inc - 0.5))
        if bn < 0 or bn >= g_size:
            return
    value = (code << 32) | np.int64(key)
    for t in range(4):
        if (m >> t) & 1 and s0 + t < n_slices:
            jj = offset[s0 + t] + bn
            best[jj] = min(best[jj], value)


# ------------------------------------------- row-ordered kernel (aligned grid, upright sensor)
#
# For the usual configuration (a full circle at the sensor's column resolution, an upright
# sensor) the bin-ordered layout of :func:`_sorted_fuse` has more structure: every bin holds
# exactly one pixel of every row, in row order, so position ``k`` inside any bin *is* row ``k``.
# If moreover ``dz`` and ``oz`` are bitwise constant along every row, the height test of a
# point depends only on its float32 range and its row: ``z(r) = float64(r) * dz + oz`` is a
# composition of correctly rounded (hence monotone) operations, so ``{r : zmin <= z(r) <= zmax}``
# is an *interval of float32 values*. :func:`band_intervals_f32` finds its ends exactly (by
# bisection over float32 bit patterns, evaluating the very same float64 formula), and the kernel
# replaces z and eight float64 comparisons per pixel by two float32 comparisons against per-row
# constants (an L1-resident (slices, H) table). Everything else is :func:`_sorted_fuse`'s rules.

_F32_MAX_BITS = 0x7F7FFFFF      # largest finite float32
_F32_INF_BITS = 0x7F800000


def band_intervals_f32(dz: np.ndarray[Any, Any], oz: np.ndarray[Any, Any],
                       min_z: np.ndarray[Any, Any], max_z: np.ndarray[Any, Any]
                       ) -> tuple[np.ndarray[Any, np.dtype[np.float32]],
                                  np.ndarray[Any, np.dtype[np.float32]]]:
    """Exact float32 range intervals of the height bands, per ray and band.

    For every finite float32 ``r > 0``: ``lo[s, i] <= r <= hi[s, i]`` if and only if
    ``min_z[s] <= float64(r) * float64(dz[i]) + float64(oz[i]) <= max_z[s]`` (float64
    arithmetic, no fused multiply-add, exactly as the kernels evaluate it). ``lo`` is positive and
    ``hi`` finite, so ``+-Inf``, NaN, 0 and negative ranges are never inside; an empty interval
    is ``lo = +Inf, hi = 0``.

    Why it is exact: ``r -> r * dz`` and ``t -> t + oz`` are correctly rounded, hence monotone
    (non-decreasing for ``dz > 0``, non-increasing for ``dz < 0``), so each side of the band is
    one threshold on the ordered float32 values; positive float32 values are ordered like their
    bit patterns, and a bisection over the patterns (31 steps) finds each threshold.

    Args:
        dz, oz: (n,) float32 ray direction and origin z in the target frame.
        min_z, max_z: (S,) float64 bands (``inf``/``-inf`` allowed; ``min_z > max_z``: empty).

    Returns:
        lo, hi: (S, n) float32.
    """
    n_s, n = len(min_z), len(dz)
    dz64 = np.broadcast_to(np.asarray(dz, np.float32).astype(np.float64)[None, :], (n_s, n))
    oz64 = np.broadcast_to(np.asarray(oz, np.float32).astype(np.float64)[None, :], (n_s, n))
    zl = np.broadcast_to(np.asarray(min_z, np.float64)[:, None], (n_s, n))
    zh = np.broadcast_to(np.asarray(max_z, np.float64)[:, None], (n_s, n))
    up = dz64 > 0

    def z_of(bits: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
        r = bits.astype(np.int32).view(np.float32).astype(np.float64)
        with np.errstate(invalid="ignore"):
            return r * dz64 + oz64

    def first(pred: Any) -> np.ndarray[Any, Any]:
        """Smallest pattern in [1, MAX] where the monotone ``pred`` holds (MAX + 1: none)."""
        a = np.ones((n_s, n), np.int64)
        b = np.full((n_s, n), _F32_INF_BITS, np.int64)
        active = a < b
        while np.any(active):
            mid = (a + b) // 2
            ok = pred(mid)
            b = np.where(active & ok, mid, b)
            a = np.where(active & ~ok, mid + 1, a)
            active = a < b
        return a

    with np.errstate(invalid="ignore"):
        # lo: first r on the band's side of its near edge; hi: last r before the far edge
        lo = first(lambda p: np.where(up, z_of(p) >= zl, z_of(p) <= zh))
        hi = first(lambda p: np.where(up, z_of(p) > zh, z_of(p) < zl)) - 1
        z_flat = 0.0 * dz64 + oz64                 # dz == 0 (either sign): z does not move
        inside = (z_flat >= zl) & (z_flat <= zh)
    flat = dz64 == 0
    lo = np.where(flat, np.where(inside, 1, _F32_INF_BITS), lo)
    hi = np.where(flat, np.where(inside, _F32_MAX_BITS, 0), hi)
    empty = lo > hi                                # also a NaN dz or oz: never inside
    lo = np.where(empty, _F32_INF_BITS, lo)
    hi = np.where(empty, 0, hi)
    return (lo.astype(np.int32).view(np.float32), hi.astype(np.int32).view(np.float32))


def _row_fuse(r: Any, src: Any, keys: Any, dx: Any, dy: Any, ox: Any, oy: Any, r_thr: Any,
              qf: Any, qn: Any, q_rows: Any, lo: Any, hi: Any, n_slices: Any, lim_lo: Any,
              lim_hi: Any, height: Any, bin_thr: Any, offset: Any, g_min: Any, g_inc: Any,
              g_size: Any, g_full: Any, best: Any) -> None:  # pragma: no cover - compiled
    """:func:`_sorted_fuse` for the row-ordered layout: bin ``b`` is positions
    ``b*H .. b*H + H - 1`` and position ``k`` of a bin is row ``k``.

    Args:
        r: (n,) float32 ranges in pixel order.
        src, keys: (n,) uint32 pixel and tie key of each position (bin order).
        dx, dy, ox, oy, r_thr: (n,) float32 ray tables and far-field threshold, bin order.
        qf, qn: bit s: slice s may report +Inf/NaN (qf) or -Inf (qn); (H,) per row when
            ``q_rows`` (the same for every bin), else (n,) in bin order.
        lo, hi: (S, H) float32 per band (padded to a multiple of four with empty ones) and row,
            from :func:`band_intervals_f32`: a range ``rv`` of row ``k`` is a point inside band
            ``s`` iff ``lo[s, k] <= rv <= hi[s, k]`` (false for every non-point).
        n_slices, lim_lo, lim_hi, bin_thr, offset, g_*, best: as in :func:`_sorted_fuse`.

    Per bin: one gather of its H ranges; one vectorised loop giving every position its value
    ``code << 32 | key`` (``EMPTY`` for a point closer than its far-field threshold: those take
    the atan2 path) and, for non-points, the qualifier bits of their class; then per block of
    four slices one vectorised loop of four running minima (a position takes part in slice s
    iff it is inside the band interval or a qualified non-point).
    """
    empty = np.int64(EMPTY)
    rows = height
    rp = np.empty(rows, np.float32)
    cv = np.empty(rows, np.int64)             # value of each position
    qx = np.empty(rows, np.int32)             # qualifier bits of non-points (0 for points)
    n_blocks = lo.shape[0] // 4
    q_step = 0 if q_rows else rows
    # Tables are read at index offsets (j0 + k): array views created per bin cost reference
    # counting calls that showed up as ~20 % of the time.
    for b in range(g_size):
        j0 = b * rows
        q0 = b * q_step
        lowest = np.float32(np.inf)           # smallest positive range of the bin
        for k in range(rows):
            rv = r[src[j0 + k]]
            rp[k] = rv
            lowest = min(lowest, rv if rv > 0.0 else np.float32(np.inf))   # branch-free
        for k in range(rows):
            rv = rp[k]
            point = (rv > 0.0) & (rv < np.inf)
            cv[k] = _J_VALUE(rv, dx[j0 + k], dy[j0 + k], ox[j0 + k], oy[j0 + k], keys[j0 + k],
                             lim_lo, lim_hi)
            # both qualifiers loaded, one picked arithmetically (keeps the loop vectorised)
            sel = np.int64(rv == -np.inf)
            q = (np.int64(qn[q0 + k]) * sel) | (np.int64(qf[q0 + k]) * (1 - sel))
            qx[k] = np.int32(0 if point else q)
        count = np.int64(0)
        if lowest < bin_thr[b]:
            # some point may be closer than its far-field threshold (rare for a centred
            # sensor): such points leave the minima and take the atan2 path below
            for k in range(rows):
                rv = rp[k]
                near = (rv > 0.0) & (rv < np.inf) & (rv < r_thr[j0 + k])
                count += np.int64(near)
                cv[k] = empty if near else cv[k]
        for blk in range(n_blocks):
            s0 = 4 * blk
            r0 = empty
            r1 = empty
            r2 = empty
            r3 = empty
            for k in range(rows):
                rv = rp[k]
                v = cv[k]
                q = qx[k] >> s0
                r0 = min(r0, v if (((rv >= lo[s0, k]) & (rv <= hi[s0, k]))
                                   | ((q & 1) != 0)) else empty)
                r1 = min(r1, v if (((rv >= lo[s0 + 1, k]) & (rv <= hi[s0 + 1, k]))
                                   | ((q & 2) != 0)) else empty)
                r2 = min(r2, v if (((rv >= lo[s0 + 2, k]) & (rv <= hi[s0 + 2, k]))
                                   | ((q & 4) != 0)) else empty)
                r3 = min(r3, v if (((rv >= lo[s0 + 3, k]) & (rv <= hi[s0 + 3, k]))
                                   | ((q & 8) != 0)) else empty)
            # (padded slices s >= n_slices have empty bands and no qualifier bits)
            if s0 < n_slices:
                best[offset[s0] + b] = min(best[offset[s0] + b], r0)
            if s0 + 1 < n_slices:
                best[offset[s0 + 1] + b] = min(best[offset[s0 + 1] + b], r1)
            if s0 + 2 < n_slices:
                best[offset[s0 + 2] + b] = min(best[offset[s0 + 2] + b], r2)
            if s0 + 3 < n_slices:
                best[offset[s0 + 3] + b] = min(best[offset[s0 + 3] + b], r3)
            if count == 0:
                continue
            # points closer than their far-field threshold: exact bin from atan2
            for k in range(rows):
                rv = rp[k]
                if not ((rv > 0.0) & (rv < np.inf) & (rv < r_thr[j0 + k])):
                    continue
                m = 0
                for t in range(4):
                    if (rv >= lo[s0 + t, k]) & (rv <= hi[s0 + t, k]):
                        m |= 1 << t
                if m != 0:
                    _J_NEAR(rv, dx[j0 + k], dy[j0 + k], ox[j0 + k], oy[j0 + k], keys[j0 + k],
                            m, s0, n_slices, lim_lo, lim_hi, g_min, g_inc, g_size, g_full,
                            offset, best)


def _row_convert(r: Any, src: Any, keys: Any, dx: Any, dy: Any, ox: Any, oy: Any, r_thr: Any,
                 qf: Any, qn: Any, q_rows: Any, lo: Any, hi: Any, n_slices: Any, lim_lo: Any,
                 lim_hi: Any, height: Any, bin_thr: Any, offset: Any, g_min: Any, g_inc: Any,
                 g_size: Any, g_full: Any, total: Any, size: Any, inf_value: Any,
                 fill_value: Any, intensity: Any, key_to_pos: Any,
                 want_ints: Any) -> Any:  # pragma: no cover - compiled
    """:func:`_row_fuse` into a fresh reduction array of ``total`` elements, then
    :func:`_decode_slices`, in one compiled call (one dispatch less per scan).

    Returns:
        (ranges, ints): float32 of all slices back to back (ints empty unless ``want_ints``).
    """
    best = np.full(total, np.int64(EMPTY), np.int64)
    _J_ROW(r, src, keys, dx, dy, ox, oy, r_thr, qf, qn, q_rows, lo, hi, n_slices, lim_lo, lim_hi,
           height, bin_thr, offset, g_min, g_inc, g_size, g_full, best)
    ranges = np.empty(total, np.float32)
    ints = np.empty(total if want_ints else 0, np.float32)
    _J_DECODE_SLICES(best, offset, size, inf_value, fill_value, intensity, key_to_pos, ranges,
                     ints)
    return ranges, ints


#: Positions per chunk of whole bins in :func:`_sorted_fuse` (at least one whole bin).
SORTED_CHUNK = 512


def aligned_rows(bin_far: np.ndarray[Any, Any], width: int, size: int
                 ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]] | None:
    """(row_start, row_step) if every row (``width`` columns) of the integer array ``bin_far``
    (far-field bins, or any per-pixel column index such as tie-key columns) is
    ``start + step*c mod size`` with step +-1 and ``size == width`` (a full circle at the
    sensor's resolution), else None."""
    if size != width or width < 2 or bin_far.size % width:
        return None
    rows = bin_far.reshape(-1, width).astype(np.int64)
    if np.any(rows < 0):
        return None
    start = rows[:, 0]
    step = np.where((rows[:, 1] - start) % size == 1, 1, -1)
    expect = (start[:, None] + step[:, None] * np.arange(width)[None, :]) % size
    if not np.array_equal(rows, expect):
        return None
    return start, step


def round_up_f32(values: np.ndarray[Any, Any]) -> np.ndarray[Any, np.dtype[np.float32]]:
    """float32 of float64 values, never below them (for conservative thresholds)."""
    out = values.astype(np.float32)
    low = out.astype(np.float64) < values
    out[low] = np.nextafter(out[low], np.float32(np.inf))
    return out
