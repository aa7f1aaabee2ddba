"""Shared pieces of the evidence scripts: blocks, fixtures, tables, layouts, machine, timing.

A *block* is the text the script writes between ``<!-- evidence:NAME:begin -->`` and
``<!-- evidence:NAME:end -->`` in ``docs/proposal.md``. Deterministic blocks (sizes, errors,
counts) are compared by ``tests/test_evidence.py``; timing blocks (names starting with
``timing-``) and the ``machine`` block change from run to run and are not compared.
"""

from __future__ import annotations

import os
import platform
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "DOC",
    "IMG",
    "OUSTER_DATA",
    "PC2_LAYOUTS",
    "ROOT",
    "Block",
    "fmt_int",
    "fmt_mb",
    "have",
    "load_frame",
    "machine_lines",
    "ouster_files",
    "ouster_info",
    "pending",
    "pointcloud2_bytes",
    "table",
    "time_call",
]

#: Repository root (this file is converters/edge/evidence/_common.py).
ROOT = Path(__file__).resolve().parents[3]
DOC = ROOT / "docs" / "proposal.md"
IMG = ROOT / "docs" / "img"
OUSTER_DATA = ROOT / "tests" / "data" / "ouster"
EVIDENCE_DATA = ROOT / "tests" / "data" / "evidence"


@dataclass
class Block:
    """One generated piece of the document.

    Attributes:
        name: marker name (``evidence:NAME:begin``).
        text: markdown between the markers (no leading/trailing blank lines).
        deterministic: compared by the test (sizes, errors, counts) or not (timings, machine).
        placeholder: True when the measured capability was not available ("not yet measured").
    """

    name: str
    text: str
    deterministic: bool = True
    placeholder: bool = False
    notes: list[str] = field(default_factory=list)


def pending(name: str, what: str, reason: str, deterministic: bool = True) -> Block:
    """A clearly marked placeholder block for a measurement that could not run."""
    text = (f"> **Not yet measured:** {what}. Reason: {reason}. "
            "Run `make evidence` again once it is available.")
    return Block(name, text, deterministic, placeholder=True)


def have(module: str, *names: str) -> tuple[bool, str]:
    """Whether ``module`` imports and has every attribute in ``names`` (reason if not)."""
    import importlib
    try:
        mod = importlib.import_module(module)
    except Exception as err:  # noqa: BLE001 - any import failure means "not available"
        return False, f"`{module}` does not import ({type(err).__name__}: {err})"
    missing = [n for n in names if not hasattr(mod, n)]
    if missing:
        return False, f"`{module}` has no {', '.join(missing)}"
    return True, ""


# ------------------------------------------------------------------------------ formatting

def table(header: Sequence[str], rows: Iterable[Sequence[Any]],
          align: Sequence[str] | None = None) -> str:
    """A GitHub markdown table; ``align`` per column: "l" or "r" (default: l then r)."""
    rows = [[str(c) for c in row] for row in rows]
    if align is None:
        align = ["l"] + ["r"] * (len(header) - 1)
    rule = ["---:" if a == "r" else "---" for a in align]
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join(rule) + "|"]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def fmt_int(n: int) -> str:
    """1234567 -> '1 234 567' (thin grouping that survives any markdown renderer)."""
    return f"{int(n):,}".replace(",", " ")


def fmt_mb(nbytes: float) -> str:
    """Bytes -> MB (10^6) with 2 decimals."""
    return f"{nbytes / 1e6:.2f}"


# -------------------------------------------------------------------------------- fixtures

def ouster_files() -> list[tuple[Path, Path | None]]:
    """(metadata json, decoded frame npz or None) of every Ouster fixture, sorted by name.

    The fixtures live in ``tests/data/ouster/`` (copied from the shared data with their NOTICE).

    Raises:
        FileNotFoundError: the fixture directory is missing or has no metadata JSON.
    """
    if not OUSTER_DATA.is_dir():
        raise FileNotFoundError(f"{OUSTER_DATA} (the Ouster test fixtures)")
    out = []
    metas = sorted(OUSTER_DATA.glob("*.json"))
    for meta in metas:
        # variants of another file (e.g. "<name>_nested.json", the same sensor in another JSON
        # layout) would only repeat its numbers
        if any(m != meta and meta.stem.startswith(m.stem) for m in metas):
            continue
        frames = sorted(OUSTER_DATA.glob(meta.stem + "_frame*.npz"))
        out.append((meta, frames[0] if frames else None))
    if not out:
        raise FileNotFoundError(f"{OUSTER_DATA}/*.json (Ouster metadata fixtures)")
    return out


@lru_cache(maxsize=8)
def load_frame(path: Path) -> dict[str, np.ndarray[Any, Any]]:
    """All arrays of a decoded-frame ``.npz`` (no pickles)."""
    with np.load(path, allow_pickle=False) as npz:
        return {k: npz[k] for k in npz.files}


@lru_cache(maxsize=16)
def ouster_info(meta: Path, use_lidar_to_sensor: bool = True, stamp_ns: int = 1_000_000_000
                ) -> Any:
    """LidarInfo dataclass of an Ouster metadata file (via :mod:`converters.sources.ouster.metadata`)."""
    from converters.sources.ouster.metadata import info_from_metadata
    return info_from_metadata(meta, stamp_ns=stamp_ns, use_lidar_to_sensor=use_lidar_to_sensor,
                              as_dataclass=True)


def short_name(meta: Path) -> str:
    """'OS-2-128-U1_v2.3.0_1024x10.json' -> 'OS-2-128 1024x10' style label from the metadata."""
    import json
    data = json.loads(meta.read_text())
    prod = data.get("prod_line") or data.get("sensor_info", {}).get("prod_line", meta.stem)
    mode = data.get("lidar_mode") or data.get("config_params", {}).get("lidar_mode", "")
    return f"{prod} {mode}".strip()


# --------------------------------------------------------------------------------- layouts

#: PointCloud2 layouts drivers publish (docs prior-art (c)): name -> (fields, point_step).
#: fields: (name, offset, PointField datatype id).
PC2_LAYOUTS: dict[str, tuple[list[tuple[str, int, int]], int]] = {
    "ouster-ros original": ([("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 16, 7),
                             ("t", 20, 6), ("reflectivity", 24, 4), ("ring", 26, 4),
                             ("ambient", 28, 4), ("range", 32, 6)], 48),
    "velodyne XYZIRT": ([("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 12, 7),
                         ("ring", 16, 4), ("time", 18, 7)], 22),
    "x,y,z,intensity": ([("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 12, 7)], 16),
    "hesai": ([("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 12, 7), ("ring", 16, 4),
               ("timestamp", 18, 8)], 26),
    "livox": ([("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 12, 7), ("tag", 16, 2),
               ("line", 17, 2), ("timestamp", 18, 8)], 26),
}


def pointcloud2_bytes(layout: str, height: int, width: int, frame_id: str = "os_sensor") -> int:
    """CDR size (bytes, with the 4-byte encapsulation header) of one PointCloud2 message.

    Built as a ``sensor_msgs/PointCloud2`` with the driver's field table and height*width
    points, and encoded with :func:`lidarscan.encode`, so the count includes the header, the
    field descriptors and the alignment exactly as on the wire.
    """
    from lidarscan import encode
    from lidarscan.types import Header, Time, message_class
    cloud_cls = message_class("sensor_msgs/msg/PointCloud2")
    field_cls = message_class("sensor_msgs/msg/PointField")
    fields, step = PC2_LAYOUTS[layout]
    empty = cloud_cls(header=Header(Time(0, 0), frame_id), height=height, width=width,
                      fields=[field_cls(name=n, offset=o, datatype=t, count=1)
                              for n, o, t in fields],
                      is_bigendian=False, point_step=step, row_step=step * width,
                      data=b"", is_dense=False)
    # the data array is the last-but-one field: its bytes add without any further alignment
    return len(encode(empty)) + step * height * width


# -------------------------------------------------------------------------- machine, timing

def machine_lines() -> list[str]:
    """CPU model, cores, OS, Python and library versions of this run."""
    cpu = platform.processor() or "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    versions = []
    for mod in ("numpy", "zstandard", "lz4", "PIL", "matplotlib"):
        try:
            import importlib
            versions.append(f"{mod} {importlib.import_module(mod).__version__}")
        except Exception:  # noqa: BLE001
            versions.append(f"{mod} missing")
    return [f"CPU: {cpu}, {os.cpu_count()} logical cores",
            f"OS: {platform.system()} {platform.release()} ({platform.machine()})",
            f"Python {platform.python_version()}; " + ", ".join(versions)]


def time_call(fn: Callable[[], Any], repeat: int = 7, min_time: float = 0.02) -> float:
    """Best (minimum) wall time of one call in seconds over ``repeat`` samples, each looping
    until ``min_time``: on a shared machine the minimum is the figure least disturbed by
    other processes."""
    fn()  # warm-up
    samples = []
    for _ in range(repeat):
        n, start = 0, time.perf_counter()
        while True:
            fn()
            n += 1
            elapsed = time.perf_counter() - start
            if elapsed >= min_time:
                break
        samples.append(elapsed / n)
    return min(samples)
