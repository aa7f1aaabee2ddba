"""Minimal PCD v0.7 reader for the ground-truth clouds in tests/data (binary x y z float32)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np


def read_xyz(path: str | Path) -> np.ndarray[Any, Any]:
    """(N, 3) float32 x y z of a binary PCD v0.7 file whose fields start with x y z (F 4)."""
    raw = Path(path).read_bytes()
    header, sep, body = raw.partition(b"DATA binary\n")
    if not sep:
        raise ValueError(f"{path}: not a binary PCD file")
    fields = dict(line.split(b" ", 1) for line in header.splitlines() if b" " in line)
    names, sizes = fields[b"FIELDS"].split(), [int(v) for v in fields[b"SIZE"].split()]
    if names[:3] != [b"x", b"y", b"z"] or sizes[:3] != [4, 4, 4] \
            or fields[b"TYPE"].split()[:3] != [b"F"] * 3:
        raise ValueError(f"{path}: expected leading float32 fields x y z")
    count, step = int(fields[b"POINTS"]), sum(sizes)
    rows = np.frombuffer(body, np.uint8, count * step).reshape(count, step)
    return rows[:, :12].copy().view("<f4")
