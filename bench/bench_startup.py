"""Start-up: how late is the first message? Fresh processes, numba's cache cold and warm.

Each case runs in a new interpreter, with ``NUMBA_CACHE_DIR`` pointing at an empty temporary
directory (cold: a new install, container or user) or at the cache the first run filled
(warm). Data: the real OS-2-128 frame of ``tests/data/ouster`` (128 x 1024), as CDR bytes, as a
node receives it.

Cases:

* ``library``: what a script pays without any warm-up: ``import lidarscan, converters``, the
  first ``to_pointcloud2`` and ``to_laserscan`` of a fresh process, then their steady state;
* ``node ...``: the rclpy ``lidarscan-converter`` node (in-process, no DDS traffic): its
  construction up to its ``ready`` line (which includes the warm-up), the LidarInfo arriving
  (``_on_info``: linkage plus the per-version tables), then the first scans through its core,
  cloud and slices timed apart, then the steady state (median of the next scans). Slices: one
  band (the row-ordered kernel), or the three of ``config/converter.yaml`` (two grids: the
  general kernels), in ``base_link`` with the YAML's mount.

Goal (issue 19): after the node is ready, first cloud and first slices each <= 2 x their
steady state + 50 ms, with a warm and with a cold cache. Figures: bench/README.md.

Run: ``.venv/bin/python bench/bench_startup.py`` (``--child CASE`` is one measurement).
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data" / "ouster"
META = DATA / "OS-2-128-U1_v2.3.0_1024x10.json"
FRAME = DATA / "OS-2-128-U1_v2.3.0_1024x10_frame1259.npz"
STEADY = 15           # scans after the first ones, for the steady state (median)

ONE_SLICE = {"slice_names": ["knee"], "slices.knee.min_height": 0.05,
             "slices.knee.max_height": 0.5}
YAML_SLICES = {"slice_names": ["floor_to_knee", "table", "full"],
               "slices.floor_to_knee.min_height": 0.05, "slices.floor_to_knee.max_height": 0.5,
               "slices.table.min_height": 0.5, "slices.table.max_height": 1.0,
               "slices.table.angle_increment": 0.004363323, "slices.table.range_max": 20.0,
               "slices.full.min_height": 0.05, "slices.full.max_height": 1.8}
MOUNT = {"target_frame": "base_link", "extrinsics": [0.0, 0.0, 0.40, 0.0, 0.0, 0.0]}
CASES = {"library": None, "node, 1 slice": ONE_SLICE, "node, converter.yaml": YAML_SLICES}


def _frames(info: Any, count: int) -> list[bytes]:
    import numpy as np

    import lidarscan
    from converters.sources.ouster.metadata import scan_from_frame

    frame = dict(np.load(FRAME))
    return [lidarscan.encode(scan_from_frame(frame, info, stamp_ns=10**9 + k * 10**8,
                                             as_dataclass=True)) for k in range(count)]


def _ms(seconds: float) -> float:
    return round(seconds * 1e3, 2)


def child_library() -> dict[str, Any]:
    t0 = time.perf_counter()
    import converters
    import lidarscan
    t_import = time.perf_counter() - t0
    from converters.sources.ouster.metadata import info_from_metadata

    info = info_from_metadata(META, stamp_ns=1, as_dataclass=True)
    scans = [lidarscan.decode_scan(raw) for raw in _frames(info, STEADY + 1)]
    t = time.perf_counter()
    converters.to_pointcloud2(scans[0], info)
    first_cloud = time.perf_counter() - t
    t = time.perf_counter()
    converters.to_laserscan(scans[0], info, min_height=0.05, max_height=0.5)
    first_slice = time.perf_counter() - t
    clouds, slices = [], []
    for scan in scans[1:]:
        t = time.perf_counter()
        converters.to_pointcloud2(scan, info)
        clouds.append(time.perf_counter() - t)
        t = time.perf_counter()
        converters.to_laserscan(scan, info, min_height=0.05, max_height=0.5)
        slices.append(time.perf_counter() - t)
    return {"import": _ms(t_import), "ready": None, "info": None,
            "first_cloud": _ms(first_cloud), "first_slices": _ms(first_slice),
            "steady_cloud": _ms(statistics.median(clouds)),
            "steady_slices": _ms(statistics.median(slices))}


def child_node(config: dict[str, Any]) -> dict[str, Any]:
    t0 = time.perf_counter()
    import converters  # noqa: F401
    import lidarscan
    t_import = time.perf_counter() - t0
    import rclpy
    from rclpy.parameter import Parameter

    from converters.edge.nodes.converter_node import ConverterNode
    from converters.sources.ouster.metadata import info_from_metadata

    info = info_from_metadata(META, stamp_ns=1, frame_id="os_lidar", as_dataclass=True)
    raws = _frames(info, STEADY + 1)
    raw_info = lidarscan.encode(info)
    rclpy.init(args=[], domain_id=1 + os.getpid() % 100)
    try:
        t = time.perf_counter()
        node = ConverterNode(parameter_overrides=[
            Parameter(k, value=v) for k, v in {**config, **MOUNT}.items()])
        t_ready = time.perf_counter() - t
        t = time.perf_counter()
        node._on_info(raw_info)                     # what the latched LidarInfo triggers
        t_info = time.perf_counter() - t
        core = node.core
        clouds, slices = [], []
        for raw in raws:
            # what _on_scan does, with the cloud and the slices timed apart
            t = time.perf_counter()
            (pair,) = core.add_scan(raw)
            extrinsics = node._extrinsics(*pair)
            cloud, _ = core.convert(*pair, slices=[])
            clouds.append(time.perf_counter() - t)
            t = time.perf_counter()
            _, out = core.convert(*pair, cloud=False, extrinsics=extrinsics)
            slices.append(time.perf_counter() - t)
            assert cloud is not None and len(out) == len(config["slice_names"])
        result = {"import": _ms(t_import), "ready": _ms(t_ready), "info": _ms(t_info),
                  "first_cloud": _ms(clouds[0]), "first_slices": _ms(slices[0]),
                  "steady_cloud": _ms(statistics.median(clouds[1:])),
                  "steady_slices": _ms(statistics.median(slices[1:])),
                  "warmup": {k: _ms(v) for k, v in node.startup.seconds.items()}}
        node.destroy_node()
    finally:
        rclpy.try_shutdown()
    return result


def show(value: float | None) -> str:
    """A table cell: '-' for none, whole milliseconds from 10 up."""
    return "-" if value is None else f"{value:.0f}" if value >= 10 else f"{value:.1f}"


def run(case: str, cache_dir: str) -> dict[str, Any]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("_ROS_WHEELS")}
    env["NUMBA_CACHE_DIR"] = cache_dir
    proc = subprocess.run([sys.executable, __file__, "--child", case], env=env,
                          capture_output=True, text=True, check=False, timeout=1800)
    if proc.returncode:
        raise RuntimeError(f"{case}: {proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])  # type: ignore[no-any-return]


def main() -> int:
    if len(sys.argv) == 3 and sys.argv[1] == "--child":
        case = sys.argv[2]
        out = child_library() if CASES[case] is None else child_node(CASES[case])
        print(json.dumps(out))
        return 0
    print(f"{'case':<22} {'cache':<5} {'import':>7} {'ready':>8} {'info':>6} "
          f"{'1st cloud':>9} {'1st slices':>10} {'cloud':>6} {'slices':>6}  goal (ms, "
          "first <= 2 x steady + 50 after ready)")
    failed = 0
    with tempfile.TemporaryDirectory() as scratch:
        for case in CASES:
            cache_dir = tempfile.mkdtemp(dir=scratch)
            for cache in ("cold", "warm"):
                # cold: an empty cache of its own; warm: the same, filled by the cold run
                r = run(case, cache_dir)
                ok = all(r[f"first_{k}"] <= 2 * r[f"steady_{k}"] + 50 for k in
                         ("cloud", "slices"))
                if r["ready"] is not None:
                    failed += not ok
                goal = "n/a (no warm-up)" if r["ready"] is None else "met" if ok else "MISSED"
                print(f"{case:<22} {cache:<5} {show(r['import']):>7} {show(r['ready']):>8} "
                      f"{show(r['info']):>6} {show(r['first_cloud']):>9} "
                      f"{show(r['first_slices']):>10} {show(r['steady_cloud']):>6} "
                      f"{show(r['steady_slices']):>6}  {goal}", flush=True)
    print("ms; import = import lidarscan, converters; ready = node construction incl. its "
          "warm-up; info = the LidarInfo's tables; cloud / slices = steady-state medians")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
