"""Ready at start: the warm-up compiles every kernel specialisation a configuration reaches, so
no scan after "ready" compiles anything, whatever its dtypes; the nodes warm before they report
ready and show it in /diagnostics.

Kernel checks run in a fresh interpreter (a kernel compiled by an earlier test in this process
would hide a missing warm-up); they count numba specialisations, not time (timings:
bench/bench_startup.py).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from converters.edge.nodes.common import Startup, warm_up
from lidarscan.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]


def _run(code: str, timeout: float = 600.0) -> dict[str, Any]:
    """Run ``code`` in a fresh interpreter; its last stdout line is JSON."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("_ROS_WHEELS")}
    proc = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=timeout, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])  # type: ignore[no-any-return]


def _numba() -> None:
    from converters._kernels import numba_enabled

    pytest.importorskip("numba")
    if not numba_enabled():
        pytest.skip("numba switched off (LIDARSCAN_NUMBA=0)")


# --------------------------------------------------------------------- warm-up and kernels

_SCANS = """
import json, numpy as np, lidarscan, converters
from converters._kernels import warm
from converters.sources.ouster.metadata import info_from_metadata, scan_from_frame

D = "tests/data/ouster/"
info = info_from_metadata(D + "OS-2-128-U1_v2.3.0_1024x10.json", stamp_ns=1, as_dataclass=True)
frame = dict(np.load(D + "OS-2-128-U1_v2.3.0_1024x10_frame1259.npz"))

def scans():
    # every way a scan's arrays can differ: range float32 (read-only view) or uint32 mm
    # (decoded: writeable), intensity of each integer dtype / float / absent, big-endian
    # channels (byte-swapped copies), destaggered, a dataclass built in memory
    for enc in ("float32", "uint32_mm"):
        for dt in ("u1", "u2", "u4", "i2", "i4"):
            f = dict(frame, signal=frame["signal"].astype(dt))
            s = scan_from_frame(f, info, range_encoding=enc, as_dataclass=True)
            yield lidarscan.decode_scan(lidarscan.encode(s))
        yield scan_from_frame(frame, info, range_encoding=enc, destagger=True,
                              as_dataclass=True)
    rng = lidarscan.range_m(lidarscan.decode_scan(lidarscan.encode(
        scan_from_frame(frame, info, as_dataclass=True))), info)
    for inten in (None, np.float32, np.float64):
        ch = {"range": np.asarray(rng)}
        if inten is not None:
            ch["intensity"] = frame["signal"].astype(inten)
        yield lidarscan.make_scan(info, ch, 5, as_dataclass=True)
    yield lidarscan.decode_scan(lidarscan.encode(lidarscan.make_scan(
        info, {"range": np.asarray(rng), "intensity": frame["signal"]}, 6, is_bigendian=True,
        as_dataclass=True)))
"""


def test_no_scan_dtype_compiles_a_kernel_after_the_warm_up() -> None:
    _numba()
    out = _run(_SCANS + """
slices = {"a": {"min_height": -0.5, "max_height": 0.5}, "b": {"min_height": 0.0,
          "max_height": 2.0}}
mixed = {**slices, "c": {"min_height": -1.0, "max_height": 1.0, "angle_increment": 0.01}}
took = warm.warm(("slices",), slices=slices)
took.update(warm.warm(("slices",), slices=mixed))
ready = warm.specialisations()
tilt = np.array([[0.96, 0, 0.28, 0], [0, 1, 0, 0], [-0.28, 0, 0.96, 0.5], [0, 0, 0, 1]])
converted = 0
for config in (slices, mixed):
    for ext in (None, tilt):
        conv = converters.SliceConverter(info, config, extrinsics=ext,
                                         frame_id=None if ext is None else "base")
        for scan in scans():
            conv.convert(scan)
            converted += 1
from converters._kernels import select
print(json.dumps({"ready": ready, "after": warm.specialisations(), "converted": converted,
                  "c_rows": bool(select("slices").c)}))
""")
    assert out["converted"] == 4 * 16
    ready = out["ready"]
    # the warm-up reached the row-ordered, bin-ordered and general kernels
    assert ready["sorted"] >= 1 and ready["decode_slices"] >= 1 and ready["bands"] >= 1
    assert ready["row_convert"] >= 1 or out["c_rows"]     # (the C kernel's AVX-512 path)
    assert out["after"] == ready


def test_merger_kernels_are_ready_after_the_warm_up() -> None:
    _numba()
    out = _run("""
import json, math, numpy as np, lidarscan
from converters._kernels import warm
from converters.merger import LaserScanMerger, MergerInput
warm.warm(("merger",))
ready = warm.specialisations()
LaserScan = lidarscan.types.message_class("sensor_msgs/msg/LaserScan")
def laser(frame, stamp, n, dtype, wire):
    msg = LaserScan(header=lidarscan.types.Header(lidarscan.types.Time(stamp, 0), frame),
                    angle_min=-math.pi, angle_max=math.pi, angle_increment=2 * math.pi / n,
                    time_increment=0.0, scan_time=0.1, range_min=0.05, range_max=30.0,
                    ranges=np.linspace(0.5, 8.0, n).astype(dtype),
                    intensities=np.arange(n).astype(dtype))
    if wire:
        msg = lidarscan.decode(lidarscan.encode(msg), "sensor_msgs/msg/LaserScan")
    return msg
m = LaserScanMerger({"a": MergerInput(), "b": MergerInput(extrinsics=np.eye(4),
                                                           frame_id="laser")})
for n, dtype, wire in ((360, np.float32, True), (1081, np.float64, False),
                       (720, np.float32, False)):
    m.merge({"a": laser("base_link", 1, n, dtype, wire), "b": laser("laser", 1, n, dtype, wire)})
print(json.dumps({"ready": ready, "after": warm.specialisations()}))
""")
    assert out["ready"]["small"] >= 1 and out["ready"]["decode"] >= 1
    assert out["after"] == out["ready"]


def test_warm_rejects_an_unknown_task_and_probes_are_valid() -> None:
    import lidarscan
    from converters._kernels import warm, warm_up

    with pytest.raises(ConfigError, match="warm task"):
        warm_up(("clouds",))
    info = warm.probe_info(8, 64)
    scan = warm.probe_scan(info, intensity_name="signal", destaggered=True)
    lidarscan.validate(scan, info)
    assert set(lidarscan.channel_names(scan)) == {"range", "signal"}
    assert scan.is_destaggered
    r = lidarscan.channel(scan, "range")
    # every class of value the kernels treat apart is there
    assert np.isinf(r).any() and np.isnan(r).any() and (r == -np.inf).any()
    assert not r.flags.writeable                     # a view of the message, as received
    assert warm_up(()) == {}


# ------------------------------------------------------------------------- ready in nodes

class _Logger:
    def __init__(self) -> None:
        self.lines: list[tuple[str, str]] = []

    def info(self, line: str) -> None:
        self.lines.append(("info", line))

    def warning(self, line: str) -> None:
        self.lines.append(("warning", line))


class _Node:
    def __init__(self) -> None:
        self.logger = _Logger()

    def get_logger(self) -> _Logger:
        return self.logger


def test_warm_up_times_steps_logs_ready_and_reports_failures() -> None:
    calls: list[str] = []
    node = _Node()

    def broken() -> None:
        raise RuntimeError("no compiler")

    startup = warm_up(node, {"a": lambda: calls.append("a"), "b": broken})
    assert calls == ["a"] and startup.ready
    assert set(startup.seconds) == {"a", "b"} and "no compiler" in startup.failed["b"]
    kind, line = node.logger.lines[-1]
    assert kind == "warning" and line.startswith("ready: warm-up") and "b: RuntimeError" in line
    status = startup.status()
    assert status.level == 1 and "warm-up step b failed" in status.message
    assert status.values["ready"] is True and "a_ms" in status.values
    fresh = Startup()
    assert fresh.status().level == 1 and fresh.status().message == "warming up"
    good = warm_up(node, {"a": lambda: None})
    assert good.status().level == 0 and node.logger.lines[-1][0] == "info"


_NODE = """
import json, time, os, numpy as np, rclpy, lidarscan
from rclpy.parameter import Parameter
from converters._kernels import warm
from converters.edge.nodes.converter_node import ConverterNode
from converters.sources.ouster.metadata import info_from_metadata, scan_from_frame

D = "tests/data/ouster/"
info = info_from_metadata(D + "OS-2-128-U1_v2.3.0_1024x10.json", stamp_ns=7, as_dataclass=True)
frame = dict(np.load(D + "OS-2-128-U1_v2.3.0_1024x10_frame1259.npz"))
raw_info = lidarscan.encode(info)
raw_scans = [lidarscan.encode(scan_from_frame(frame, info, stamp_ns=10**9 * (k + 1),
                                              range_encoding=enc, as_dataclass=True))
             for k, enc in enumerate(("float32", "uint32_mm", "float32"))]
rclpy.init(domain_id=1 + os.getpid() % 100)
P = lambda **kw: [Parameter(k.replace("__", "."), value=v) for k, v in kw.items()]
t0 = time.perf_counter()
node = ConverterNode(parameter_overrides=P(
    slice_names=["low", "high"], slices__low__min_height=-0.3, slices__low__max_height=0.3,
    slices__high__min_height=0.3, slices__high__max_height=2.0, target_frame="base_link",
    extrinsics=[0.0, 0.0, 0.4, 0.0, 0.0, 0.0]))
built = time.perf_counter() - t0
ready = warm.specialisations()
# what the callbacks do (no subscriber is needed): info, then scans through the core
node._on_info(raw_info)
prepared = (list(node.core._clouds.values()), list(node.core._slicers.values()))
times = []
for raw in raw_scans:
    t = time.perf_counter()
    (pair,) = node.core.add_scan(raw)
    cloud, slices = node.core.convert(*pair, extrinsics=node._extrinsics(*pair))
    times.append(time.perf_counter() - t)
# the scans used the converters prepared when the info arrived (same cache keys)
used = (list(node.core._clouds.values()), list(node.core._slicers.values()))
out = {"ready": ready, "after": warm.specialisations(), "startup": node.startup.seconds,
       "failed": node.startup.failed, "is_ready": node.startup.ready,
       "status": node.startup.status().values, "times": times, "built": built,
       "slices": sorted(slices), "has_cloud": cloud is not None,
       "prepared": [len(p) for p in prepared],
       "same_converters": all(len(a) == len(b) and all(x is y for x, y in zip(a, b))
                              for a, b in zip(prepared, used))}
node.destroy_node()
rclpy.try_shutdown()
print(json.dumps(out))
"""


@pytest.mark.ros
def test_converter_node_compiles_nothing_after_it_reports_ready() -> None:
    pytest.importorskip("rclpy")
    out = _run(_NODE)
    assert out["is_ready"] and not out["failed"] and "kernels" in out["startup"]
    assert out["status"]["ready"] is True and "kernels_ms" in out["status"]
    assert out["slices"] == ["high", "low"] and out["has_cloud"]
    assert out["prepared"] == [1, 1] and out["same_converters"]
    if out["ready"]:                       # numba: the warm-up compiled or loaded the kernels
        assert sum(out["ready"].values()) >= 1
        # the first scans (float and integer ranges) after ready compiled nothing
        assert out["after"] == out["ready"]


def test_cloud_slicer_warm_up_leaves_nothing_to_compile_for_a_driver_cloud() -> None:
    """The cloud-to-scan node's slicer runs the C cloud slices kernel (nothing to compile, no
    numba import): its warm-up (:func:`probe_cloud`) and the first driver cloud of another size
    and sensor (the real OS-2 frame as an unorganized x, y, z, intensity cloud) load numba
    nowhere."""
    got = _run("""
        import json, sys, numpy as np
        from converters import _kernels
        from converters._kernels.warm import probe_cloud
        from converters.edge.nodes.cloud_to_scan_node import CloudSlicer
        from converters.edge.nodes.params import SliceConfig
        from converters.sources.ouster.metadata import info_from_metadata, scan_from_frame
        from converters.pointcloud2.converter import to_pointcloud2

        kernel = _kernels.select("cloud_slices").c
        slicer = CloudSlicer([SliceConfig("mid", -0.5, 0.5, "slices/mid"),
                              SliceConfig("low", -1.5, -0.5, "slices/low")])
        slicer.convert(probe_cloud())                        # the node's warm-up step
        D = "tests/data/ouster/"
        info = info_from_metadata(D + "OS-2-128-U1_v2.3.0_1024x10.json", stamp_ns=1,
                                  as_dataclass=True)
        frame = dict(np.load(D + "OS-2-128-U1_v2.3.0_1024x10_frame1259.npz"))
        cloud = to_pointcloud2(scan_from_frame(frame, info), info, organized=False,
                               fields=("x", "y", "z", "intensity"), frame_id="os_lidar")
        scans = slicer.convert(cloud)
        print(json.dumps([kernel is not None, "numba" in sys.modules, len(scans)]))
    """)
    from converters._kernels import cloud_slices

    if not cloud_slices.available():
        pytest.skip("the C cloud slices kernel is not built")
    assert got == [True, False, 2], got
