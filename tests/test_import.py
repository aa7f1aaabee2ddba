"""The core imports and works without rclpy (convention 1 of the style guide).

Each check runs in a fresh interpreter so that other tests' imports cannot hide a regression.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap

CHECK_NOT_IMPORTED = """
import sys
import lidarscan, converters
import lidarscan.cdr, lidarscan.scan, lidarscan.types, lidarscan.msgdef, lidarscan.stamps
assert "rclpy" not in sys.modules, sorted(m for m in sys.modules if m.startswith("rclpy"))
print("ok")
"""

# rclpy made unimportable: the whole dataclass path (build, encode, decode, view, validate)
# must work, and so must importing every core module.
CHECK_WORKS_WITHOUT_RCLPY = """
import sys
sys.modules["rclpy"] = None  # any "import rclpy" now raises ImportError
import numpy as np
import lidarscan, converters
info = lidarscan.make_info(stamp_ns=1_000, frame_id="lidar", vertical_angles=[0.1, -0.1],
                           horizontal_angles=[0.0, 3.0, 6.0], range_multiplier=0.001,
                           as_dataclass=True)
scan = lidarscan.make_scan(info, {"range": np.array([[0, 1, 2], [3, 4, 5]], np.uint32),
                                  "intensity": np.ones((2, 3), np.uint16)}, 2_000,
                           as_dataclass=True)
lidarscan.validate(scan, info)
payload = lidarscan.encode(scan)
back = lidarscan.decode_scan(payload)
assert lidarscan.channel(back, "range").tolist() == [[0, 1, 2], [3, 4, 5]]
assert lidarscan.range_m(back, info)[0, 0] == np.inf
assert lidarscan.decode_info(lidarscan.encode(info)).width == 3
assert lidarscan.decode(lidarscan.encode(info), "lidarscan_msgs/msg/LidarInfo").height == 2
print("ok")
"""


def _run(code: str) -> None:
    result = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True,
                            text=True, timeout=120, check=False)
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.strip().endswith("ok"), result.stdout


def test_import_does_not_import_rclpy() -> None:
    _run(CHECK_NOT_IMPORTED)


def test_encode_decode_make_scan_without_rclpy() -> None:
    _run(CHECK_WORKS_WITHOUT_RCLPY)
