"""The numpy reference path of :class:`converters.pointcloud2.converter.PointCloud2Converter`: row rolling
(destagger / restagger), the per-conversion plan records and the field writers.

Conventions as in :mod:`converters.pointcloud2.converter`: grids are (H, W) structured arrays over the
output buffer (little endian, ``point_step`` itemsize); x, y, z float32 metres in the info's
frame, ``r * D + O`` from the projector's float32 tables; ranges NaN (the canonical quiet NaN)
where there is no return; times int64 ns. A converter holds one :class:`FieldWriter` (its
scratch images, range decoding and grid column order) and hands it each conversion's
:class:`_Job`.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from converters._kernels import cloud as _ck
from converters.shared.cloud_layout import FieldSpec
from lidarscan.datatypes import FLOAT32, dtype_of
from lidarscan.errors import ConversionError

_NS = 1_000_000_000


# ================================================================================ row rolling

def _shift_groups(shifts: np.ndarray[Any, Any], width: int) -> list[tuple[Any, int]]:
    """Rows grouped by shift (mod W): (slice or index array, shift) pairs."""
    values = np.asarray(shifts, dtype=np.int64) % max(width, 1)
    groups: list[tuple[Any, int]] = []
    for value in np.unique(values):
        rows = np.flatnonzero(values == value)
        step = int(rows[1] - rows[0]) if rows.size > 1 else 1
        if rows.size == 1 or np.all(np.diff(rows) == step):
            sel: Any = slice(int(rows[0]), int(rows[-1]) + 1, step)
        else:
            sel = rows
        groups.append((sel, int(value)))
    return groups


def _roll_into(dst: np.ndarray[Any, Any], src: np.ndarray[Any, Any],
               groups: list[tuple[Any, int]] | None, sign: int) -> None:
    """``dst[u, (c + sign * s_u) mod W] = src[u, c]`` (destagger: sign +1, restagger: -1).

    ``dst`` may be a strided field view of another dtype (values are cast).
    """
    if groups is None:
        dst[...] = src
        return
    width = src.shape[1]
    for rows, shift in groups:
        k = (sign * shift) % width
        if k == 0:
            dst[rows] = src[rows]
        else:
            dst[rows, k:] = src[rows, :width - k]
            dst[rows, :k] = src[rows, width - k:]


# ======================================================================== plan records

def _xy_pair(grid: np.ndarray[Any, Any], specs: Sequence[FieldSpec]
             ) -> np.ndarray[Any, Any] | None:
    """complex64 (H, W) view of adjacent float32 x, y fields of a C-contiguous grid, or None."""
    by_name = {s.name: s for s in specs}
    sx, sy = by_name.get("x"), by_name.get("y")
    if (sx is None or sy is None or sx.source != "x" or sy.source != "y"
            or not sx.datatype == FLOAT32 == sy.datatype or sy.offset != sx.offset + 4
            or not grid.flags.c_contiguous):
        return None
    # a plain ndarray over the buffer (a structured-field view of the same bytes makes numpy's
    # ufuncs take a much slower path)
    return np.ndarray(grid.shape, np.complex64, buffer=grid, offset=sx.offset,
                      strides=grid.strides)


@dataclasses.dataclass
class _Block:
    rows: slice
    groups: list[tuple[Any, int]] | None      # destagger row groups, relative to rows.start


@dataclasses.dataclass
class _Job:
    rays: Any                                 # converters.shared.scan_rays.ScanRays
    raw: np.ndarray[Any, Any]
    grid: np.ndarray[Any, Any]
    pair: np.ndarray[Any, Any] | None
    specs: Sequence[FieldSpec]
    tables: _Planes | None                    # None: the kernel's factored form does x, y, z
    images: dict[str, Any]
    times: np.ndarray[Any, Any] | None
    ref: int
    stamp_ns: int
    scan_dest: bool
    kernel: _ck.Job | None = None


@dataclasses.dataclass(frozen=True)
class _Plan:
    """What the kernel writes for one layout and scan
    (:func:`converters.pointcloud2.kernel.kernel_plan`)."""

    xyz_offset: int
    raw: np.ndarray[Any, Any]                 # the range image, C-contiguous and aligned
    raw_type: int                             # its kernel type code
    extra: FieldSpec | None                   # a float32 channel field, or None
    image: np.ndarray[Any, Any] | None        # its channel image
    extra_type: int
    covers_all: bool                          # x, y, z (+ extra) are all the fields


class _Planes:
    """Direction / offset tables as contiguous float32 (H, W) planes (x, y, z each), plus the
    (x, y) pairs as complex64 planes: ``r * (Dx + iDy) + (Ox + iOy)`` computes x and y in one
    pass and writes both with one strided store when the layout has y right after x."""

    def __init__(self, d: list[np.ndarray[Any, Any]], o: list[np.ndarray[Any, Any]]) -> None:
        self.d, self.o = d, o
        self._pair: tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]] | None = None
        self._interleaved: tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]] | None = None

    def interleaved(self) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
        """(D, O) as C-contiguous float32 (H, W, 3), the compiled kernel's tables."""
        if self._interleaved is None:
            self._interleaved = (np.ascontiguousarray(np.stack(self.d, -1)),
                                 np.ascontiguousarray(np.stack(self.o, -1)))
        return self._interleaved

    def pair(self) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
        if self._pair is None:
            dc = np.empty(self.d[0].shape, np.complex64)
            oc = np.empty(self.d[0].shape, np.complex64)
            dc.real, dc.imag = self.d[0], self.d[1]
            oc.real, oc.imag = self.o[0], self.o[1]
            self._pair = (dc, oc)
        return self._pair


# ======================================================================= field writers

class FieldWriter:
    """The numpy field writers of one converter.

    Args:
        height, width: the grid (H, W).
        mult, offset: the info's range decoding (integer range channels).
        has_shift: the info has pixel shifts (scan and grid column orders can differ).
        grid_destaggered: the grid's columns are destaggered.

    Attributes:
        r: (H, W) float32 decoded ranges of the latest conversion, grid order (NaN: no
            return); the compiled kernel writes it too.
    """

    def __init__(self, height: int, width: int, mult: float, offset: float, *,
                 has_shift: bool, grid_destaggered: bool) -> None:
        shape = (height, width)
        self.r = np.empty(shape, np.float32)
        self._tmp = np.empty(shape, np.float32)
        self._cplx = np.empty(shape, np.complex64)
        self._mask = np.empty(shape, bool)
        self._mask2 = np.empty(shape, bool)
        self._mult, self._offset = float(mult), float(offset)
        self._has_shift, self._grid_destaggered = bool(has_shift), bool(grid_destaggered)

    def scratch(self, rows: slice) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any],
                                            np.ndarray[Any, Any]]:
        """(r, mask, tmp): the rows ``rows`` of the range image and of two scratch images."""
        return self.r[rows], self._mask[rows], self._tmp[rows]

    def place_rows(self, dst: np.ndarray[Any, Any], src: np.ndarray[Any, Any],
                    block: _Block, scan_dest: bool) -> None:
        """Rows ``block.rows`` of a scan image (scan column order) into ``dst`` (those rows of
        the grid, grid column order)."""
        src = src[block.rows]
        if not self._has_shift or scan_dest == self._grid_destaggered:
            dst[...] = src
        else:
            _roll_into(dst, src, block.groups, 1 if self._grid_destaggered else -1)

    def ranges(self, job: _Job, block: _Block, r: np.ndarray[Any, Any],
                mask: np.ndarray[Any, Any], tmp: np.ndarray[Any, Any]) -> None:
        """Metres of the rows ``block.rows`` into ``r`` (grid order), NaN (the canonical quiet
        NaN, as the kernel writes) where there is no return: float ranges not in (0, +Inf),
        integer ranges 0 (others: ``raw * multiplier + offset`` in float32)."""
        raw = job.raw
        self.place_rows(r, raw, block, job.scan_dest)
        with np.errstate(invalid="ignore"):
            if raw.dtype.kind == "f":
                ok, bad = mask, self._mask2[block.rows]
                np.greater(r, 0, out=ok)                      # False: NaN, -Inf, 0, negative
                np.less(r, np.float32(np.inf), out=bad)       # False: +Inf, NaN
                np.logical_and(ok, bad, out=ok)
                if not ok.all():
                    np.logical_not(ok, out=bad)
                    np.copyto(r, np.float32(np.nan), where=bad)
            else:
                np.equal(r, 0, out=mask)                      # raw 0 = no return
                if self._mult != 1.0:
                    np.multiply(r, np.float32(self._mult), out=r)
                if self._offset != 0.0:
                    np.add(r, np.float32(self._offset), out=r)
                if mask.any():
                    np.copyto(r, np.float32(np.nan), where=mask)

    def deskew(self, job: _Job, times: np.ndarray[Any, Any], motion: Any,
               header_ns: int) -> None:
        """x, y, z of the whole grid moved by ``motion`` to its pose at ``header_ns`` (int64 ns),
        each pixel from its own time (``times``: (H, W) int64 ns since the scan stamp, grid
        order); the ranges must be in :attr:`r`."""
        from converters.shared.deskew import deskew_points
        r, tables, grid = self.r, job.tables, job.grid
        xyz = np.stack([r * d + o for d, o in zip(tables.d, tables.o)], axis=-1)
        moved = deskew_points(xyz, times + np.int64(job.stamp_ns), motion, header_ns)
        for k, name in enumerate("xyz"):
            if name in grid.dtype.names:
                grid[name] = moved[..., k]

    def write_xyz(self, grid: np.ndarray[Any, Any], specs: Sequence[FieldSpec],
                   r: np.ndarray[Any, Any], tables: _Planes, rows: slice,
                   pair_full: np.ndarray[Any, Any] | None) -> None:
        """x, y, z = r * D + O for the grid rows ``rows`` (float32 throughout)."""
        tmp = self._tmp[rows]
        todo = [s.name for s in specs if s.source in ("x", "y", "z")]
        if pair_full is not None:
            # x and y together: one complex64 product and one strided 8-byte store
            pair = pair_full[rows]
            dc, oc = tables.pair()
            cplx = self._cplx[rows]
            np.multiply(r, dc[rows], out=cplx)
            np.add(cplx, oc[rows], out=pair)
            todo = [n for n in todo if n not in ("x", "y")]
        for name in todo:
            k = "xyz".index(name)
            np.multiply(r, tables.d[k][rows], out=tmp)
            np.add(tmp, tables.o[k][rows], out=tmp)
            grid[name] = tmp

    def range_field(self, field: np.ndarray[Any, Any], spec: FieldSpec,
                     r: np.ndarray[Any, Any], raw: np.ndarray[Any, Any], block: _Block,
                     scan_dest: bool) -> None:
        if dtype_of(spec.datatype).kind == "f":
            field[...] = r
            return
        # integer millimetres (ouster-ros), 0 = no return
        if raw.dtype.kind in "iu" and math.isclose(self._mult, 0.001) and self._offset == 0:
            self.place_rows(field, raw, block, scan_dest)
            return
        mm = np.rint(r.astype(np.float64) * 1000.0)
        mm[np.isnan(mm)] = 0
        info = np.iinfo(dtype_of(spec.datatype))
        np.clip(mm, 0, info.max, out=mm)
        field[...] = mm

    @staticmethod
    def time_field(field: np.ndarray[Any, Any], spec: FieldSpec,
                   times: np.ndarray[Any, Any], ref: int, stamp_ns: int) -> None:
        if spec.source == "timestamp":
            sec, nsec = divmod(stamp_ns, _NS)
            field[...] = (times + np.int64(nsec)) * 1e-9 + float(sec)
            return
        rel = times - np.int64(ref)
        if spec.source == "time":
            field[...] = rel * 1e-9
            return
        lo, hi = int(rel.min(initial=0)), int(rel.max(initial=0))
        kind = dtype_of(spec.datatype)
        if kind.kind in "iu":
            limits = np.iinfo(kind)
            if lo < limits.min or hi > limits.max:
                raise ConversionError(f"field {spec.name!r}", (lo, hi),
                                      f"pixel times since the header stamp within "
                                      f"[{limits.min}, {limits.max}] ns",
                                      hint='use time_reference="first" or a float "time" field')
        field[...] = rel
