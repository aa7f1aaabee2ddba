"""Record LidarInfo + LidarScans to MCAP and read them back, each scan paired with its info.

Run: python examples/02_mcap_roundtrip.py [OUT_DIR]   (default: a temporary folder)
"""

import sys
import tempfile
from pathlib import Path

import numpy as np

import lidarscan
from lidarscan.mcap import McapWriter, read_messages, read_scans

out_dir = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(tempfile.mkdtemp())
out_dir.mkdir(parents=True, exist_ok=True)
path = out_dir / "roundtrip.mcap"

info = lidarscan.make_info(stamp_ns=1_000_000_000, frame_id="lidar",
                           vertical_angles=np.radians(np.linspace(10, -10, 16)),
                           horizontal_angles=2 * np.pi * (1 - np.arange(256) / 256),
                           as_dataclass=True)
rng = np.random.default_rng(1)
frames = [rng.uniform(0.5, 30.0, (16, 256)).astype(np.float32) for _ in range(5)]

# Write: the info once (it is latched in a live system), then one scan per frame.
with McapWriter(path) as writer:
    writer.write("/lidar/info", info)
    for k, ranges in enumerate(frames):
        scan = lidarscan.make_scan(info, {"range": ranges}, 2_000_000_000 + k * 100_000_000,
                                   as_dataclass=True)
        writer.write("/lidar/scan", scan)
print(f"wrote {path} ({path.stat().st_size} bytes)")

# Read every record (bad records would come out as BadMessage, the rest still readable) ...
topics = sorted({m.topic for m in read_messages(path)})
print(f"topics: {topics}")

# ... or scans already paired with the LidarInfo their lidar_info_time names.
problems = []
for k, (scan, scan_info) in enumerate(read_scans(path, on_error=problems.append)):
    assert np.array_equal(lidarscan.range_m(scan, scan_info), frames[k])
print(f"read back {len(frames)} scans, identical; problems: {problems}")
