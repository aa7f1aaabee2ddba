"""Python side of the compiled slicing kernel ``converters/_slicekernel.c``.

The kernel computes all height slices of one scan in the *row-ordered* configuration of
:mod:`converters.slices.spec` (one full-circle grid at the sensor's column resolution, an upright
sensor, every row mapping its columns onto the bins as ``start + step*c mod W``), bit-identical
to the numba kernel :func:`converters._kernels.slices_numba._row_convert`, but streaming the
scan in pixel order instead of gathering it bin by bin. :class:`SlicePlan` holds the per-table-version arguments
(a ``ctypes`` structure, built once); :meth:`SlicePlan.run` converts one scan.
"""

from __future__ import annotations

import ctypes
from typing import Any

import numpy as np

from converters._kernels import _loader

#: ABI of converters/_slicekernel.c (its LSS_ABI).
ABI = 2
#: Most slices the kernel takes (its qualifier bits are uint32).
MAX_SLICES = 32
#: 0 forces the kernel's scalar code even where AVX-512 is available (tests cover both).
SIMD = 1

_i64, _f64, _ptr = ctypes.c_int64, ctypes.c_double, ctypes.c_void_p


class _Plan(ctypes.Structure):
    """``lss_plan`` of _slicekernel.c: the same fields, in the same order."""

    _fields_ = [("height", _i64), ("width", _i64), ("n_slices", _i64),
                ("dx", _ptr), ("dy", _ptr), ("ox", _ptr), ("oy", _ptr),
                ("r_thr", _ptr), ("group_thr", _ptr),
                ("bin_start", _ptr), ("bin_step", _ptr), ("key_start", _ptr), ("key_step", _ptr),
                ("qf", _ptr), ("qn", _ptr), ("q_per_pixel", _i64),
                ("lo", _ptr), ("hi", _ptr),
                ("lim_lo", _f64), ("lim_hi", _f64), ("g_min", _f64), ("g_inc", _f64),
                ("g_full", _i64),
                ("inf_value", _ptr), ("fill_value", _ptr), ("key_to_pos", _ptr)]


def library() -> Any:
    """The kernel's ``lss_slices`` (a ctypes function; it releases the GIL), or None when the
    kernel is not built, stale or disabled (``LIDARSCAN_NO_KERNEL``, read at the first use)."""
    return _library.get()


def _load() -> Any:
    loaded = _loader.load_planned("converters._kernels._slicekernel", "lss", ABI, _Plan)
    if loaded is None:
        return None
    fn = loaded[0].lss_slices
    fn.vectorised = loaded[1]
    fn.restype = _i64
    fn.argtypes = [ctypes.POINTER(_Plan), _ptr, _ptr, ctypes.c_int32,   # plan, r, intensity, type
                   _ptr, _ptr, _ptr, ctypes.c_int32]          # ranges, ints, winners, simd
    return fn


_library = _loader.LoadOnce(_load)


def available() -> bool:
    """Whether the compiled slicing kernel is built and enabled."""
    return library() is not None


def vectorised() -> bool:
    """Whether the kernel runs its AVX-512 path on this CPU (its scalar path elsewhere; which
    one pays against numba: bench/README.md)."""
    fn = library()
    return fn is not None and bool(fn.vectorised)


class SlicePlan:
    """Everything the kernel needs but the scan, for one table version (arrays kept alive here).

    Args:
        dx, dy, ox, oy: (H*W,) float32 rays in the target frame, pixel order.
        r_thr: (H*W,) float32 far-field thresholds, rounded up, pixel order.
        bins: (start, step) of the far-field bins per row (:func:`converters.slices.spec.aligned_rows`).
        keys: (start, step) of the tie-key columns per row (key = u*W + column).
        qf, qn: uint bit masks of the qualifiers, (H,) per row or (H*W,) in pixel order.
        lo, hi: (>= S, H) float32 band intervals (rows beyond S ignored).
        lim_lo, lim_hi: planar range limits (metres); g_min, g_inc, g_full: the grid.
        inf_value, fill_value: (S,) float32 decoded values.
        key_to_pos: (H*W,) int64 tie key -> pixel, or None (key = pixel).

    Raises:
        RuntimeError: the compiled kernel is not available (:func:`available`).
    """

    def __init__(self, *, height: int, width: int, n_slices: int,
                 dx: np.ndarray[Any, Any], dy: np.ndarray[Any, Any],
                 ox: np.ndarray[Any, Any], oy: np.ndarray[Any, Any],
                 r_thr: np.ndarray[Any, Any],
                 bins: tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]],
                 keys: tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]],
                 qf: np.ndarray[Any, Any], qn: np.ndarray[Any, Any],
                 lo: np.ndarray[Any, Any], hi: np.ndarray[Any, Any],
                 lim_lo: float, lim_hi: float, g_min: float, g_inc: float, g_full: bool,
                 inf_value: np.ndarray[Any, Any], fill_value: np.ndarray[Any, Any],
                 key_to_pos: np.ndarray[Any, Any] | None) -> None:
        fn = library()
        if fn is None:
            raise RuntimeError("the compiled slicing kernel is not available")
        self._fn = fn                          # fetched once per plan, not per scan
        n = height * width
        f32 = np.float32

        def arr(a: np.ndarray[Any, Any], dtype: Any, size: int) -> np.ndarray[Any, Any]:
            out = np.ascontiguousarray(a, dtype)
            if out.size != size:
                raise ValueError(f"kernel table of {out.size} elements, expected {size}")
            return out

        groups = -(-width // 8)
        thr = arr(r_thr, f32, n).reshape(height, width)
        padded = np.zeros((height, groups * 8), f32)
        padded[:, :width] = thr
        self.q_per_pixel = qf.size != height
        q_size = n if self.q_per_pixel else height
        keep = {
            "dx": arr(dx, f32, n), "dy": arr(dy, f32, n), "ox": arr(ox, f32, n),
            "oy": arr(oy, f32, n), "r_thr": thr.reshape(-1),
            "group_thr": np.ascontiguousarray(padded.reshape(height, groups, 8).max(axis=2)),
            "bin_start": arr(bins[0], np.int64, height), "bin_step": arr(bins[1], np.int64, height),
            "key_start": arr(keys[0], np.int64, height), "key_step": arr(keys[1], np.int64, height),
            "qf": arr(qf, np.uint32, q_size), "qn": arr(qn, np.uint32, q_size),
            "lo": arr(lo[:n_slices], f32, n_slices * height),
            "hi": arr(hi[:n_slices], f32, n_slices * height),
            "inf_value": arr(inf_value, f32, n_slices),
            "fill_value": arr(fill_value, f32, n_slices)}
        if key_to_pos is not None:
            keep["key_to_pos"] = arr(key_to_pos, np.int64, n)
        self._keep = keep
        self.n_slices, self.width = n_slices, width
        self.plan = _Plan(height=height, width=width, n_slices=n_slices,
                          q_per_pixel=int(self.q_per_pixel), lim_lo=lim_lo, lim_hi=lim_hi,
                          g_min=g_min, g_inc=g_inc, g_full=int(g_full),
                          **{k: v.ctypes.data for k, v in keep.items()})
        self._plan_ref = ctypes.byref(self.plan)

    def run(self, r: np.ndarray[Any, Any], intensity: np.ndarray[Any, Any] | None,
            winners: bool = False
            ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any], np.ndarray[Any, Any] | None]:
        """All slices of one scan.

        Args:
            r: (H*W,) float32 ranges (metres), pixel order.
            intensity: (H*W,) intensity image of any real dtype, or None.
            winners: also return the winners' tie keys.

        Returns:
            (ranges, ints, keys): (S*W,) float32 slices back to back; float32 intensities of
            the winners (0 for an empty bin; empty without ``intensity``); int64 tie keys (-1
            for an empty bin) or None.
        """
        size = self.n_slices * self.width
        r = np.ascontiguousarray(r, np.float32)
        if r.size != self.plan.height * self.width:
            raise ValueError(f"{r.size} ranges, expected {self.plan.height * self.width}")
        ranges = np.empty(size, np.float32)
        ints = np.empty(size if intensity is not None else 0, np.float32)
        keys = np.empty(size, np.int64) if winners else None
        i_addr, i_type = None, 0
        if intensity is not None:
            img = np.ascontiguousarray(intensity)
            code = _loader.type_code(img)
            if code is None:                      # another dtype: cast to float32 first
                img, code = img.astype(np.float32), 0
            if img.size != r.size:
                raise ValueError(f"{img.size} intensities, expected {r.size}")
            i_addr, i_type = img.ctypes.data, code
        status = self._fn(self._plan_ref, r.ctypes.data, i_addr, i_type, ranges.ctypes.data,
                    ints.ctypes.data if intensity is not None else None,
                    None if keys is None else keys.ctypes.data, SIMD)
        if status == -1:
            raise MemoryError("the slicing kernel could not allocate its reduction rows")
        if status != 0:
            raise RuntimeError(f"the slicing kernel failed with status {status}")
        return ranges, ints, keys
