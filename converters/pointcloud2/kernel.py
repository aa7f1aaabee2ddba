"""The compiled path of :class:`converters.pointcloud2.converter.PointCloud2Converter`: what the optional
C kernel (:mod:`converters._kernels.cloud`) can write for a layout, and the arguments of one
kernel call (factored beam model or per-pixel tables, column rotations).

Conventions as in :mod:`converters.pointcloud2.converter`: x, y, z float32 metres in the info's frame,
consecutive in the point; ranges of integer channels scaled by ``_mult`` / ``_offset``; column
rotations are int64 per-row right shifts (0..W-1). :class:`_KernelWriter` is mixed into the
converter and uses its state: ``projector``, ``width``, ``_kfn`` (the selected kernel
functions), ``_r`` (the float32 range image), ``_mult`` / ``_offset``, the grid order
(``_has_shift``, ``_grid_destaggered``) and two caches (``_rolls``, ``_static_args``).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from converters.pointcloud2.fields import _Plan, _Planes
from converters._kernels import _loader
from converters._kernels import cloud as _ck
from converters.shared.cloud_layout import FieldSpec
from lidarscan.datatypes import FLOAT32
from lidarscan.errors import ConversionError


class _KernelWriter:
    """The converter's compiled-kernel methods (see the module docstring for the state used)."""

    def _kernel_plan(self, specs: Sequence[FieldSpec], raw: np.ndarray[Any, Any],
                     images: dict[str, Any]) -> _Plan | None:
        """What the kernel can write for this layout and scan: x, y, z (float32, consecutive)
        and the first float32 channel field with a kernel-readable image; None: numpy only."""
        by_source = {s.source: s for s in specs if s.source in ("x", "y", "z")}
        if len(by_source) != 3:
            return None
        xoff = by_source["x"].offset
        for k, axis in enumerate("xyz"):
            s = by_source[axis]
            if s.datatype != FLOAT32 or s.count != 1 or s.offset != xoff + 4 * k:
                return None
        raw_type = _loader.type_code(raw)
        if raw_type is None:
            return None
        if not (raw.flags.c_contiguous and raw.flags.aligned):
            raw = np.require(raw, requirements=["C", "A"])
        extra, extra_image, extra_type = None, None, 0
        for s in specs:
            if s.source != "channel" or s.datatype != FLOAT32 or s.count != 1:
                continue
            image = images.get(s.name)
            if image is None or image.ndim != 2:
                continue
            code = _loader.type_code(image)
            if code is not None:
                if not (image.flags.c_contiguous and image.flags.aligned):
                    image = np.require(image, requirements=["C", "A"])
                extra, extra_image, extra_type = s, image, code
                break
        covered = {"x", "y", "z"} | ({extra.name} if extra is not None else set())
        return _Plan(xoff, raw, raw_type, extra, extra_image, extra_type,
                     all(s.name in covered for s in specs))

    def _roll(self, scan_dest: bool) -> np.ndarray[Any, Any] | None:
        """Per-row right rotation (0..W-1, int64) taking scan columns to grid columns, or None
        when both are in the same order (the kernel's ``roll``)."""
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

    def _kernel_job(self, plan: _Plan, out: int, step: int, tables: _Planes | None,
                    factors: tuple[np.ndarray[Any, Any], ...] | None, scan_dest: bool,
                    r_out: bool) -> _ck.Job:
        """One kernel call's arguments: the factored form when ``factors`` is given, else the
        per-pixel ``tables``."""
        raw, spec, image = plan.raw, plan.extra, plan.image
        scale = 0
        if raw.dtype.kind != "f":
            scale = ((_ck.MULTIPLY if self._mult != 1.0 else 0)
                     | (_ck.OFFSET if self._offset != 0.0 else 0))
        source = factors if factors is not None else tables
        static = self._static_args                 # of the latest geometry and column order
        if static is None or static[0] is not source or static[1] != scan_dest:
            static = (source, scan_dest,
                      *self._static_kernel_args(source, factors is not None, scan_dest))
            self._static_args = static
        fn, geometry, roll_addr, keep = static[2:]
        return _ck.Job(
            fn=fn, out=out, step=int(step), xyz_offset=int(plan.xyz_offset),
            range=_ck.addr(raw), range_type=plan.raw_type,
            roll=roll_addr, width=self.width,
            scale=scale, mult=self._mult, offset=self._offset, geometry=geometry,
            extra=None if image is None else _ck.addr(image),
            extra_type=plan.extra_type,
            extra_offset=0 if spec is None else int(spec.offset),
            r_out=_ck.addr(self._r) if r_out else None,
            done=frozenset({"x", "y", "z"} | ({spec.name} if spec is not None else set())),
            keep=(raw, image, keep), factored=factors is not None)

    def _static_kernel_args(self, source: Any, factored: bool, scan_dest: bool
                            ) -> tuple[Any, tuple[int | None, ...], int | None, Any]:
        """(kernel function, geometry addresses, roll address, arrays to keep alive) of one
        geometry (factors or tables) and scan column order: the same for every scan."""
        kernels: Any = self._kfn
        roll = self._roll(scan_dest)
        geometry: tuple[int | None, ...]
        if factored:
            colshift = self._colshift()
            geometry = (None if colshift is None else _ck.addr(colshift),
                        *(_ck.addr(a) for a in source))
            return (kernels.project_rc, geometry, None if roll is None else _ck.addr(roll),
                    (roll, colshift, source))
        if source is None:                                     # unreachable: see convert()
            raise ConversionError("kernel geometry", None, "tables or factors")
        d, o, d_addr, o_addr = source.interleaved()
        return (kernels.project, (d_addr, o_addr), None if roll is None else _ck.addr(roll),
                (roll, d, o))
