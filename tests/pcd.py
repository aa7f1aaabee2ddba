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


def nearest_within(query: np.ndarray, ref: np.ndarray, tol: float) -> np.ndarray:
    """(N,) distance from each query point to its nearest ``ref`` point, +inf beyond ``tol``.

    Uses scipy's cKDTree when installed, else a grid hash with cells of ``tol`` (27 cells).
    """
    query = np.asarray(query, np.float64).reshape(-1, 3)
    ref = np.asarray(ref, np.float64).reshape(-1, 3)
    try:
        from scipy.spatial import cKDTree
    except ImportError:
        pass
    else:
        dist, _ = cKDTree(ref).query(query, distance_upper_bound=tol)
        return np.where(dist <= tol, dist, np.inf)
    cells = np.floor(ref / tol).astype(np.int64)
    lo = cells.min(0) - 1
    dims = cells.max(0) - lo + 2
    key_of = lambda c: ((c[:, 0] - lo[0]) * dims[1] + (c[:, 1] - lo[1])) * dims[2] + (c[:, 2] - lo[2])  # noqa: E731
    keys = key_of(cells)
    order = np.argsort(keys, kind="stable")
    keys, ref = keys[order], ref[order]
    qcells = np.floor(query / tol).astype(np.int64)
    inside = np.all((qcells >= lo + 1) & (qcells < lo + dims - 1), axis=1)
    best = np.full(len(query), np.inf)
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dz in (-1, 0, 1):
                k = key_of(qcells + np.array([dx, dy, dz]))
                start = np.searchsorted(keys, k, "left")
                stop = np.searchsorted(keys, k, "right")
                stop = np.where(inside, stop, start)
                j = start.copy()
                while True:
                    live = np.flatnonzero(j < stop)
                    if live.size == 0:
                        break
                    d = np.linalg.norm(ref[j[live]] - query[live], axis=1)
                    best[live] = np.minimum(best[live], d)
                    j[live] += 1
    return np.where(best <= tol, best, np.inf)
