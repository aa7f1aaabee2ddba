"""Question 3a: SI metres as float32 vs integer units: worst round-trip error over each range.

For each sensor the native range word (Ouster: uint32 mm; Velodyne: uint16 in 2 mm units, as
``velodyne_pointcloud``'s DISTANCE_RESOLUTION; Hesai: 4 mm units, as Nebula's DISTANCE_UNIT) is
converted to float32 metres for EVERY raw value up to the sensor's maximum range, exactly as
:func:`lidarscan.range_m` does (``float32(raw * unit)``), and back. The table gives the worst
error and whether every raw value comes back exactly; the plot shows the error against range for
float32 metres and for the integer encodings a ``range_multiplier`` allows.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np

from converters.edge.evidence._common import IMG, Block, table

__all__ = ["SENSORS", "blocks", "measure", "plot"]

#: (label, native unit in m (None: not an integer range), max range m, source of the max range)
SENSORS: tuple[tuple[str, float | None, float, str], ...] = (
    ("Ouster OS-0", 0.001, 120.0, "LidarInfo.range_max of the OS-0-32 fixture"),
    ("Ouster OS-1", 0.001, 240.0, "LidarInfo.range_max of the OS-1-128 fixture"),
    ("Ouster OS-2", 0.001, 450.0, "LidarInfo.range_max of the OS-2-128 fixture"),
    ("Velodyne VLP-16 / HDL", 0.002, 130.0, "velodyne_pointcloud DISTANCE_MAX"),
    ("Hesai (XT32, AT128, Pandar)", 0.004, 262.14, "uint16 x 4 mm"),
    ("Livox Mid-360 (int32 mm x,y,z)", None, 70.0, "datasheet 70 m"),
)


def f32_spacing(r: np.ndarray[Any, Any] | float) -> np.ndarray[Any, Any]:
    """Distance between adjacent float32 values at ``r`` metres (np.spacing in float32)."""
    return np.spacing(np.asarray(r, np.float32)).astype(np.float64)


def roundtrip(unit: float, max_range: float) -> dict[str, Any]:
    """Every raw value 0..max_range/unit through float32 metres and back.

    Returns:
        {"count", "max_err_um" (|float32(raw*unit) - raw*unit| in µm), "exact" (all raw values
        recovered by rint(f32 / unit)), "at_m" (range of the worst error)}.
    """
    raw = np.arange(0, round(max_range / unit) + 1, dtype=np.int64)
    exact_m = raw * unit
    as_f32 = (raw.astype(np.float64) * unit).astype(np.float32)
    err = np.abs(as_f32.astype(np.float64) - exact_m)
    worst = int(np.argmax(err))
    back = np.rint(as_f32.astype(np.float64) / unit).astype(np.int64)
    return {"count": int(raw.size), "max_err_um": float(err[worst] * 1e6),
            "exact": bool(np.array_equal(back, raw)), "at_m": float(exact_m[worst])}


@lru_cache(maxsize=1)
def measure() -> list[dict[str, Any]]:
    """One record per sensor (see :data:`SENSORS`)."""
    out = []
    for label, unit, rmax, source in SENSORS:
        rec: dict[str, Any] = {"label": label, "unit": unit, "max": rmax, "source": source,
                               "half_spacing_um": float(f32_spacing(rmax) / 2 * 1e6)}
        if unit is not None:
            rec.update(roundtrip(unit, rmax))
            rec["u16_native_fits"] = rmax / unit <= 65535
        out.append(rec)
    return out


def blocks(records: list[dict[str, Any]] | None = None) -> list[Block]:
    """The ``range-error`` table."""
    records = measure() if records is None else records
    rows = []
    for rec in records:
        unit = rec["unit"]
        if unit is None:
            rows.append([rec["label"], "float (x,y,z int32 mm)", f"{rec['max']:g}",
                         f"{rec['half_spacing_um']:.2f}", "—", "—", "—",
                         f"{f32_spacing(rec['max']) * 1e6:.2f} µm spacing"])
            continue
        u16 = "yes" if rec["u16_native_fits"] else f"no (> {65535 * unit:.2f} m)"
        rows.append([rec["label"], f"{unit * 1000:g} mm", f"{rec['max']:g}",
                     f"{rec['half_spacing_um']:.2f}",
                     f"{rec['max_err_um']:.2f} (at {rec['at_m']:.3f} m)",
                     f"{rec['count']:,}".replace(",", " "),
                     "yes" if rec["exact"] else "**no**", u16])
    text = table(["sensor", "native range unit", "max range (m)",
                  "float32 worst error vs a true range at max (µm, half spacing)",
                  "float32 worst error on native values (µm)", "native values checked",
                  "every native value recovered from float32", "uint16 in native unit fits"],
                 rows, ["l", "l", "r", "r", "r", "r", "l", "l"])
    return [Block("range-error", text)]


def plot(path: Any = None) -> Any:
    """Error vs range: float32 metres, uint32 mm, uint16 2 mm / 4 mm, uint16 mm (clips)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    r = np.geomspace(0.1, 500.0, 4000)
    fig, ax = plt.subplots(figsize=(12, 5.5), dpi=100)
    ax.step(r, f32_spacing(r) / 2 * 1e3, where="post", color="#1f77b4", lw=2,
            label="float32 metres: worst error (half spacing)")
    mm = np.arange(100, 450_001, 97)
    f32 = (mm * 0.001).astype(np.float32).astype(np.float64)
    ax.plot(mm * 0.001, np.abs(f32 - mm * 0.001) * 1e3 + 1e-9, ".", ms=1.5, color="#17becf",
            alpha=0.5, label="float32 of Ouster mm values: measured error")
    ax.hlines(0.5, 0.1, 500, color="#2ca02c", lw=2, label="integer mm (uint32): ±0.5 mm")
    ax.hlines(1.0, 0.1, 131.07, color="#ff7f0e", lw=2,
              label="uint16 × 2 mm (Velodyne): ±1 mm, ends at 131 m")
    ax.hlines(2.0, 0.1, 262.14, color="#d62728", lw=2,
              label="uint16 × 4 mm (Hesai, ouster-ros range_image): ±2 mm, ends at 262 m")
    ax.axvline(65.535, color="#9467bd", ls="--", lw=1.2,
               label="uint16 × 1 mm ends at 65.5 m")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_ylim(1e-5, 10)
    ax.set_xlim(0.1, 500)
    ax.set_xlabel("range (m)")
    ax.set_ylabel("worst round-trip error (mm)")
    ax.set_title("Range encoding error vs range (float32 stays < 0.02 mm up to 500 m)")
    ax.grid(True, which="both", alpha=0.25)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    path = IMG / "range_error.png" if path is None else path
    fig.savefig(path)
    plt.close(fig)
    return path
