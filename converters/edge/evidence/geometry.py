"""Question 4: what omitting a geometry field costs, on the REAL Ouster metadata.

For every metadata fixture the exact LidarInfo (:func:`converters.sources.ouster.metadata.info_from_metadata`)
projects the ranges with the project's projector; the same is done with a LidarInfo in which one
field is zeroed or replaced by what a simpler message would carry; the table gives the distance
between the two point sets. Ranges: the real frame of that sensor when there is one (every pixel
with a return), else 10 m on every pixel; a second column uses 100 m on every pixel, since
angular errors grow with range.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from functools import lru_cache
from typing import Any

import numpy as np

from converters.edge.evidence._common import (
    IMG,
    Block,
    fmt_int,
    load_frame,
    ouster_files,
    ouster_info,
    short_name,
    table,
)

__all__ = ["VARIANTS", "blocks", "measure", "plot"]


def _zero_origins(info: Any) -> Any:
    return dataclasses.replace(info, beam_origins=np.zeros(0), beam_range_offsets=np.zeros(0))


def _zero_beam_azimuth(info: Any) -> Any:
    return dataclasses.replace(info, beam_azimuth_offsets=np.zeros(0))


def _mean_beam_azimuth(info: Any) -> Any:
    beta = np.asarray(info.beam_azimuth_offsets, np.float64)
    return dataclasses.replace(info, beam_azimuth_offsets=np.full_like(beta, beta.mean()))


def _uniform_vertical(info: Any) -> Any:
    phi = np.asarray(info.vertical_angles, np.float64)
    return dataclasses.replace(info, vertical_angles=np.linspace(phi.max(), phi.min(), phi.size))


def _fov_horizontal(info: Any) -> Any:
    width = int(info.width)
    inclusive = 2 * np.pi * (1 - np.arange(width) / (width - 1))  # min + i/(W-1)*span
    return dataclasses.replace(info, horizontal_angles=inclusive)


def _no_translation(info: Any) -> Any:
    matrix = np.asarray(info.lidar_to_sensor_transform, np.float64).reshape(4, 4).copy()
    if not np.any(matrix):
        matrix = np.eye(4)
    matrix[:3, 3] = 0.0
    return dataclasses.replace(info, lidar_to_sensor_transform=matrix.reshape(16))


def _no_transform(info: Any) -> Any:
    return dataclasses.replace(info, lidar_to_sensor_transform=np.eye(4).reshape(16))


#: label -> (what the receiver would use instead, info transform or None for "destagger").
VARIANTS: dict[str, tuple[str, Callable[[Any], Any] | None]] = {
    "beam-origin offset (`beam_origins`, `beam_range_offsets`)":
        ("ρ·d from the lidar origin (the 2026 draft)", _zero_origins),
    "per-beam azimuth (`beam_azimuth_offsets`)": ("β_u = 0", _zero_beam_azimuth),
    "per-beam azimuth → one row-averaged value": ("β_u = mean β", _mean_beam_azimuth),
    "per-beam elevation → uniform spacing (FOV fallback)":
        ("linspace(max φ, min φ, H)", _uniform_vertical),
    "`horizontal_angles` → FOV fallback, inclusive": ("2π(1 − c/(W−1))", _fov_horizontal),
    "`is_destaggered` flag / `pixel_shift_by_row`":
        ("staggered image read as destaggered", None),
    "`lidar_to_sensor_transform` translation": ("rotation only (yaw kept)", _no_translation),
    "`lidar_to_sensor_transform` (whole)": ("identity: points in the lidar frame", _no_transform),
}


def _ranges(meta: Any, frame_path: Any, info: Any) -> tuple[np.ndarray[Any, Any], str]:
    if frame_path is None:
        return np.full((int(info.height), int(info.width)), 10.0, np.float32), "10 m everywhere"
    from converters.sources.ouster.metadata import scan_from_frame
    from lidarscan import channel
    scan = scan_from_frame(load_frame(frame_path), info, as_dataclass=True)
    return np.array(channel(scan, "range")), "real frame"


def _errors(info: Any, variant: Callable[[Any], Any] | None, ranges: np.ndarray[Any, Any]
            ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
    """(per-pixel error in m, per-pixel angle between the two directions in rad)."""
    from lidarscan.geometry import beam_tables, exact_xyz
    good = exact_xyz(info, ranges)
    d_good, _ = beam_tables(info)
    if variant is None:
        bad = exact_xyz(info, ranges, destaggered=True)
        d_bad, _ = beam_tables(info)
        shifts = np.asarray(info.pixel_shift_by_row, np.int64)
        index = (np.arange(int(info.width))[None, :] - shifts[:, None]) % int(info.width)
        d_bad = np.take_along_axis(d_bad, index[..., None], axis=1)
    else:
        other = variant(info)
        bad = exact_xyz(other, ranges)
        d_bad, _ = beam_tables(other)
    err = np.linalg.norm(bad - good, axis=-1)
    cosang = np.clip(np.sum(d_good * d_bad, axis=-1), -1.0, 1.0)
    return err, np.arccos(cosang)


@lru_cache(maxsize=1)
def measure() -> list[dict[str, Any]]:
    """One record per (metadata file, omitted field)."""
    out = []
    for meta, frame_path in ouster_files():
        info = ouster_info(meta)
        ranges, source = _ranges(meta, frame_path, info)
        valid = np.isfinite(ranges) & (ranges > 0)
        far = np.full_like(ranges, 100.0)
        col_pitch = 2 * np.pi / int(info.width)
        for label, (instead, variant) in VARIANTS.items():
            err, ang = _errors(info, variant, ranges)
            err100, _ = _errors(info, variant, far)
            out.append({"sensor": short_name(meta), "source": source, "label": label,
                        "instead": instead, "max_mm": float(err[valid].max() * 1e3),
                        "mean_mm": float(err[valid].mean() * 1e3),
                        "max100_mm": float(err100.max() * 1e3),
                        "max_deg": float(np.degrees(ang.max())),
                        "max_col": float(ang.max() / col_pitch),
                        "per_beam_10m": None, "n_valid": int(valid.sum())})
    return out


def per_beam(meta: Any, labels: tuple[str, ...], range_m: float = 10.0
             ) -> dict[str, np.ndarray[Any, Any]]:
    """Max error per beam (mm) at ``range_m`` on every pixel, for the given variants."""
    info = ouster_info(meta)
    ranges = np.full((int(info.height), int(info.width)), range_m, np.float32)
    return {label: _errors(info, VARIANTS[label][1], ranges)[0].max(axis=1) * 1e3
            for label in labels}


def _num(x: float) -> str:
    if x >= 100:
        return f"{x:.0f}"
    if x >= 1:
        return f"{x:.1f}"
    return f"{x:.3f}"


def blocks(records: list[dict[str, Any]] | None = None) -> list[Block]:
    """The ``geometry`` table."""
    records = measure() if records is None else records
    rows = [[f"{r['sensor']} ({r['source']}, {fmt_int(r['n_valid'])} returns)",
             r["label"], r["instead"], _num(r["max_mm"]), _num(r["mean_mm"]),
             _num(r["max100_mm"]), f"{r['max_deg']:.3f}", f"{r['max_col']:.2f}"]
            for r in records]
    text = table(["metadata (ranges)", "field omitted", "receiver uses instead",
                  "max error (mm)", "mean error (mm)", "max error at 100 m (mm)",
                  "max direction error (°)", "… in columns (360°/W)"], rows,
                 ["l", "l", "l", "r", "r", "r", "r", "r"])
    return [Block("geometry", text)]


PLOT_LABELS = ("beam-origin offset (`beam_origins`, `beam_range_offsets`)",
               "per-beam azimuth (`beam_azimuth_offsets`)",
               "per-beam elevation → uniform spacing (FOV fallback)",
               "`lidar_to_sensor_transform` translation")


def plot(path: Any = None, range_m: float = 10.0) -> Any:
    """Max error per beam at 10 m for each real metadata file, one panel per sensor."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = ouster_files()
    fig, axes = plt.subplots(1, len(files), figsize=(5.2 * len(files), 4.8), dpi=100,
                             sharey=True)
    axes = np.atleast_1d(axes)
    colors = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd")
    for ax, (meta, _) in zip(axes, files):
        curves = per_beam(meta, PLOT_LABELS, range_m)
        for (label, values), color in zip(curves.items(), colors):
            ax.plot(np.arange(values.size), np.maximum(values, 0.1), color=color, lw=1.4,
                    label=label.replace("`", ""))
        ax.set_yscale("log")
        ax.set_ylim(0.1, 3000)
        ax.set_title(short_name(meta))
        ax.set_xlabel("beam (row 0 = top)")
        ax.grid(True, which="both", alpha=0.25)
    axes[0].set_ylabel(f"max error over the row at {range_m:g} m (mm, floor 0.1)")
    axes[0].legend(fontsize=7, loc="lower left")
    fig.suptitle("What omitting a geometry field costs, per beam (real Ouster metadata, "
                 f"every pixel at {range_m:g} m)")
    fig.tight_layout()
    path = IMG / "geometry_per_beam.png" if path is None else path
    fig.savefig(path)
    plt.close(fig)
    return path
