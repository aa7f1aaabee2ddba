"""Build a LidarScan from numpy arrays, serialize it to CDR and read it back without copying.

Run: python examples/01_encode_decode.py
"""

import numpy as np

import lidarscan

# 1. The sensor's intrinsics: 32 beams from +15 to -15 deg, 512 columns sweeping clockwise.
info = lidarscan.make_info(
    stamp_ns=1_700_000_000_000_000_000,          # the version key of this geometry
    frame_id="lidar",
    vertical_angles=np.radians(np.linspace(15.0, -15.0, 32)),
    horizontal_angles=2 * np.pi * (1 - np.arange(512) / 512),
    column_time_increment=195_312,               # ns between columns (10 Hz)
    range_min=0.3, range_max=100.0,
    as_dataclass=True,                           # plain Python: no ROS libraries needed
)

# 2. One frame: float32 ranges in metres (+Inf = no return) and a uint16 intensity image.
rng = np.random.default_rng(0)
ranges = rng.uniform(1.0, 20.0, (32, 512)).astype(np.float32)
ranges[:4, 100:140] = np.inf                     # nothing came back from the sky
intensity = rng.integers(0, 4000, (32, 512), dtype=np.uint16)
scan = lidarscan.make_scan(info, {"range": ranges, "intensity": intensity},
                           stamp_ns=1_700_000_000_100_000_000, as_dataclass=True)
lidarscan.validate(scan, info)                   # raises with field, value and expectation

# 3. CDR bytes, as they travel over DDS or sit in an MCAP file.
payload = lidarscan.encode(scan)
print(f"LidarScan {scan.height}x{scan.width}, channels {lidarscan.channel_names(scan)}: "
      f"{len(payload)} bytes of CDR")

# 4. Decode: every array views `payload` (no copy); channels are (H, W) numpy views.
decoded = lidarscan.decode_scan(payload)
view = lidarscan.channel(decoded, "intensity")
print(f"intensity view: shape {view.shape}, dtype {view.dtype}, "
      f"shares memory with payload: {np.shares_memory(view, np.frombuffer(payload, np.uint8))}")
assert np.array_equal(lidarscan.range_m(decoded, info), ranges)
assert np.array_equal(view, intensity)

# 5. Points: the projector is built once per LidarInfo version and reused for every scan.
points = lidarscan.make_projector(info).project(decoded, info)   # (H, W, 3) float32, NaN = none
print(f"points: {points.shape}, {np.isfinite(points[..., 0]).sum()} with a return")
