"""The demo robot's fixed set-up: sensor mounts, height slices, rates, and the depth camera's
slicer (below the run and its views, which both read it)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from converters.edge.demo.scene import pose_matrix

#: Height slices of the demo in ``base_link``: name -> (min_height, max_height) in metres.
DEFAULT_SLICES: dict[str, tuple[float, float]] = {
    "floor_to_knee": (0.05, 0.5),
    "table": (0.5, 1.0),
    "full": (0.05, 1.8),
}


@dataclass(frozen=True)
class DemoConfig:
    """Fixed set-up of the demo robot.

    Attributes:
        lidar_mount: 4x4 base_link_from_os_sensor (the Ouster 0.40 m above the base centre).
        laser_mount: 4x4 base_link_from_laser (the 2D lidar 0.25 m forward, 0.2 m high).
        camera_mount: 4x4 base_link_from_camera_link (the depth camera 0.2 m forward, 0.6 m
            high, pitched 0.5 rad down, turned 0.45 rad to the right; its optical frame:
            :data:`LINK_FROM_OPTICAL`).
        slices: name -> (min_height, max_height) in base_link, metres.
        camera_slice: (min_height, max_height) of the depth camera's slice, with hole detection
            (floor at base_link z = 0, holes 5 cm deep or more, edges up to 3 m).
        rate_hz: frame rate of both sensors.
        laser_delay_ns: the 2D lidar's stamps lag the 3D lidar's by this much.
    """

    lidar_mount: np.ndarray[Any, Any] = field(
        default_factory=lambda: pose_matrix(0.0, 0.0, 0.40))
    laser_mount: np.ndarray[Any, Any] = field(
        default_factory=lambda: pose_matrix(0.25, 0.0, 0.20))
    camera_mount: np.ndarray[Any, Any] = field(
        default_factory=lambda: pose_matrix(0.2, -0.05, 0.6, pitch=0.5, yaw=-0.45))
    slices: dict[str, tuple[float, float]] = field(default_factory=lambda: dict(DEFAULT_SLICES))
    camera_slice: tuple[float, float] = (0.05, 1.8)
    rate_hz: float = 10.0
    laser_delay_ns: int = 10_000_000


def camera_slicer(info: Any, optical_mount: np.ndarray[Any, Any], config: DemoConfig, *,
                   holes: bool) -> Any:
    """The depth camera's slice (a sector of base_link covering its view, at 0.25 degrees)."""
    from converters.slices.converter import SliceConverter

    lo, hi = config.camera_slice
    return SliceConverter(info, {"camera": {"min_height": lo, "max_height": hi}},
                          extrinsics=optical_mount, frame_id="base_link", angle_min=-1.3,
                          angle_max=0.4, angle_increment=math.radians(0.25), range_min=0.1,
                          range_max=6.0, intensity_channel=None, holes=holes,
                          floor_height=0.0, hole_depth=0.05, hole_range_max=3.0)
