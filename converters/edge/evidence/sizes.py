"""Question 1a: bytes per frame and MB/s, LidarScan vs the PointCloud2 layouts drivers publish.

Every number is the length of a CDR message the project encodes (:func:`lidarscan.encode`): a
LidarScan with the canonical channels built by :func:`lidarscan.make_scan`, and a
``sensor_msgs/PointCloud2`` with each driver's field table (``_common.PC2_LAYOUTS``). Sizes do not
depend on the values, so the scans are synthetic (zeros); compression is measured on real
frames in :mod:`converters.edge.evidence.compression`.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np

from converters.edge.evidence._common import (
    IMG,
    Block,
    fmt_int,
    fmt_mb,
    have,
    load_frame,
    ouster_files,
    pointcloud2_bytes,
    short_name,
    table,
)

__all__ = ["LAYOUTS", "Layout", "blocks", "info_bytes", "plot", "scan_bytes"]

OUSTER_SINGLE = (("range", "f4"), ("intensity", "u2"), ("reflectivity", "u1"),
                 ("ambient", "u2"), ("flags", "u1"))
OUSTER_SECOND = (("range2", "f4"), ("intensity2", "u2"), ("reflectivity2", "u1"),
                 ("flags2", "u1"))
SPINNING_SINGLE = (("range", "f4"), ("intensity", "u1"))
SPINNING_SECOND = (("range2", "f4"), ("intensity2", "u1"))
LIVOX = (("range", "f4"), ("azimuth", "f4"), ("elevation", "f4"), ("reflectivity", "u1"),
         ("tag", "u1"))


@dataclass(frozen=True)
class Layout:
    """A sensor layout: grid, channels and which PointCloud2 layouts its drivers publish.

    Attributes:
        name: label in the tables.
        height, width: grid at 10 Hz.
        dual: two returns per pixel.
        channels: LidarScan channels (name, numpy dtype string).
        azimuth_per_column: the sensor reports a measured azimuth per firing (Velodyne, Hesai).
        width_20hz: columns per frame at 20 Hz (None: no 20 Hz mode).
        clouds: PointCloud2 layouts to compare with.
        family: plot group.
    """

    name: str
    height: int
    width: int
    dual: bool
    channels: tuple[tuple[str, str], ...]
    azimuth_per_column: bool
    width_20hz: int | None
    clouds: tuple[str, ...]
    family: str


def _ouster(beams: int, width: int, dual: bool) -> Layout:
    channels = OUSTER_SINGLE + (OUSTER_SECOND if dual else ())
    return Layout(f"Ouster {beams}-beam", beams, width, dual, channels, False,
                  width if width <= 1024 else None,
                  ("ouster-ros original", "velodyne XYZIRT", "x,y,z,intensity"), "ouster")


def _spinning(name: str, beams: int, width: int, dual: bool) -> Layout:
    channels = SPINNING_SINGLE + (SPINNING_SECOND if dual else ())
    return Layout(name, beams, width, dual, channels, True, width // 2,
                  ("ouster-ros original", "velodyne XYZIRT", "hesai", "x,y,z,intensity"),
                  "spinning")


LAYOUTS: tuple[Layout, ...] = tuple(
    [_ouster(b, w, d) for d in (False, True) for b in (32, 64, 128) for w in (512, 1024, 2048)]
    + [_spinning("Velodyne VLP-16", 16, 1800, False),
       _spinning("Velodyne VLP-16", 16, 1800, True),
       _spinning("32-beam Velodyne/Hesai-style", 32, 1800, False),
       _spinning("64-beam Velodyne/Hesai-style", 64, 1800, False),
       _spinning("64-beam Velodyne/Hesai-style", 64, 1800, True),
       Layout("Livox Mid-360 (non-grid, 1×N)", 1, 20000, False, LIVOX, False, 10000,
              ("livox", "x,y,z,intensity"), "livox")])


def _info(height: int, width: int) -> Any:
    import lidarscan as ls
    return ls.make_info(stamp_ns=1, frame_id="os_sensor",
                        vertical_angles=np.linspace(0.4, -0.4, height),
                        horizontal_angles=2 * np.pi * (1 - np.arange(width) / width),
                        beam_azimuth_offsets=np.zeros(height),
                        beam_origins=np.zeros(3 * height), beam_range_offsets=np.zeros(height),
                        pixel_shift_by_row=np.zeros(height, np.int32),
                        beam_ids=np.arange(height, dtype=np.uint16), as_dataclass=True)


def scan_bytes(layout: Layout, width: int | None = None) -> int:
    """CDR size of one LidarScan of the layout (header, descriptors, per-column arrays, data)."""
    import lidarscan as ls
    width = layout.width if width is None else width
    info = _info(layout.height, width)
    channels = {n: np.zeros((layout.height, width), np.dtype(t)) for n, t in layout.channels}
    scan = ls.make_scan(info, channels, 1_000_000_000,
                        column_time_offsets=np.arange(width, dtype=np.int64),
                        column_azimuth_angles=(np.zeros(width) if layout.azimuth_per_column
                                               else None),
                        as_dataclass=True)
    return len(ls.encode(scan))


def info_bytes(layout: Layout) -> int:
    """CDR size of the layout's LidarInfo (every per-beam array filled, no vendor JSON)."""
    import lidarscan as ls
    return len(ls.encode(_info(layout.height, layout.width)))


def cloud_bytes(layout: Layout, cloud: str, width: int | None = None) -> int:
    """Bytes per frame of the same data as a PointCloud2 of ``cloud`` layout.

    One point per pixel and return (organized clouds keep no-return pixels as NaN points).
    ouster-ros publishes the second return as a second cloud (``points2``): two messages.
    """
    width = layout.width if width is None else width
    if cloud == "ouster-ros original" and layout.dual:
        return 2 * pointcloud2_bytes(cloud, layout.height, width)
    returns = 2 if layout.dual else 1
    return pointcloud2_bytes(cloud, layout.height, width * returns)


ALL_CLOUDS = ("ouster-ros original", "velodyne XYZIRT", "x,y,z,intensity", "hesai", "livox")

#: The cloud each family's own driver publishes.
DRIVER = {"ouster": "ouster-ros original", "spinning": "velodyne XYZIRT", "livox": "livox"}


@lru_cache(maxsize=1)
def measure() -> list[dict[str, Any]]:
    """One record per layout: bytes per frame at 10 Hz and at 20 Hz for LidarScan and clouds."""
    out = []
    for layout in LAYOUTS:
        rec: dict[str, Any] = {"layout": layout, "scan": scan_bytes(layout),
                               "info": info_bytes(layout)}
        rec["scan20"] = scan_bytes(layout, layout.width_20hz) if layout.width_20hz else None
        for cloud in ALL_CLOUDS:
            if cloud in layout.clouds:
                rec[cloud] = cloud_bytes(layout, cloud)
                rec[cloud + "@20"] = (cloud_bytes(layout, cloud, layout.width_20hz)
                                      if layout.width_20hz else None)
            else:
                rec[cloud] = rec[cloud + "@20"] = None
        out.append(rec)
    return out


def _b(n: int | None) -> str:
    return "—" if n is None else fmt_int(n)


def _rate(n: int | None, hz: int) -> str:
    return "—" if n is None else fmt_mb(n * hz)


def blocks(records: list[dict[str, Any]] | None = None) -> list[Block]:
    """The ``sizes`` (bytes per frame) and ``rates`` (MB/s) tables."""
    records = measure() if records is None else records
    rows = []
    for rec in records:
        lay: Layout = rec["layout"]
        first = rec[DRIVER[lay.family]]
        rows.append([lay.name, f"{lay.height}×{lay.width}", "2" if lay.dual else "1",
                     _b(rec["scan"]), _b(rec["ouster-ros original"]), _b(rec["velodyne XYZIRT"]),
                     _b(rec["livox"] or rec["hesai"]),
                     _b(rec["x,y,z,intensity"]),
                     f"{first / rec['scan']:.1f}×", f"{rec['x,y,z,intensity'] / rec['scan']:.2f}×",
                     _b(rec["info"])])
    sizes = table(["layout", "H×W", "returns", "LidarScan", "ouster-ros (48 B/pt)",
                   "velodyne (22 B/pt)", "hesai / livox (26 B/pt)", "x,y,z,i (16 B/pt)",
                   "own driver's cloud ÷ LidarScan", "x,y,z,i ÷ LidarScan", "LidarInfo (once)"],
                  rows, ["l", "l", "r"] + ["r"] * 8)
    rate_rows = []
    for rec in records:
        lay = rec["layout"]
        w20 = f"{lay.height}×{lay.width_20hz}" if lay.width_20hz else "—"
        driver = DRIVER[lay.family]
        rate_rows.append([lay.name, f"{lay.height}×{lay.width}", w20, "2" if lay.dual else "1",
                          _rate(rec["scan"], 10), _rate(rec["scan20"], 20),
                          _rate(rec[driver], 10), _rate(rec[driver + "@20"], 20),
                          _rate(rec["x,y,z,intensity"], 10),
                          _rate(rec["x,y,z,intensity@20"], 20)])
    rates = table(["layout", "grid @10 Hz", "grid @20 Hz", "returns", "LidarScan 10 Hz",
                   "LidarScan 20 Hz", "driver cloud 10 Hz", "driver cloud 20 Hz",
                   "x,y,z,i 10 Hz", "x,y,z,i 20 Hz"], rate_rows,
                  ["l", "l", "l", "r"] + ["r"] * 6)
    return [Block("sizes", sizes + "\n\n" + crosscheck()),
            Block("rates", "MB/s (10^6 bytes per second), uncompressed:\n\n" + rates)]


#: converters.pointcloud2.converter preset -> the layout of PC2_LAYOUTS it reproduces
_PRESETS = {"ouster": "ouster-ros original", "velodyne": "velodyne XYZIRT",
            "hesai": "hesai", "xyzi": "x,y,z,intensity"}


def crosscheck() -> str:
    """Sizes of what the project's converters publish for the real frames vs the layout model.

    Returns a short markdown paragraph (or a not-yet-measured note when a converter is
    missing).
    """
    ok, why = have("converters.pointcloud2.converter", "to_pointcloud2")
    if not ok:
        return f"> **Not yet measured:** the cross-check with `converters.pointcloud2.converter` ({why})."
    import lidarscan as ls
    from converters.sources.ouster.metadata import info_from_metadata, scan_from_frame
    from converters.pointcloud2.converter import to_pointcloud2
    rows = []
    for meta, frame_path in ouster_files():
        if frame_path is None:
            continue
        info = info_from_metadata(meta, stamp_ns=1, as_dataclass=True)
        frame = load_frame(frame_path)
        scan = scan_from_frame(frame, info, as_dataclass=True)
        height, width = int(info.height), int(info.width)
        dual = "range2_mm" in frame
        layout = next(lay for lay in LAYOUTS if lay.family == "ouster" and lay.dual == dual
                      and (lay.height, lay.width) == (height, width))
        rows.append([short_name(meta), "LidarScan (scan_from_frame)",
                     fmt_int(len(ls.encode(scan))), fmt_int(scan_bytes(layout))])
        for preset, name in _PRESETS.items():
            cloud = to_pointcloud2(scan, info, preset=preset, organized=True)
            rows.append([short_name(meta), f"PointCloud2 preset `{preset}` (organized, "
                         "first return)", fmt_int(len(ls.encode(cloud))),
                         fmt_int(pointcloud2_bytes(name, height, width))])
        for preset in ("ouster", "velodyne"):
            cloud = to_pointcloud2(scan, info, preset=preset, organized=False)
            rows.append([short_name(meta), f"PointCloud2 preset `{preset}` (dense: returns only, "
                         f"{int(cloud.width) / (height * width):.0%} of the pixels)",
                         fmt_int(len(ls.encode(cloud))), "—"])
    return ("Cross-check on the real frames: bytes of the messages the project's importer and "
            "`converters.pointcloud2.converter` produce vs the layout model used above:\n\n"
            + table(["frame", "message", "produced", "model"], rows, ["l", "l", "r", "r"]))


def plot(records: list[dict[str, Any]], path: Any = None) -> Any:
    """Bar chart: MB per frame per sensor model, LidarScan vs the PointCloud2 layouts."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    picked = [r for r in records
              if (r["layout"].family != "ouster" or r["layout"].width in (1024, 2048))
              and not (r["layout"].family != "ouster" and r["layout"].dual)]
    labels = [f"{r['layout'].name.replace('Velodyne/Hesai-style', 'Vel./Hesai')}\n"
              f"{r['layout'].height}×{r['layout'].width}{' dual' if r['layout'].dual else ''}"
              for r in picked]
    series = [("LidarScan (canonical channels)", lambda r: r["scan"], "#1f77b4"),
              ("own driver's PointCloud2 (ouster-ros 48, velodyne 22, livox 26 B/pt)",
               lambda r: r[DRIVER[r["layout"].family]], "#d62728"),
              ("minimal x,y,z,intensity PointCloud2 (16 B/pt)",
               lambda r: r["x,y,z,intensity"], "#7f7f7f")]
    fig, ax = plt.subplots(figsize=(13, 5.5), dpi=100)
    x = np.arange(len(picked))
    bar = 0.27
    for i, (label, get, color) in enumerate(series):
        ax.bar(x + (i - 1) * bar, [get(r) / 1e6 for r in picked],  # type: ignore[no-untyped-call]
               bar, label=label, color=color)
    ax.set_xticks(x)
    ax.set_xticklabels(labels, rotation=60, ha="right", fontsize=8)
    ax.set_ylabel("MB per frame (uncompressed)")
    ax.set_title("Bytes per frame, uncompressed: LidarScan vs PointCloud2 (same pixels/points)")
    ax.grid(axis="y", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    path = IMG / "sizes.png" if path is None else path
    fig.savefig(path)
    plt.close(fig)
    return path
