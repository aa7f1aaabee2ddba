"""Minimal PCD v0.7 reader for the test fixtures: binary, float32 x y z fields (others skipped)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def read_pcd(path: str | Path) -> np.ndarray:
    """(N, 3) float32 x, y, z of a binary PCD v0.7 file (fields of any PCD type)."""
    raw = Path(path).read_bytes()
    header: dict[str, list[str]] = {}
    pos = 0
    while True:
        end = raw.index(b"\n", pos)
        key, *values = raw[pos:end].decode("ascii").split()
        pos = end + 1
        header[key] = values
        if key == "DATA":
            break
    if header["DATA"] != ["binary"]:
        raise ValueError(f"PCD DATA {header['DATA']}: only binary is supported")
    kinds = {"F": "f", "I": "i", "U": "u"}
    dtype = np.dtype([(f, f"<{kinds[t]}{s}", (int(c),) if int(c) > 1 else ())
                      for f, t, s, c in zip(header["FIELDS"], header["TYPE"], header["SIZE"],
                                            header.get("COUNT", ["1"] * len(header["FIELDS"])))])
    points = np.frombuffer(raw, dtype, int(header["POINTS"][0]), pos)
    return np.stack([points[k].astype(np.float32) for k in ("x", "y", "z")], axis=-1)

