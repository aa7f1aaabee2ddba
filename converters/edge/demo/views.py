"""The PNG views of ``lidarscan demo`` (:mod:`converters.edge.demo.run`), drawn with matplotlib
(:mod:`converters.edge.demo.viz`) from the last frame of the run.

``range_image.png`` (the simulated scan, one image per channel), ``birdseye_slices.png`` (the
plain 2D lidar vs the 3D lidar's height slices), ``merged_scan.png``, ``depth_camera.png`` (the
depth image beside the camera's slice with the detected stairwell edge, :func:`hole_bins`) and
``pointcloud_topview.png``. Everything is drawn in ``base_link`` (metres, REP 103, x forward,
y left).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from converters.edge.demo.scene import LINK_FROM_OPTICAL, STAIRWELL, Pose2D, Scene

if TYPE_CHECKING:
    from converters.edge.demo.config import DemoConfig

__all__ = ["draw", "hole_bins"]


def draw(out: Path, scene: Scene, info: Any, last: dict[str, Any], config: DemoConfig
         ) -> list[Path]:
    """Write every PNG view of the run into ``out``; ``last`` holds the last frame's messages
    (see :func:`converters.edge.demo.run.run_demo`). Returns the paths written."""
    from converters.edge.demo import viz

    pose: Pose2D = last["pose"]
    base_from_odom = np.linalg.inv(pose.matrix())
    outlines = [(name, _footprint_in(base_from_odom, rect))
                for name, rect in scene.footprints(0.01, 2.0) if name not in ("floor",)]
    paths = [viz.range_image(last["scan"], info, out / "range_image.png",
                             title="Simulated OS-1-128 (destaggered), one image per channel")]
    laser_xy = viz.laserscan_xy(last["laser"], config.laser_mount)
    slice_xy = {name: viz.laserscan_xy(scan) for name, scan in last["slices"].items()}
    band = {name: f"{lo:g}..{hi:g} m" for name, (lo, hi) in config.slices.items()}
    extent = viz._extent([poly for _, poly in outlines])
    notes = _notes(base_from_odom, scene)
    panels = [("plain 2D lidar at 0.2 m: table legs only, no table top, no shelf",
               [viz.Layer("2D lidar", laser_xy, "tab:red")])]
    # the wide, faint floor_to_knee band under the table band, so the table band's walls (the
    # same walls, seen by both) stay visible on top of it
    low = [viz.Layer(f"'{name}' {band[name]}", slice_xy[name], color, size=size, alpha=alpha)
           for name, color, size, alpha in (("floor_to_knee", "tab:green", 12.0, 0.35),
                                            ("table", "tab:orange", 2.5, 1.0))
           if name in slice_xy]
    if low:
        panels.append(("3D lidar slices: the table top appears in 'table'", low))
    rest = [viz.Layer(f"'{name}' {band[name]}", xy, "tab:blue")
            for name, xy in slice_xy.items() if name not in ("table", "floor_to_knee")]
    if rest:
        panels.append(("3D lidar slice 'full': table top and overhanging shelf", rest))
    paths.append(viz.birdseye(out / "birdseye_slices.png", panels, outlines=outlines,
                              notes=notes, extent=extent))
    bins = _camera_bins(last, config)          # the camera scan sliced once for both views
    if last["merged"] is not None:
        xy, edge, _ = bins
        well = ("stairwell (down; below every lidar band)",
                _footprint_in(base_from_odom, STAIRWELL), "#d9a07a")
        mount = config.camera_mount
        camera = ("depth camera (its slice sees the stairwell's edge)", float(mount[0, 3]),
                  float(mount[1, 3]), float(np.arctan2(mount[1, 0], mount[0, 0])), "tab:cyan")
        paths.append(viz.birdseye(
            out / "merged_scan.png",
            [("merged scan (slice 'full' + 2D lidar + camera slice) over the plain 2D lidar",
              [viz.Layer("2D lidar alone", laser_xy, "tab:red", size=14.0, alpha=0.35),
               viz.Layer("merged", viz.laserscan_xy(last["merged"]), "tab:purple",
                         size=2.5),
               viz.Layer("of which the camera slice's hole edge (stairwell)",
                         xy[edge], "tab:brown", size=6.0)])],
            outlines=outlines, notes=notes, extent=extent, areas=[well], markers=[camera]))
    paths.append(_draw_camera(out / "depth_camera.png", last, config, bins, base_from_odom,
                              outlines))
    paths.append(viz.cloud_topview(last["cloud"], out / "pointcloud_topview.png",
                                   extrinsics=config.lidar_mount, extent=extent,
                                   title="PointCloud2 (organized 128x2048) in base_link, "
                                         "coloured by height"))
    return paths


def _camera_bins(last: dict[str, Any], config: DemoConfig
                 ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any], np.ndarray[Any, Any]]:
    """The camera slice's bins: (N, 2) base_link x, y, and two (N,) masks: hole edge
    (:func:`hole_bins` against the same slice without hole detection), band (finite, not an
    edge)."""
    from converters.edge.demo.config import camera_slicer

    optical_mount = config.camera_mount @ LINK_FROM_OPTICAL
    plain = camera_slicer(last["camera_info"], optical_mount, config, holes=False).convert(
        last["camera_scan"])["camera"]
    cut = last["camera_slice"]
    ranges = np.asarray(cut.ranges, np.float64)
    angles = cut.angle_min + cut.angle_increment * np.arange(ranges.size)
    edge = hole_bins(cut, plain)
    band = np.isfinite(ranges) & ~edge
    return np.stack([ranges * np.cos(angles), ranges * np.sin(angles)], 1), edge, band


def hole_bins(with_holes: Any, without: Any) -> np.ndarray[Any, np.dtype[np.bool_]]:
    """(N,) bool: bins of a slice with holes whose obstacle is a hole edge, given the same slice
    without holes (the edge is nearer than anything the band saw)."""
    a = np.asarray(with_holes.ranges, np.float32)
    b = np.asarray(without.ranges, np.float32)
    with np.errstate(invalid="ignore"):
        return np.isfinite(a) & ~(a >= b)


def _draw_camera(path: Path, last: dict[str, Any], config: DemoConfig,
                 bins: tuple[np.ndarray[Any, Any], ...], base_from_odom: np.ndarray[Any, Any],
                 outlines: list[tuple[str, np.ndarray[Any, Any]]]) -> Path:
    """The depth image and the camera's slice with the detected stair edge (``bins``: the
    slice's :func:`_camera_bins`)."""
    from converters.edge.demo import viz

    xy, edge, band = bins
    image = last["image"]
    depth = np.frombuffer(bytes(image.data), "<u2").reshape(image.height, image.width)
    x0, y0, x1, y1 = STAIRWELL
    well = _footprint_in(base_from_odom, (x0, y0, x1, y1))
    fig = viz._figure(12.0, 5.4)
    ax_img, ax_top = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1.15, 1.0]})
    shown = ax_img.imshow(np.where(depth > 0, depth / 1000.0, np.nan), cmap=viz._cmap("viridis"))
    fig.colorbar(shown, ax=ax_img, shrink=0.7, label="depth z [m] (black: no measurement)")
    ax_img.set_title(f"depth image {image.width}x{image.height} 16UC1: the stairs go down "
                     "ahead, right", fontsize=9)
    ax_img.set_axis_off()
    for _, poly in outlines:
        ax_top.fill(poly[:, 0], poly[:, 1], color="0.88", zorder=0)
    ax_top.fill(well[:, 0], well[:, 1], color="#f3d9c9", zorder=0, label="stairwell (down)")
    ax_top.plot(well[:, 0], well[:, 1], color="tab:brown", lw=0.8, zorder=1)
    lo, hi = config.camera_slice
    ax_top.scatter(xy[band, 0], xy[band, 1], s=4, color="tab:blue", linewidths=0, zorder=3,
                   label=f"band {lo:g}..{hi:g} m ({int(band.sum())} bins)")
    ax_top.scatter(xy[edge, 0], xy[edge, 1], s=7, color="tab:red", linewidths=0, zorder=4,
                   label=f"hole edge ({int(edge.sum())} bins)")
    ax_top.add_patch(viz._robot_patch())
    ax_top.set_xlim(-0.5, 4.5)
    ax_top.set_ylim(-2.5, 2.5)
    ax_top.set_aspect("equal")
    ax_top.grid(True, lw=0.3)
    ax_top.set_xlabel("x [m] (forward)")
    ax_top.set_ylabel("y [m] (left)")
    ax_top.set_title("camera slice in base_link with hole detection: the drop is an obstacle",
                     fontsize=9)
    ax_top.legend(loc="upper left", fontsize=7, markerscale=2, framealpha=0.9)
    return viz._save(fig, path)


def _footprint_in(matrix: np.ndarray[Any, Any], rect: tuple[float, float, float, float]
                  ) -> np.ndarray[Any, Any]:
    x0, y0, x1, y1 = rect
    corners = np.array([[x0, y0, 0, 1], [x1, y0, 0, 1], [x1, y1, 0, 1], [x0, y1, 0, 1],
                        [x0, y0, 0, 1]], dtype=np.float64)
    out: np.ndarray[Any, Any] = (corners @ matrix.T)[:, :2]
    return out


def _notes(base_from_odom: np.ndarray[Any, Any], scene: Scene) -> list[tuple[str, float, float]]:
    notes = []
    for name in ("table", "shelf"):
        boxes = [b for b in scene.boxes if b.name == name]
        top = max(boxes, key=lambda b: b.hi[2])
        centre = np.array([(top.lo[0] + top.hi[0]) / 2, (top.lo[1] + top.hi[1]) / 2, 0.0, 1.0])
        x, y = (base_from_odom @ centre)[:2]
        label = f"{name} top {top.lo[2]:.2f}..{top.hi[2]:.2f} m"
        notes.append((label, float(x), float(y)))
    return notes
