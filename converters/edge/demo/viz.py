"""PNG views of scans, slices and clouds (matplotlib, Agg canvas; imported only when drawing).

No pyplot and no global backend switch: every figure is a ``matplotlib.figure.Figure`` drawn on
its own Agg canvas, so these functions work headless and do not disturb a caller's matplotlib.
Install the ``viz`` extra (``pip install 'lidarscan[viz]'``) for matplotlib.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["Layer", "birdseye", "cloud_topview", "cloud_xyz", "laserscan_xy", "range_image"]


@dataclass(frozen=True)
class Layer:
    """A set of 2D points drawn in one colour.

    Attributes:
        label: legend text.
        xy: (N, 2) float metres in the plot frame.
        color: a matplotlib colour.
        size: marker size (points^2).
        alpha: opacity.
    """

    label: str
    xy: np.ndarray[Any, Any]
    color: str
    size: float = 3.0
    alpha: float = 1.0


def _figure(width: float, height: float) -> Any:
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError as err:  # pragma: no cover - depends on the environment
        raise ImportError("PNG views need matplotlib: pip install 'lidarscan[viz]'") from err
    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _save(fig: Any, path: str | Path, dpi: int = 110) -> Path:
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=dpi)
    return out


def laserscan_xy(scan: Any, extrinsics: Any = None) -> np.ndarray[Any, np.dtype[np.float64]]:
    """Points of a LaserScan's finite in-range rays.

    Args:
        scan: ``sensor_msgs/LaserScan`` (rclpy or dataclass).
        extrinsics: optional 4x4 plot_frame_from_scan_frame; default identity.

    Returns:
        (N, 2) float64 x, y in metres (the plot frame; z is dropped after the transform).
    """
    ranges = np.asarray(scan.ranges, dtype=np.float64).reshape(-1)
    angles = float(scan.angle_min) + float(scan.angle_increment) * np.arange(ranges.size)
    keep = np.isfinite(ranges) & (ranges >= float(scan.range_min)) & \
        (ranges <= float(scan.range_max))
    r, a = ranges[keep], angles[keep]
    pts = np.stack([r * np.cos(a), r * np.sin(a), np.zeros_like(r), np.ones_like(r)], 1)
    if extrinsics is not None:
        pts = pts @ np.asarray(extrinsics, dtype=np.float64).reshape(4, 4).T
    return pts[:, :2]


_POINTFIELD_DTYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


def cloud_xyz(cloud: Any, fields: Sequence[str] = ("x", "y", "z")
              ) -> np.ndarray[Any, np.dtype[np.float64]]:
    """Finite points of a PointCloud2 as (N, len(fields)) float64 (copies, never a view).

    Raises:
        ConversionError: a requested field is missing.
    """
    from lidarscan.errors import ConversionError

    order = ">" if bool(cloud.is_bigendian) else "<"
    by_name = {f.name: f for f in cloud.fields}
    names, formats, offsets = [], [], []
    for name in fields:
        if name not in by_name:
            raise ConversionError("PointCloud2.fields", sorted(by_name), f"a field {name!r}")
        f = by_name[name]
        names.append(name)
        formats.append(order + _POINTFIELD_DTYPES[int(f.datatype)])
        offsets.append(int(f.offset))
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets,
                      "itemsize": int(cloud.point_step)})
    count = int(cloud.width) * int(cloud.height)
    data = cloud.data if isinstance(cloud.data, (bytes, np.ndarray)) else bytes(cloud.data)
    raw = np.frombuffer(data, np.uint8)
    rows = raw.reshape(int(cloud.height), int(cloud.row_step))[:, :int(cloud.width) *
                                                               int(cloud.point_step)]
    points = np.frombuffer(np.ascontiguousarray(rows).tobytes(), dtype, count)
    out = np.stack([points[n].astype(np.float64) for n in names], 1)
    return out[np.all(np.isfinite(out), axis=1)]


def range_image(scan: Any, info: Any, path: str | Path, *, title: str | None = None,
                channels: Sequence[str] | None = None) -> Path:
    """One image per channel of a LidarScan, destaggered, row 0 (highest beam) at the top.

    The range is drawn in metres with no-return pixels black; other channels are stretched
    between their 1st and 99th percentile.

    Returns:
        the PNG path.
    """
    import lidarscan

    projector = lidarscan.make_projector(info)
    names = list(channels) if channels is not None else lidarscan.channel_names(scan)
    fig = _figure(16, 1.0 + 2.0 * len(names))
    axes = fig.subplots(len(names), 1, squeeze=False)[:, 0]
    for ax, name in zip(axes, names):
        if name.startswith("range"):
            image = np.asarray(lidarscan.range_m(scan, info, name), dtype=np.float64)
            image = np.where(np.isfinite(image) & (image > 0), image, np.nan)
            label = f"{name} [m]"
        else:
            image = np.asarray(lidarscan.channel(scan, name), dtype=np.float64)
            if image.ndim == 3:
                image = image[..., 0]
            label = name
        if not bool(scan.is_destaggered):
            image = projector.destagger(image)
        finite = image[np.isfinite(image)]
        lo, hi = (np.percentile(finite, [1, 99]) if finite.size else (0.0, 1.0))
        if name.startswith("range") and finite.size:
            lo, hi = float(finite.min()), float(finite.max())
        cmap = _cmap("turbo" if name.startswith("range") else "gray")
        shown = ax.imshow(image, aspect="auto", cmap=cmap, vmin=lo, vmax=max(hi, lo + 1e-9),
                          interpolation="nearest")
        ax.set_ylabel(f"{label}\nrow")
        fig.colorbar(shown, ax=ax, pad=0.01, fraction=0.03)
    axes[-1].set_xlabel("column (destaggered; azimuth decreases to the right for Ouster)")
    fig.suptitle(title or f"LidarScan {int(scan.height)}x{int(scan.width)}")
    return _save(fig, path)


def _cmap(name: str) -> Any:
    import matplotlib

    return matplotlib.colormaps[name].with_extremes(bad="black")


def _extent(points: Sequence[np.ndarray[Any, Any]], margin: float = 0.4,
            limit: float = 30.0) -> tuple[float, float, float, float]:
    """Square view around every point given (robot at the origin included), clipped to
    +-``limit`` metres."""
    stacked = [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in points if len(p)]
    allp = np.concatenate(stacked + [np.zeros((1, 2))])
    allp = allp[np.all(np.isfinite(allp), axis=1)]
    lo = np.maximum(allp.min(axis=0) - margin, -limit)
    hi = np.minimum(allp.max(axis=0) + margin, limit)
    centre, half = (lo + hi) / 2, float(max(hi - lo)) / 2
    return (centre[0] - half, centre[0] + half, centre[1] - half, centre[1] + half)


def birdseye(path: str | Path, panels: Sequence[tuple[str, Sequence[Layer]]], *,
             outlines: Sequence[tuple[str, np.ndarray[Any, Any]]] = (),
             notes: Sequence[tuple[str, float, float]] = (),
             extent: tuple[float, float, float, float] | None = None,
             columns: int | None = None) -> Path:
    """Top views side by side (x to the right, y up; metres; the robot arrow at the origin).

    Args:
        path: PNG to write.
        panels: (title, layers) per panel; layers are drawn in order (later on top).
        outlines: (name, (K, 2) polygon) drawn in light grey in every panel (ground truth).
        notes: (text, x, y) annotations drawn in every panel.
        extent: (xmin, xmax, ymin, ymax); default: a square around the outlines, or around the
            points when there are no outlines.
        columns: panels per row (default all in one row).

    Returns:
        the PNG path.
    """
    if extent is None:
        pts = [poly for _, poly in outlines] or [layer.xy for _, ls in panels for layer in ls]
        extent = _extent(pts)
    cols = max(1, min(columns or len(panels), len(panels)))
    rows = math.ceil(len(panels) / cols)
    fig = _figure(5.6 * cols, 5.9 * rows)
    grid = fig.subplots(rows, cols, squeeze=False)
    axes = list(grid.reshape(-1))
    for ax in axes[len(panels):]:
        ax.set_visible(False)
    for ax, (title, layers) in zip(axes, panels):
        for name, poly in outlines:
            ax.fill(poly[:, 0], poly[:, 1], color="0.88", zorder=0)
            ax.plot(poly[:, 0], poly[:, 1], color="0.6", lw=0.6, zorder=1)
        for layer in layers:
            xy = np.asarray(layer.xy).reshape(-1, 2)
            ax.scatter(xy[:, 0], xy[:, 1], s=layer.size, color=layer.color, alpha=layer.alpha,
                       label=f"{layer.label} ({len(xy)} pts)", zorder=3, linewidths=0)
        for text, x, y in notes:
            ax.annotate(text, (x, y), fontsize=7, color="0.3", ha="center", va="center",
                        zorder=4)
        ax.add_patch(_robot_patch())
        ax.set_xlim(extent[0], extent[1])
        ax.set_ylim(extent[2], extent[3])
        ax.set_aspect("equal")
        ax.grid(True, lw=0.3)
        ax.set_xlabel("x [m] (forward)")
        ax.set_ylabel("y [m] (left)")
        ax.set_title(title, fontsize=9)
        ax.legend(loc="upper left", fontsize=7, markerscale=2, framealpha=0.9)
    return _save(fig, path)


def _robot_patch() -> Any:
    from matplotlib.patches import FancyArrow

    return FancyArrow(-0.2, 0.0, 0.35, 0.0, width=0.12, head_width=0.3, head_length=0.15,
                      color="black", zorder=5)


def cloud_topview(cloud: Any, path: str | Path, *, extrinsics: Any = None,
                  title: str | None = None,
                  extent: tuple[float, float, float, float] | None = None,
                  max_points: int = 300_000) -> Path:
    """Top view of a PointCloud2 coloured by height.

    Args:
        cloud: ``sensor_msgs/PointCloud2`` with x, y, z fields.
        path: PNG to write.
        extrinsics: 4x4 plot_frame_from_cloud_frame (default identity).
        title: figure title.
        extent: (xmin, xmax, ymin, ymax); default a square around the 0.5..99.5 % of points.
        max_points: points drawn at most (evenly subsampled).

    Returns:
        the PNG path.
    """
    xyz = cloud_xyz(cloud)
    if extrinsics is not None:
        matrix = np.asarray(extrinsics, dtype=np.float64).reshape(4, 4)
        xyz = xyz @ matrix[:3, :3].T + matrix[:3, 3]
    if len(xyz) > max_points:
        xyz = xyz[:: math.ceil(len(xyz) / max_points)]
    xyz = xyz[np.argsort(xyz[:, 2], kind="stable")]  # high points on top
    if extent is None:
        lo = np.percentile(xyz[:, :2], 0.5, axis=0) if len(xyz) else np.zeros(2)
        hi = np.percentile(xyz[:, :2], 99.5, axis=0) if len(xyz) else np.ones(2)
        extent = _extent([np.array([lo, hi])])
    fig = _figure(7.5, 6.5)
    ax = fig.subplots()
    shown = ax.scatter(xyz[:, 0], xyz[:, 1], c=xyz[:, 2], s=0.4, cmap="viridis", linewidths=0,
                       vmin=float(np.percentile(xyz[:, 2], 1)) if len(xyz) else 0.0,
                       vmax=float(np.percentile(xyz[:, 2], 99)) if len(xyz) else 1.0)
    fig.colorbar(shown, ax=ax, label="z [m]")
    ax.add_patch(_robot_patch())
    ax.set_xlim(extent[0], extent[1])
    ax.set_ylim(extent[2], extent[3])
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(title or f"PointCloud2 ({len(xyz)} points)", fontsize=10)
    return _save(fig, path)
