"""Benchmark: ``lidarscan.validate_info`` and what it adds to ``lidarscan.make_info``.

Run: ``.venv/bin/python bench/bench_scan.py [--rounds N]``. Prints CPU-time
(``time.process_time``) medians of interleaved rounds and ratios measured in the same run (no
assertions), for two real infos, as dataclasses and as rclpy messages (when built):

* the Ouster OS-2-128 1024x10 info of ``tests/data/ouster`` (``converters.sources.ouster.metadata``);
* a 128-row Velodyne info, the VLS-128 calibration of ``tests/data/nebula`` with 1 800 columns
  (``converters.sources.velodyne.calibration``).

Candidates per info: ``validate_info(info)``; ``make_info(**fields)`` (which validates); the same
``make_info`` with validation switched off (the baseline: building the info alone). The ratio
``make_info / make_info without validation`` is what validation costs a producer.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).parent))
from _timing import interleaved_times  # noqa: E402

import lidarscan  # noqa: E402
from lidarscan import scan as ls_scan  # noqa: E402
from lidarscan._install import have_messages  # noqa: E402
from lidarscan.stamps import to_ns  # noqa: E402

DATA = Path(__file__).resolve().parents[1] / "tests" / "data"


def infos() -> dict[str, Any]:
    """name -> dataclass LidarInfo of the two real sensors."""
    from converters.sources.ouster.metadata import info_from_metadata
    from converters.sources.velodyne.calibration import info_from_calibration
    return {
        "OS-2-128 1024x10": info_from_metadata(
            DATA / "ouster" / "OS-2-128-U1_v2.3.0_1024x10.json", stamp_ns=1, as_dataclass=True),
        "VLS-128 x1800": info_from_calibration(
            DATA / "nebula" / "velodyne_vls128" / "VLS128.yaml", columns=1800, stamp_ns=1,
            as_dataclass=True),
    }


def make_info_call(info: Any, as_dataclass: bool) -> Callable[[], Any]:
    """``make_info`` rebuilding ``info`` from its fields."""
    fields = {f.name: getattr(info, f.name) for f in dataclasses.fields(info)
              if f.name not in ("header", "height", "width")}
    stamp_ns = to_ns(info.header.stamp)
    frame_id = info.header.frame_id
    return lambda: lidarscan.make_info(stamp_ns=stamp_ns, frame_id=frame_id,
                                       as_dataclass=as_dataclass, **fields)


def unvalidated(call: Callable[[], Any]) -> Callable[[], Any]:
    """``call`` with ``make_info``'s validation switched off (the baseline)."""
    def run() -> Any:
        saved = ls_scan.validate_info
        ls_scan.validate_info = lambda info: None  # type: ignore[assignment]
        try:
            return call()
        finally:
            ls_scan.validate_info = saved
    return run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=400)
    args = parser.parse_args()
    kinds = [True]
    if have_messages():
        kinds.append(False)
    for name, info in infos().items():
        for as_dataclass in kinds:
            make = make_info_call(info, as_dataclass)
            target = make()
            candidates = {
                "validate_info": lambda target=target: lidarscan.validate_info(target),
                "make_info": make,
                "make_info, no validation": unvalidated(make),
            }
            times = interleaved_times(candidates, args.rounds, clock=time.process_time)
            med = {k: statistics.median(v) * 1e6 for k, v in times.items()}
            base = med["make_info, no validation"]
            kind = "dataclass" if as_dataclass else "rclpy message"
            print(f"{name}, {kind}: " + ", ".join(f"{k} {v:.1f} us" for k, v in med.items())
                  + f"; make_info / no validation {med['make_info'] / base:.2f}x, "
                  f"validate_info / make_info without it {med['validate_info'] / base:.2f}x")
    print(f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
