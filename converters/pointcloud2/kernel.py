"""The compiled path of :class:`converters.pointcloud2.converter.PointCloud2Converter`: what the
optional C kernel (:mod:`converters._kernels.cloud`) can write for a layout (:func:`kernel_plan`)
and the arguments of one kernel call (:class:`KernelJobs`: factored beam model or per-pixel
tables, column rotations).

Conventions as in :mod:`converters.pointcloud2.converter`: x, y, z float32 metres in the info's
frame, consecutive in the point; ranges of integer channels decoded as ``raw * mult + offset``;
column rotations are int64 per-row right shifts (0..W-1), given by the converter (it owns the
grid's column order).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from converters._kernels import cloud as _ck
from converters.pointcloud2.fields import _Plan, _Planes
from converters.shared.cloud_layout import FieldSpec
from lidarscan.datatypes import FLOAT32
from lidarscan.errors import ConversionError

__all__ = ["KernelJobs", "kernel_plan"]


def _aligned(image: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """``image`` itself when C-contiguous and aligned (what the kernel reads), else a copy."""
    if image.flags.c_contiguous and image.flags.aligned:
        return image
    return np.require(image, requirements=["C", "A"])


def kernel_plan(specs: Sequence[FieldSpec], raw: np.ndarray[Any, Any],
                images: dict[str, Any]) -> _Plan | None:
    """What the kernel can write for this layout and scan: x, y, z (float32, consecutive) and
    the first float32 channel field with a kernel-readable image; None: numpy only.

    Args:
        specs: the cloud's fields.
        raw: the native range image (H, W).
        images: field name -> the scan's (H, W) channel view feeding it (None: zero-filled).
    """
    by_source = {s.source: s for s in specs if s.source in ("x", "y", "z")}
    if len(by_source) != 3:
        return None
    xoff = by_source["x"].offset
    for k, axis in enumerate("xyz"):
        s = by_source[axis]
        if s.datatype != FLOAT32 or s.count != 1 or s.offset != xoff + 4 * k:
            return None
    raw_type = _ck.DTYPE_CODES.get(raw.dtype)
    if raw_type is None:
        return None
    extra, extra_image, extra_type = None, None, 0
    for s in specs:
        if s.source != "channel" or s.datatype != FLOAT32 or s.count != 1:
            continue
        image = images.get(s.name)
        if image is None or image.ndim != 2:
            continue
        code = _ck.DTYPE_CODES.get(image.dtype)
        if code is not None:
            extra, extra_image, extra_type = s, _aligned(image), code
            break
    covered = {"x", "y", "z"} | ({extra.name} if extra is not None else set())
    return _Plan(xoff, _aligned(raw), raw_type, extra, extra_image, extra_type,
                 all(s.name in covered for s in specs))


class KernelJobs:
    """Builds the kernel calls of one converter (one LidarInfo, one range decoding).

    Args:
        kernels: the compiled entry points (:func:`converters._kernels.cloud.kernel`).
        width: W, columns of the grid.
        mult, offset: the info's range decoding (integer range channels).
    """

    def __init__(self, kernels: _ck.Kernels, width: int, mult: float, offset: float) -> None:
        self.kernels = kernels
        self.width = int(width)
        self.mult, self.offset = float(mult), float(offset)
        #: (geometry source, roll, kernel function, geometry arrays) of the latest call
        self._static: tuple[Any, ...] | None = None

    def job(self, plan: _Plan, out: Any, step: int, *, tables: _Planes | None,
            factors: tuple[np.ndarray[Any, Any], ...] | None,
            roll: np.ndarray[Any, Any] | None, colshift: np.ndarray[Any, Any] | None,
            r_out: np.ndarray[Any, Any] | None) -> _ck.Job:
        """One kernel call's arguments: the factored form when ``factors`` is given, else the
        per-pixel ``tables``.

        Args:
            plan: :func:`kernel_plan` of the layout and scan.
            out: the point buffer (``array.array('B')`` or a structured ndarray).
            step: point_step, bytes.
            tables, factors: the geometry (one of them).
            roll: per-row right rotation from scan columns to grid columns, or None.
            colshift: per-row right rotation from measurement columns to grid columns (the
                factored form), or None.
            r_out: (H, W) float32 image the kernel writes the decoded ranges into, or None.
        """
        raw, spec = plan.raw, plan.extra
        scale = 0
        if raw.dtype.kind != "f":
            scale = ((_ck.MULTIPLY if self.mult != 1.0 else 0)
                     | (_ck.OFFSET if self.offset != 0.0 else 0))
        source = factors if factors is not None else tables
        static = self._static                 # of the latest geometry and column order
        if static is None or static[0] is not source or static[1] is not roll:
            static = (source, roll, *self._geometry(source, factors is not None, colshift))
            self._static = static
        fn, geometry = static[2:]
        return _ck.Job(
            fn=fn, out=out, step=int(step), xyz_offset=int(plan.xyz_offset),
            range=raw, range_type=plan.raw_type, roll=roll, width=self.width,
            scale=scale, mult=self.mult, offset=self.offset, geometry=geometry,
            extra=plan.image, extra_type=plan.extra_type,
            extra_offset=0 if spec is None else int(spec.offset), r_out=r_out,
            done=frozenset({"x", "y", "z"} | ({spec.name} if spec is not None else set())),
            factored=factors is not None)

    def _geometry(self, source: Any, factored: bool, colshift: np.ndarray[Any, Any] | None
                  ) -> tuple[Any, tuple[np.ndarray[Any, Any] | None, ...]]:
        """(kernel function, geometry arrays) of one geometry (factors or tables)."""
        if factored:
            return self.kernels.project_rc, (colshift, *source)
        if source is None:                                     # unreachable: see convert()
            raise ConversionError("kernel geometry", None, "tables or factors")
        d, o = source.interleaved()
        return self.kernels.project, (d, o)
