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
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from lidarscan.rosmsg import bare_message
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
    "merge_min",
    "point_codes",
    "qualify",
    "rho_codes",
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

def output_layout(grids: Sequence[AngleGrid]
                  ) -> tuple[int, np.ndarray[Any, Any], list[AngleGrid], list[int]]:
    """Where each slice's bins lie in one flat output array, for the slices' grids in order:
    (total bins, each slice's first bin (int64), the distinct grids, each slice's index into
    them -- slices sharing a grid share its binning work)."""
    sizes = [g.size for g in grids]
    offsets = np.cumsum([0] + sizes, dtype=np.int64)[:-1]
    distinct: list[AngleGrid] = []
    index: list[int] = []
    for grid in grids:
        if grid not in distinct:
            distinct.append(grid)
        index.append(distinct.index(grid))
    return int(sum(sizes)), offsets, distinct, index


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
    return sel, bins[sel], rho_codes(rho, rmin, rmax)


def rho_codes(rho: np.ndarray[Any, Any], range_min: Any, range_max: Any
              ) -> np.ndarray[Any, np.dtype[np.int64]]:
    """int64 codes of planar ranges ``rho`` (float64, >= 0): the float32 bit pattern inside the
    inclusive ``[range_min, range_max]``, ``CODE_NEG_INF`` below, ``CODE_POS_INF`` above."""
    codes = rho.astype(np.float32).view(np.int32).astype(np.int64)
    codes[rho < range_min] = CODE_NEG_INF
    codes[rho > range_max] = CODE_POS_INF
    return codes


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


def merge_min(best: np.ndarray[Any, Any], bins: np.ndarray[Any, Any],
              codes: np.ndarray[Any, Any], keys: np.ndarray[Any, Any]) -> None:
    """Fuse more candidates into a reduction array in place (as :func:`reduce_min`)."""
    if bins.size:
        combined = (np.asarray(codes, np.int64) << 32) | np.asarray(keys, np.int64)
        np.minimum.at(best, np.asarray(bins, np.intp), combined)


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
    kernels of :func:`converters._kernels.slices_numba.kernels` to use, or None for numpy).

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
                   time_increment: float = 0.0, stamp: tuple[int, int] | None = None) -> Any:
    """An rclpy ``sensor_msgs.msg.LaserScan`` with array.array fields (the fast path).

    Args:
        stamp_ns: header.stamp, int ns.
        frame_id: header.frame_id.
        grid: the grid (angle fields are the float32 of its values).
        ranges: (N,) float32 metres.
        intensities: (N,) float32 or None for an empty field.
        options: range limits published.
        scan_time, time_increment: seconds.
        stamp: ``stamp_ns`` as (sec, nanosec) when the caller has it already, or None.
    """
    laser_scan, header, time, split_ns = _message_types()
    sec, nanosec = split_ns(stamp_ns) if stamp is None else stamp
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


# ------------------------------------------- exact band intervals (row-ordered kernels)
#
# For the usual configuration (a full circle at the sensor's column resolution, an upright
# sensor) the layout of the bin-ordered kernel has more structure: every bin holds
# exactly one pixel of every row, in row order, so position ``k`` inside any bin *is* row ``k``.
# If moreover ``dz`` and ``oz`` are bitwise constant along every row, the height test of a
# point depends only on its float32 range and its row: ``z(r) = float64(r) * dz + oz`` is a
# composition of correctly rounded (hence monotone) operations, so ``{r : zmin <= z(r) <= zmax}``
# is an *interval of float32 values*. :func:`band_intervals_f32` finds its ends exactly (by
# bisection over float32 bit patterns, evaluating the very same float64 formula), and the kernel
# replaces z and eight float64 comparisons per pixel by two float32 comparisons against per-row
# constants (an L1-resident (slices, H) table). Everything else follows the bin-ordered
# kernel's rules (:mod:`converters._kernels.slices_numba`).

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
