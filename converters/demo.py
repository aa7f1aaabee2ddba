"""The simulated scene of ``lidarscan demo``: a robot with a 3D lidar, a 2D lidar and a depth
camera in a small room with a staircase down.

Everything here is deterministic and offline (no network, nothing read outside the package):

* the room (``room_scene``): floor, four walls 2.5 m high with a doorway, a table (top at
  0.68..0.72 m on four thin legs), a shelf overhanging from a wall at 1.18..1.22 m, a crate, a
  pillar and a staircase down (a stairwell in the floor, four 0.18 m steps); every object is an
  axis-aligned box in the ``odom`` frame (metres, REP 103, z up);
* the 3D lidar (:class:`SimulatedLidar3D`): the geometry of a real Ouster OS-1-128 (2048 x 10,
  metadata shipped in ``converters/data``, see its NOTICE.md) turned into a LidarInfo by
  :func:`converters.ouster.info_from_metadata`; every pixel's ray (``P = rho * D + O`` from the
  projector) is intersected exactly with the boxes, so projecting the produced ranges lands on the
  surfaces to float32 precision; intensity, reflectivity and ambient follow a simple model
  (albedo, incidence angle, 1/r^2, light from the doorway);
* the 2D lidar (:class:`SimulatedLaser2D`): a 270 degree scanner 0.2 m above the floor, which sees
  the table legs but not the table top or the shelf;
* the depth camera (:class:`SimulatedDepthCamera`): a pinhole camera (424 x 240, 87 degrees wide,
  no distortion) 0.6 m up, pitched down and turned to the right, publishing 16UC1 depth images
  (REP 118, millimetres) and their CameraInfo, which
  :class:`converters.depth.DepthImageConverter` turns into LidarScans;
* :func:`run_demo`: moves the robot slowly through the room, converts every frame (PointCloud2,
  three height slices in ``base_link``, the depth camera's slice with hole detection, the merged
  scan of the full slice, the 2D lidar and the camera slice), writes ``demo.mcap`` and PNG
  views, and returns sizes and timings. Neither lidar's height band sees the staircase (it is
  below the floor); the camera slice reports its edge as an obstacle (holes, see
  :mod:`converters.laserscan`).

The robot pose is constant during one frame (no motion inside a scan; at 0.2 m/s it would move
2 cm in 0.1 s). Ranges are exact (no noise) unless ``noise_m`` is given.
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "DEFAULT_SLICES",
    "METADATA_PATH",
    "Box",
    "DemoConfig",
    "DemoResult",
    "Hits",
    "Pose2D",
    "Scene",
    "STAIRWELL",
    "SimulatedDepthCamera",
    "SimulatedLaser2D",
    "SimulatedLidar3D",
    "pose_matrix",
    "room_scene",
    "run_demo",
    "trajectory",
]

#: The Ouster metadata the simulated 3D lidar is built from (shipped with the package).
METADATA_PATH = Path(__file__).resolve().parent / "data" / \
    "2_0_0_os1-992008000494-128_col_win_legacy.json"

#: Height slices of the demo in ``base_link``: name -> (min_height, max_height) in metres.
DEFAULT_SLICES: dict[str, tuple[float, float]] = {
    "floor_to_knee": (0.05, 0.5),
    "table": (0.5, 1.0),
    "full": (0.05, 1.8),
}

START_NS = 1_700_000_000 * 1_000_000_000  # 2023-11-14, a fixed epoch: reproducible files

#: The opening of the stairwell in the floor, ``odom`` frame: (x0, y0, x1, y1) metres. The stairs
#: go down towards +x from its edge x = x0, in four steps of 0.18 m (0.25 m treads).
STAIRWELL = (-1.4, -2.0, -0.4, -0.8)


# ------------------------------------------------------------------------------------ geometry

def pose_matrix(x: float = 0.0, y: float = 0.0, z: float = 0.0, roll: float = 0.0,
                pitch: float = 0.0, yaw: float = 0.0) -> np.ndarray[Any, np.dtype[np.float64]]:
    """4x4 float64 homogeneous transform (parent_from_child) from a translation (m) and
    roll/pitch/yaw (rad), R = Rz(yaw) Ry(pitch) Rx(roll) as in tf2."""
    from converters.nodes.tf import matrix_from_xyz_rpy

    return matrix_from_xyz_rpy(x, y, z, roll, pitch, yaw)


# ------------------------------------------------------------------------------------- scene

@dataclass(frozen=True)
class Box:
    """An axis-aligned box in the scene frame.

    Attributes:
        name: label (several boxes may share one, e.g. the four legs are "table").
        lo, hi: (3,) opposite corners in metres, ``lo < hi`` on every axis.
        albedo: diffuse reflectance 0..1 (drives reflectivity and intensity).
    """

    name: str
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    albedo: float = 0.5


@dataclass(frozen=True)
class Hits:
    """Result of :meth:`Scene.cast` for N rays.

    Attributes:
        t: (N,) float64 distance along each (unit) ray to the first hit, +inf if none.
        box: (N,) int index of the box hit (-1 if none).
        normal: (N, 3) float64 unit outward normal of the face hit (0 if none).
    """

    t: np.ndarray[Any, np.dtype[np.float64]]
    box: np.ndarray[Any, np.dtype[np.int64]]
    normal: np.ndarray[Any, np.dtype[np.float64]]


@dataclass(frozen=True)
class Scene:
    """A set of boxes and a light source (for the ambient channel).

    Attributes:
        boxes: the objects.
        light: (3,) position of the light (the doorway), metres.
    """

    boxes: tuple[Box, ...]
    light: tuple[float, float, float] = (2.0, 3.2, 1.2)

    def cast(self, origins: np.ndarray[Any, Any], directions: np.ndarray[Any, Any], *,
             t_min: float = 1e-9) -> Hits:
        """First intersection of each ray with the boxes (slab method, vectorised).

        Args:
            origins: (N, 3) ray origins, metres, scene frame.
            directions: (N, 3) unit directions, scene frame.
            t_min: hits closer than this along the ray are ignored (rays starting inside a box
                do not see that box).

        Returns:
            :class:`Hits` (distances along the ray in metres).
        """
        o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
        d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
        return self.cast_components([np.ascontiguousarray(o[:, k]) for k in range(3)],
                                    [np.ascontiguousarray(d[:, k]) for k in range(3)],
                                    t_min=t_min)

    def cast_components(self, origins: Sequence[np.ndarray[Any, Any]],
                        directions: Sequence[np.ndarray[Any, Any]], *,
                        t_min: float = 1e-9) -> Hits:
        """:meth:`cast` with rays given as three (N,) float64 arrays per vector (x, y, z).

        One contiguous array per axis keeps every step a fast elementwise numpy loop.
        """
        oc = [np.asarray(v, dtype=np.float64) for v in origins]
        dc = [np.asarray(v, dtype=np.float64) for v in directions]
        n = oc[0].size
        best = np.full(n, np.inf)
        which = np.full(n, -1, dtype=np.int64)
        axis = np.zeros(n, dtype=np.int64)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = [1.0 / v for v in dc]
            for index, box in enumerate(self.boxes):
                near = []
                t_far = None
                for k in range(3):
                    t0 = (box.lo[k] - oc[k]) * inv[k]
                    t1 = (box.hi[k] - oc[k]) * inv[k]
                    near.append(np.fmin(t0, t1))
                    far = np.fmax(t0, t1)
                    t_far = far if t_far is None else np.fmin(t_far, far)
                t_near = np.fmax(np.fmax(near[0], near[1]), near[2])
                hit = (t_near <= t_far) & (t_near > t_min) & (t_near < best)
                rows = np.flatnonzero(hit)
                if rows.size:
                    best[rows] = t_near[rows]
                    which[rows] = index
                    axis[rows] = np.argmax(np.stack([near[0][rows], near[1][rows],
                                                     near[2][rows]], 1), axis=1)
        normal = np.zeros((n, 3))
        rows = np.flatnonzero(which >= 0)
        hit_axis = axis[rows]
        d_axis = np.choose(hit_axis, [dc[0][rows], dc[1][rows], dc[2][rows]])
        normal[rows, hit_axis] = -np.sign(d_axis)
        return Hits(best, which, normal)

    def footprints(self, min_z: float = -math.inf, max_z: float = math.inf
                   ) -> list[tuple[str, tuple[float, float, float, float]]]:
        """(name, (x0, y0, x1, y1)) of the boxes that overlap the height band [min_z, max_z]."""
        return [(b.name, (b.lo[0], b.lo[1], b.hi[0], b.hi[1])) for b in self.boxes
                if b.hi[2] >= min_z and b.lo[2] <= max_z]


def room_scene() -> Scene:
    """The demo room (``odom`` frame): 8 m x 6 m, walls 2.5 m high, open doorway at y = +3.

    Objects: floor (z <= 0, 0.9 m thick around the stairwell :data:`STAIRWELL`, whose four steps
    down have their tops at -0.18, -0.36, -0.54 and -0.72 m); table 1.2 x 0.8 m, top at
    0.68..0.72 m, four 4 cm legs; shelf 0.45 m deep at 1.18..1.22 m on the wall y = -3 (no legs:
    it overhangs); a crate 0.5 x 0.5 x 0.4 m; a pillar 0.3 x 0.3 m. The doorway (x in [1.5,
    2.4], z < 2.1) opens to nothing, so rays through it return nothing (+Inf).
    """
    wall_h, t = 2.5, 0.1
    x0, y0, x1, y1 = STAIRWELL
    floor = (0.35, -0.9)                                                  # albedo, bottom
    boxes = [
        Box("floor", (-4.1, -3.1, floor[1]), (x0, 3.1, 0.0), floor[0]),
        Box("floor", (x1, -3.1, floor[1]), (4.1, 3.1, 0.0), floor[0]),
        Box("floor", (x0, -3.1, floor[1]), (x1, y0, 0.0), floor[0]),
        Box("floor", (x0, y1, floor[1]), (x1, 3.1, 0.0), floor[0]),
        Box("wall", (-4.1, -3.1, 0.0), (4.1, -3.0, wall_h), 0.7),          # south, y = -3
        Box("wall", (-4.1, -3.0, 0.0), (-4.0, 3.0, wall_h), 0.7),          # west, x = -4
        Box("wall", (4.0, -3.0, 0.0), (4.1, 3.0, wall_h), 0.7),            # east, x = +4
        Box("wall", (-4.1, 3.0, 0.0), (1.5, 3.0 + t, wall_h), 0.7),        # north, left of door
        Box("wall", (2.4, 3.0, 0.0), (4.1, 3.0 + t, wall_h), 0.7),         # north, right of door
        Box("wall", (1.5, 3.0, 2.1), (2.4, 3.0 + t, wall_h), 0.7),         # lintel
        Box("table", (0.8, -1.3, 0.68), (2.0, -0.5, 0.72), 0.55),          # table top
        Box("shelf", (-1.2, -3.0, 1.18), (0.8, -2.55, 1.22), 0.8),         # overhanging shelf
        Box("crate", (-1.0, 1.4, 0.0), (-0.5, 1.9, 0.4), 0.45),
        Box("pillar", (3.0, 1.2, 0.0), (3.3, 1.5, wall_h), 0.6),
    ]
    tread = (x1 - x0) / 4
    for k in range(4):
        boxes.append(Box("stairs", (x0 + k * tread, y0, floor[1]),
                         (x0 + (k + 1) * tread, y1, -0.18 * (k + 1)), 0.4))
    leg = 0.04
    for x in (0.85, 2.0 - 0.05 - leg):
        for y in (-1.25, -0.5 - 0.05 - leg):
            boxes.append(Box("table", (x, y, 0.0), (x + leg, y + leg, 0.68), 0.3))
    return Scene(tuple(boxes))


# ------------------------------------------------------------------------------------ sensors

class SimulatedLidar3D:
    """A spinning 3D lidar with the geometry of a LidarInfo, ray-cast against a :class:`Scene`.

    Args:
        info: the sensor's LidarInfo (e.g. from :func:`converters.ouster.info_from_metadata`).
        scene: what it sees.
        noise_m: standard deviation of Gaussian range noise in metres (0: exact).
        seed: random seed of the noise and the intensity shot noise.
    """

    def __init__(self, info: Any, scene: Scene, *, noise_m: float = 0.0, seed: int = 1) -> None:
        import lidarscan

        self.info = info
        self.scene = scene
        self.noise_m = float(noise_m)
        self._rng = np.random.default_rng(seed)
        projector = lidarscan.make_projector(info)
        # P = rho * D + O: casting from O along D gives rho directly (O lies on the ray, behind
        # the beam origin by the beam's range offset).
        d = projector.directions.reshape(-1, 3).astype(np.float64)
        o = projector.offsets.reshape(-1, 3).astype(np.float64)
        self._d = [np.ascontiguousarray(d[:, k]) for k in range(3)]
        self._o = [np.ascontiguousarray(o[:, k]) for k in range(3)]
        self._albedo = np.array([b.albedo for b in scene.boxes] + [0.0])
        self.height, self.width = projector.height, projector.width
        self.range_min = float(info.range_min) or 0.0
        self.range_max = float(info.range_max) or math.inf

    def channels(self, world_from_sensor: np.ndarray[Any, Any]
                 ) -> dict[str, np.ndarray[Any, Any]]:
        """Simulated channel images (measurement column order, i.e. staggered).

        Args:
            world_from_sensor: 4x4 pose of the sensor frame (the info's frame_id) in the scene.

        Returns:
            ``range`` (H, W) float32 metres (+Inf no return, -Inf closer than range_min),
            ``intensity`` uint16, ``reflectivity`` uint8 (0..100 for diffuse targets),
            ``ambient`` uint16.
        """
        m = np.asarray(world_from_sensor, dtype=np.float64)
        # world = R p + t per component (a (N, 3) @ (3, 3) matmul is much slower here)
        origins = [m[i, 0] * self._o[0] + m[i, 1] * self._o[1] + m[i, 2] * self._o[2] + m[i, 3]
                   for i in range(3)]
        directions = [m[i, 0] * self._d[0] + m[i, 1] * self._d[1] + m[i, 2] * self._d[2]
                      for i in range(3)]
        hits = self.scene.cast_components(origins, directions)
        rho = hits.t.copy()
        if self.noise_m > 0:
            finite = np.isfinite(rho)
            rho[finite] += self._rng.normal(0.0, self.noise_m, int(finite.sum()))
        hit = np.isfinite(rho)
        too_far = hit & (rho > self.range_max)
        too_close = hit & (rho < self.range_min)
        ranges = rho.astype(np.float32)
        ranges[too_far] = np.inf
        ranges[too_close] = -np.inf
        valid = hit & ~too_far & ~too_close
        albedo = self._albedo[hits.box]
        normal = hits.normal
        cos_inc = np.abs(normal[:, 0] * directions[0] + normal[:, 1] * directions[1]
                         + normal[:, 2] * directions[2])
        r = np.where(valid, rho, 1.0)
        signal = np.where(valid, 4000.0 * albedo * (0.2 + 0.8 * cos_inc) / np.maximum(r, 0.5) ** 2,
                          0.0)
        # shot noise ~ sqrt(signal) plus a small dark count
        signal += 3.0 + np.sqrt(signal + 3.0) * self._rng.standard_normal(signal.size)
        t = np.where(valid, rho, 0.0)
        light = self.scene.light
        to_light = np.sqrt(sum((origins[k] + directions[k] * t - light[k]) ** 2
                               for k in range(3)))
        ambient = np.where(valid, 150.0 + 900.0 * albedo / (1.0 + to_light ** 2),
                           2500.0)  # rays into the open (through the doorway) see daylight
        shape = (self.height, self.width)
        return {
            "range": ranges.reshape(shape),
            "intensity": np.clip(np.round(signal), 0, 65535).astype(np.uint16).reshape(shape),
            "reflectivity": np.where(valid, np.round(100.0 * albedo), 0).astype(
                np.uint8).reshape(shape),
            "ambient": np.clip(ambient, 0, 65535).astype(np.uint16).reshape(shape),
        }

    def scan(self, world_from_sensor: np.ndarray[Any, Any], stamp_ns: int, *,
             as_dataclass: bool = True) -> Any:
        """A LidarScan (staggered, as the sensor sends it) of the scene from that pose."""
        import lidarscan

        return lidarscan.make_scan(self.info, self.channels(world_from_sensor), stamp_ns,
                                   as_dataclass=as_dataclass)


class SimulatedLaser2D:
    """A planar scanner (REP 117 values), ray-cast against a :class:`Scene`.

    Args:
        scene: what it sees.
        frame_id: header.frame_id of the scans.
        angle_min, angle_max: first and last beam (rad, CCW, in the laser frame).
        angle_increment: rad between beams; N = round((max - min) / inc) + 1 beams.
        range_min, range_max: valid interval (m); closer -> -Inf, farther or nothing -> +Inf.
        scan_time: seconds per revolution (time_increment = scan_time / beams of a full turn).
    """

    def __init__(self, scene: Scene, *, frame_id: str = "laser",
                 angle_min: float = -3 * math.pi / 4, angle_max: float = 3 * math.pi / 4,
                 angle_increment: float = math.radians(0.25), range_min: float = 0.05,
                 range_max: float = 20.0, scan_time: float = 0.1) -> None:
        self.scene = scene
        self.frame_id = frame_id
        count = round((angle_max - angle_min) / angle_increment) + 1
        self.angles = angle_min + angle_increment * np.arange(count)
        self.angle_min, self.angle_increment = float(angle_min), float(angle_increment)
        self.range_min, self.range_max, self.scan_time = range_min, range_max, scan_time
        self.time_increment = scan_time * angle_increment / (2 * math.pi)

    def ranges(self, world_from_laser: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
        """(N,) float32 ranges in metres, REP 117 (+Inf nothing in range, -Inf too close)."""
        d = np.stack([np.cos(self.angles), np.sin(self.angles), np.zeros_like(self.angles)], 1)
        rot, trans = world_from_laser[:3, :3], world_from_laser[:3, 3]
        hits = self.scene.cast(np.broadcast_to(trans, d.shape), d @ rot.T)
        out = hits.t.astype(np.float32)
        out[out > self.range_max] = np.inf
        out[out < self.range_min] = -np.inf
        return out

    def scan(self, world_from_laser: np.ndarray[Any, Any], stamp_ns: int) -> Any:
        """A ``sensor_msgs.msg.LaserScan`` of the scene from that pose."""
        import array

        from sensor_msgs.msg import LaserScan
        from std_msgs.msg import Header

        from lidarscan.stamps import time_msg

        msg = LaserScan()
        msg.header = Header(stamp=time_msg(stamp_ns), frame_id=self.frame_id)
        msg.angle_min = self.angle_min
        msg.angle_max = float(self.angles[-1])
        msg.angle_increment = self.angle_increment
        msg.time_increment = self.time_increment
        msg.scan_time = self.scan_time
        msg.range_min, msg.range_max = self.range_min, self.range_max
        msg.ranges = array.array("f", self.ranges(world_from_laser).tobytes())
        return msg


#: camera_link <- camera_depth_optical_frame (REP 103 body axes <- optical axes z forward).
LINK_FROM_OPTICAL = np.array([[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0],
                              [0.0, 0.0, 0.0, 1.0]])


class SimulatedDepthCamera:
    """A pinhole depth camera (no distortion) ray-cast against a :class:`Scene`.

    Args:
        scene: what it sees.
        width, height: image size, pixels.
        hfov: horizontal field of view, radians (square pixels, principal point at the centre).
        frame_id: the optical frame (z forward, x right, y down).
        range_min, range_max: depths (z, metres) outside this interval read 0 (no measurement,
            REP 118), as do rays that hit nothing.
    """

    def __init__(self, scene: Scene, *, width: int = 424, height: int = 240,
                 hfov: float = math.radians(87.0),
                 frame_id: str = "camera_depth_optical_frame", range_min: float = 0.1,
                 range_max: float = 6.0) -> None:
        self.scene = scene
        self.width, self.height, self.frame_id = int(width), int(height), frame_id
        self.range_min, self.range_max = float(range_min), float(range_max)
        f = self.width / 2 / math.tan(hfov / 2)
        cx, cy = (self.width - 1) / 2, (self.height - 1) / 2
        self.k = (f, 0.0, cx, 0.0, f, cy, 0.0, 0.0, 1.0)
        v, u = np.mgrid[0:self.height, 0:self.width].astype(np.float64)
        # (x, y, 1) per pixel: a hit at parameter t along it has z-depth t
        self._rays = [((u - cx) / f).reshape(-1), ((v - cy) / f).reshape(-1),
                      np.ones(u.size)]

    def depth(self, world_from_optical: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
        """(H, W) uint16 z-depth in millimetres (0 = no measurement)."""
        m = np.asarray(world_from_optical, dtype=np.float64)
        directions = [m[i, 0] * self._rays[0] + m[i, 1] * self._rays[1] + m[i, 2] * self._rays[2]
                      for i in range(3)]
        origins = [np.full(self._rays[0].size, m[i, 3]) for i in range(3)]
        z = self.scene.cast_components(origins, directions).t
        valid = (z >= self.range_min) & (z <= self.range_max)
        mm = np.where(valid, np.round(np.where(valid, z, 0.0) * 1000.0), 0.0)
        return mm.astype(np.uint16).reshape(self.height, self.width)

    def camera_info(self, stamp_ns: int) -> Any:
        """The ``sensor_msgs.msg.CameraInfo`` of every image (plumb_bob, zero distortion)."""
        from sensor_msgs.msg import CameraInfo
        from std_msgs.msg import Header

        from lidarscan.stamps import time_msg

        k = list(self.k)
        return CameraInfo(header=Header(stamp=time_msg(stamp_ns), frame_id=self.frame_id),
                          height=self.height, width=self.width, distortion_model="plumb_bob",
                          d=[0.0] * 5, k=k, r=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                          p=[k[0], 0.0, k[2], 0.0, 0.0, k[4], k[5], 0.0, 0.0, 0.0, 1.0, 0.0])

    def image(self, world_from_optical: np.ndarray[Any, Any], stamp_ns: int) -> Any:
        """A ``sensor_msgs.msg.Image`` (16UC1, little-endian) of the scene from that pose."""
        from sensor_msgs.msg import Image
        from std_msgs.msg import Header

        from lidarscan.stamps import time_msg

        depth = self.depth(world_from_optical).astype("<u2")
        msg = Image(header=Header(stamp=time_msg(stamp_ns), frame_id=self.frame_id),
                    height=self.height, width=self.width, encoding="16UC1", is_bigendian=0,
                    step=2 * self.width)
        msg.data = depth.tobytes()
        return msg


# --------------------------------------------------------------------------------- trajectory

@dataclass(frozen=True)
class Pose2D:
    """Planar robot pose and velocity at one time.

    Attributes:
        stamp_ns: time, int ns.
        x, y, yaw: pose of ``base_link`` in ``odom`` (m, rad).
        vx, wz: forward speed (m/s) and yaw rate (rad/s) in ``base_link``.
    """

    stamp_ns: int
    x: float
    y: float
    yaw: float
    vx: float
    wz: float

    def matrix(self) -> np.ndarray[Any, np.dtype[np.float64]]:
        """4x4 odom_from_base_link."""
        return pose_matrix(self.x, self.y, 0.0, yaw=self.yaw)


def trajectory(frames: int, *, rate_hz: float = 10.0, start_ns: int = START_NS,
               speed: float = 0.2, yaw_rate: float = 0.08) -> list[Pose2D]:
    """A slow arc through the room starting at (-2.2, 0.2), heading +x.

    Exact integration of a unicycle with constant ``speed`` (m/s) and ``yaw_rate`` (rad/s).
    """
    period = 1.0 / rate_hz
    out = []
    for k in range(frames):
        t = k * period
        yaw = yaw_rate * t
        if abs(yaw_rate) > 1e-12:
            x = -2.2 + speed / yaw_rate * math.sin(yaw)
            y = 0.2 + speed / yaw_rate * (1.0 - math.cos(yaw))
        else:
            x, y = -2.2 + speed * t, 0.2
        out.append(Pose2D(start_ns + round(t * 1e9), x, y, yaw, speed, yaw_rate))
    return out


# ----------------------------------------------------------------------------- ROS messages

def _transform_msg(parent: str, child: str, matrix: np.ndarray[Any, Any], stamp_ns: int) -> Any:
    from geometry_msgs.msg import Quaternion, Transform, TransformStamped, Vector3
    from std_msgs.msg import Header

    from converters.nodes.tf import quaternion_from_matrix
    from lidarscan.stamps import time_msg

    qx, qy, qz, qw = quaternion_from_matrix(matrix)
    return TransformStamped(
        header=Header(stamp=time_msg(stamp_ns), frame_id=parent), child_frame_id=child,
        transform=Transform(translation=Vector3(x=float(matrix[0, 3]), y=float(matrix[1, 3]),
                                                z=float(matrix[2, 3])),
                            rotation=Quaternion(x=qx, y=qy, z=qz, w=qw)))


def tf_message(transforms: Sequence[Any]) -> Any:
    """A ``tf2_msgs/msg/TFMessage`` (rclpy class if built, else a lidarscan dataclass)."""
    try:
        from tf2_msgs.msg import TFMessage
        return TFMessage(transforms=list(transforms))
    except ImportError:
        from lidarscan.errors import SchemaError
        from lidarscan.msgdef import find_msg_text, register_msg_text
        from lidarscan.types import message_class
        try:
            find_msg_text("tf2_msgs/msg/TFMessage")
        except SchemaError:
            register_msg_text("tf2_msgs/msg/TFMessage",
                              "geometry_msgs/TransformStamped[] transforms\n")
        return message_class("tf2_msgs/msg/TFMessage")(transforms=tuple(transforms))


def _odometry_msg(pose: Pose2D) -> Any:
    from geometry_msgs.msg import (
        Point,
        Pose,
        PoseWithCovariance,
        Quaternion,
        Twist,
        TwistWithCovariance,
        Vector3,
    )
    from nav_msgs.msg import Odometry
    from std_msgs.msg import Header

    from lidarscan.stamps import time_msg

    return Odometry(
        header=Header(stamp=time_msg(pose.stamp_ns), frame_id="odom"), child_frame_id="base_link",
        pose=PoseWithCovariance(pose=Pose(
            position=Point(x=pose.x, y=pose.y, z=0.0),
            orientation=Quaternion(x=0.0, y=0.0, z=math.sin(pose.yaw / 2),
                                   w=math.cos(pose.yaw / 2)))),
        twist=TwistWithCovariance(twist=Twist(linear=Vector3(x=pose.vx),
                                              angular=Vector3(z=pose.wz))))


# ---------------------------------------------------------------------------------- the demo

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


@dataclass
class DemoResult:
    """What :func:`run_demo` produced.

    Attributes:
        out_dir: output folder.
        mcap_path: the recording.
        images: PNG files written.
        frames: frames simulated.
        topics: topic -> (type, message count).
        sizes: name -> CDR bytes of one message (first frame): "LidarScan", "PointCloud2", ...
        timings: stage -> list of seconds per frame.
        total_s: wall time of the whole run.
    """

    out_dir: Path
    mcap_path: Path
    images: list[Path] = field(default_factory=list)
    frames: int = 0
    topics: dict[str, tuple[str, int]] = field(default_factory=dict)
    sizes: dict[str, int] = field(default_factory=dict)
    timings: dict[str, list[float]] = field(default_factory=dict)
    total_s: float = 0.0

    def summary(self) -> str:
        """A human-readable report (the CLI prints it)."""
        lines = [f"lidarscan demo: {self.frames} frames -> {self.mcap_path}"]
        lines.append("  topics:")
        for topic, (msgtype, count) in self.topics.items():
            lines.append(f"    {topic:<28} {msgtype:<32} {count:>4} msgs")
        scan = self.sizes.get("LidarScan")
        lines.append("  message sizes (CDR bytes, one frame):")
        lines.append("    (LidarScan: range f32 + intensity u16 + reflectivity u8 + ambient u16;"
                     " PointCloud2: x y z intensity f32, 16 B/point; ouster-ros: 48 B/point)")
        for name, size in self.sizes.items():
            ratio = f"  ({size / scan:.2f}x LidarScan)" if scan and name.startswith(
                "PointCloud2") else ""
            lines.append(f"    {name:<30} {size:>12,d}{ratio}")
        lines.append("  timings per frame (median, ms; the first frame also builds tables"
                     " and compiles kernels):")
        for stage, values in self.timings.items():
            if values:
                lines.append(f"    {stage:<28} {1e3 * statistics.median(values):>9.1f}"
                             f"   (first frame {1e3 * values[0]:.1f})")
        if self.images:
            lines.append("  images:")
            lines.extend(f"    {p}" for p in self.images)
        lines.append(f"  total {self.total_s:.1f} s. Open {self.mcap_path.name} in Foxglove, or "
                     f"run: lidarscan info {self.mcap_path}")
        return "\n".join(lines)


def _info(stamp_ns: int) -> Any:
    from converters.ouster import info_from_metadata

    return info_from_metadata(METADATA_PATH, stamp_ns=stamp_ns, frame_id="os_sensor")


def run_demo(out_dir: str | Path = "demo_out", frames: int = 10, *, images: bool = True,
             config: DemoConfig | None = None, noise_m: float = 0.0,
             progress: Callable[[int, int], None] | None = None) -> DemoResult:
    """Simulate, convert, record and draw: the whole pipeline in one call.

    Args:
        out_dir: folder for ``demo.mcap`` and the PNG views (created).
        frames: number of 3D/2D frames (>= 1), at ``config.rate_hz``.
        images: write the PNG views (needs matplotlib).
        config: robot set-up (default :class:`DemoConfig`).
        noise_m: range noise of the 3D lidar (standard deviation, m).
        progress: called as ``progress(done, total)`` after each frame.

    Returns:
        :class:`DemoResult` with paths, message sizes and per-stage timings.

    Raises:
        ConfigError: ``frames`` < 1.
    """
    import lidarscan
    from converters.depth import DepthImageConverter
    from converters.laserscan import SliceConverter
    from converters.merger import LaserScanMerger, MergerInput
    from converters.pointcloud2 import PointCloud2Converter
    from lidarscan.errors import ConfigError
    from lidarscan.mcap import McapWriter

    if int(frames) < 1:
        raise ConfigError("frames", frames, ">= 1")
    started = time.perf_counter()
    config = config or DemoConfig()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    result = DemoResult(out, out / "demo.mcap", frames=int(frames))
    timings: dict[str, list[float]] = {k: [] for k in (
        "ray casting (3D + 2D + depth)", "LidarScan build", "PointCloud2", "slices (3)",
        "depth image -> scan + slice", "merge", "encode + write")}
    result.timings = timings

    scene = room_scene()
    poses = trajectory(int(frames), rate_hz=config.rate_hz)
    info = _info(poses[0].stamp_ns - 1_000_000_000)
    lidar = SimulatedLidar3D(info, scene, noise_m=noise_m)
    laser = SimulatedLaser2D(scene)
    camera = SimulatedDepthCamera(scene)
    optical_mount = config.camera_mount @ LINK_FROM_OPTICAL      # base_link <- optical frame
    # the camera's LidarInfo is derived from the CameraInfo and not recorded (the recording holds
    # the Image + CameraInfo a robot would); its version key is the first image's stamp
    depth_converter = DepthImageConverter(camera.camera_info(poses[0].stamp_ns))
    camera_slicer = _camera_slicer(depth_converter.info, optical_mount, config, holes=True)
    cloud_converter = PointCloud2Converter(info)
    slicer = SliceConverter(info, {name: {"min_height": lo, "max_height": hi}
                                   for name, (lo, hi) in config.slices.items()},
                            extrinsics=config.lidar_mount, frame_id="base_link",
                            angle_min=-math.pi, angle_increment=math.radians(0.25),
                            range_min=0.1, range_max=20.0)
    merger = LaserScanMerger(
        {"full": MergerInput(extrinsics=None),
         "laser": MergerInput(extrinsics=config.laser_mount),
         "camera": MergerInput(extrinsics=None)},
        frame_id="base_link", angle_min=-math.pi, angle_increment=math.radians(0.25),
        range_min=0.1, range_max=20.0)

    counts: dict[str, list[Any]] = {}

    def write(writer: McapWriter, topic: str, msg: Any, stamp_ns: int | None = None) -> None:
        writer.write(topic, msg, log_time_ns=stamp_ns)
        entry = counts.setdefault(topic, [lidarscan.types.msgtype_of(msg), 0])
        entry[1] += 1

    last: dict[str, Any] = {}
    with McapWriter(result.mcap_path, chunk_size=1 << 20) as writer:
        static = [_transform_msg("base_link", "os_sensor", config.lidar_mount, info_stamp(info)),
                  _transform_msg("base_link", "laser", config.laser_mount, info_stamp(info)),
                  _transform_msg("base_link", "camera_link", config.camera_mount,
                                 info_stamp(info)),
                  _transform_msg("camera_link", camera.frame_id, LINK_FROM_OPTICAL,
                                 info_stamp(info))]
        write(writer, "/tf_static", tf_message(static), info_stamp(info))
        write(writer, "/lidar/info", info)
        for k, pose in enumerate(poses):
            base = pose.matrix()
            laser_stamp = pose.stamp_ns + config.laser_delay_ns
            t0 = time.perf_counter()
            channels = lidar.channels(base @ config.lidar_mount)
            laser_scan = laser.scan(base @ config.laser_mount, laser_stamp)
            image = camera.image(base @ optical_mount, pose.stamp_ns)
            camera_info = camera.camera_info(pose.stamp_ns)
            t1 = time.perf_counter()
            scan = lidarscan.make_scan(info, channels, pose.stamp_ns)
            t2 = time.perf_counter()
            cloud = cloud_converter.convert(scan)
            t3 = time.perf_counter()
            slices = slicer.convert(scan)
            t4 = time.perf_counter()
            camera_scan, _ = depth_converter.convert(image, camera_info=camera_info)
            camera_slice = camera_slicer.convert(camera_scan)["camera"]
            t4b = time.perf_counter()
            merged = merger.merge({"full": slices["full"], "laser": laser_scan,
                                   "camera": camera_slice})
            t5 = time.perf_counter()
            write(writer, "/tf", tf_message([_transform_msg("odom", "base_link", base,
                                                            pose.stamp_ns)]), pose.stamp_ns)
            write(writer, "/odom", _odometry_msg(pose))
            write(writer, "/lidar/scan", scan)
            write(writer, "/lidar/points", cloud)
            for name, slice_scan in slices.items():
                write(writer, f"/lidar/slices/{name}", slice_scan)
            write(writer, "/laser/scan", laser_scan)
            write(writer, "/camera/depth/image_rect_raw", image)
            write(writer, "/camera/depth/camera_info", camera_info)
            write(writer, "/camera/slice", camera_slice)
            if merged is not None:
                write(writer, "/scan_merged", merged)
            t6 = time.perf_counter()
            for stage, seconds in zip(timings, (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t4b - t4,
                                                t5 - t4b, t6 - t5)):
                timings[stage].append(seconds)
            if k == 0:
                from converters.pointcloud2 import to_pointcloud2

                result.sizes = {
                    "LidarScan": len(lidarscan.encode(scan)),
                    "PointCloud2": len(lidarscan.encode(cloud)),
                    "PointCloud2 ouster-ros layout": len(lidarscan.encode(
                        to_pointcloud2(scan, info, preset="ouster"))),
                    "LidarInfo (once, latched)": len(lidarscan.encode(info)),
                    "LaserScan slice 'full'": len(lidarscan.encode(slices["full"])),
                    "LaserScan 2D lidar": len(lidarscan.encode(laser_scan)),
                    "Image 16UC1 depth": len(lidarscan.encode(image)),
                    "LidarScan depth camera": len(lidarscan.encode(camera_scan)),
                }
            last = {"scan": scan, "cloud": cloud, "slices": slices, "laser": laser_scan,
                    "merged": merged, "pose": pose, "image": image, "camera_scan": camera_scan,
                    "camera_slice": camera_slice, "camera_info": depth_converter.info}
            if progress is not None:
                progress(k + 1, len(poses))
    result.topics = {topic: (msgtype, n) for topic, (msgtype, n) in counts.items()}
    if images:
        result.images = _draw(out, scene, info, last, config)
    result.total_s = time.perf_counter() - started
    return result


def _camera_slicer(info: Any, optical_mount: np.ndarray[Any, Any], config: DemoConfig, *,
                   holes: bool) -> Any:
    """The depth camera's slice (a sector of base_link covering its view, at 0.25 degrees)."""
    from converters.laserscan import SliceConverter

    lo, hi = config.camera_slice
    return SliceConverter(info, {"camera": {"min_height": lo, "max_height": hi}},
                          extrinsics=optical_mount, frame_id="base_link", angle_min=-1.3,
                          angle_max=0.4, angle_increment=math.radians(0.25), range_min=0.1,
                          range_max=6.0, intensity_channel=None, holes=holes,
                          floor_height=0.0, hole_depth=0.05, hole_range_max=3.0)


def info_stamp(info: Any) -> int:
    """The info's version key in int ns."""
    from lidarscan.stamps import to_ns

    return to_ns(info.header.stamp)


def _draw(out: Path, scene: Scene, info: Any, last: dict[str, Any], config: DemoConfig
          ) -> list[Path]:
    from converters import viz

    pose: Pose2D = last["pose"]
    base_from_odom = np.linalg.inv(pose.matrix())
    outlines = [(name, _footprint_in(base_from_odom, rect))
                for name, rect in scene.footprints(0.01, 2.0) if name not in ("floor",)]
    paths = [viz.range_image(last["scan"], info, out / "range_image.png",
                             title="Simulated OS-1-128 (destaggered), one image per channel")]
    laser_xy = viz.laserscan_xy(last["laser"], config.laser_mount)
    slice_xy = {name: viz.laserscan_xy(scan) for name, scan in last["slices"].items()}
    band = {name: f"{lo:g}..{hi:g} m" for name, (lo, hi) in config.slices.items()}
    extent = viz._extent([poly for _, poly in outlines])
    notes = _notes(base_from_odom, scene)
    panels = [("plain 2D lidar at 0.2 m: table legs only, no table top, no shelf",
               [viz.Layer("2D lidar", laser_xy, "tab:red")])]
    low = [viz.Layer(f"'{name}' {band[name]}", slice_xy[name], color)
           for name, color in (("table", "tab:orange"), ("floor_to_knee", "tab:green"))
           if name in slice_xy]
    if low:
        panels.append(("3D lidar slices: the table top appears in 'table'", low))
    rest = [viz.Layer(f"'{name}' {band[name]}", xy, "tab:blue")
            for name, xy in slice_xy.items() if name not in ("table", "floor_to_knee")]
    if rest:
        panels.append(("3D lidar slice 'full': table top and overhanging shelf", rest))
    paths.append(viz.birdseye(out / "birdseye_slices.png", panels, outlines=outlines,
                              notes=notes, extent=extent))
    if last["merged"] is not None:
        paths.append(viz.birdseye(
            out / "merged_scan.png",
            [("merged scan (slice 'full' + 2D lidar + camera slice) over the plain 2D lidar",
              [viz.Layer("2D lidar alone", laser_xy, "tab:red", size=14.0, alpha=0.35),
               viz.Layer("merged", viz.laserscan_xy(last["merged"]), "tab:purple",
                         size=2.5)])],
            outlines=outlines, notes=notes, extent=extent))
    paths.append(_draw_camera(out / "depth_camera.png", scene, last, config, base_from_odom,
                              outlines))
    paths.append(viz.cloud_topview(last["cloud"], out / "pointcloud_topview.png",
                                   extrinsics=config.lidar_mount, extent=extent,
                                   title="PointCloud2 (organized 128x2048) in base_link, "
                                         "coloured by height"))
    return paths


def hole_bins(with_holes: Any, without: Any) -> np.ndarray[Any, np.dtype[np.bool_]]:
    """(N,) bool: bins of a slice with holes whose obstacle is a hole edge, given the same slice
    without holes (the edge is nearer than anything the band saw)."""
    a = np.asarray(with_holes.ranges, np.float32)
    b = np.asarray(without.ranges, np.float32)
    with np.errstate(invalid="ignore"):
        return np.isfinite(a) & ~(a >= b)


def _draw_camera(path: Path, scene: Scene, last: dict[str, Any], config: DemoConfig,
                 base_from_odom: np.ndarray[Any, Any],
                 outlines: list[tuple[str, np.ndarray[Any, Any]]]) -> Path:
    """The depth image and the camera's slice with the detected stair edge."""
    from converters import viz

    optical_mount = config.camera_mount @ LINK_FROM_OPTICAL
    plain = _camera_slicer(last["camera_info"], optical_mount, config, holes=False).convert(
        last["camera_scan"])["camera"]
    cut = last["camera_slice"]
    ranges = np.asarray(cut.ranges, np.float64)
    angles = cut.angle_min + cut.angle_increment * np.arange(ranges.size)
    edge = hole_bins(cut, plain)
    band = np.isfinite(ranges) & ~edge
    xy = np.stack([ranges * np.cos(angles), ranges * np.sin(angles)], 1)
    image = last["image"]
    depth = np.frombuffer(bytes(image.data), "<u2").reshape(image.height, image.width)
    x0, y0, x1, y1 = STAIRWELL
    well = _footprint_in(base_from_odom, (x0, y0, x1, y1))
    fig = viz._figure(12.0, 5.4)
    ax_img, ax_top = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1.15, 1.0]})
    shown = ax_img.imshow(np.where(depth > 0, depth / 1000.0, np.nan), cmap=viz._cmap("viridis"))
    fig.colorbar(shown, ax=ax_img, shrink=0.7, label="depth z [m] (black: no measurement)")
    ax_img.set_title(f"depth image {image.width}x{image.height} 16UC1: the stairs go down "
                     "ahead, right", fontsize=9)
    ax_img.set_axis_off()
    for _, poly in outlines:
        ax_top.fill(poly[:, 0], poly[:, 1], color="0.88", zorder=0)
    ax_top.fill(well[:, 0], well[:, 1], color="#f3d9c9", zorder=0, label="stairwell (down)")
    ax_top.plot(well[:, 0], well[:, 1], color="tab:brown", lw=0.8, zorder=1)
    lo, hi = config.camera_slice
    ax_top.scatter(xy[band, 0], xy[band, 1], s=4, color="tab:blue", linewidths=0, zorder=3,
                   label=f"band {lo:g}..{hi:g} m ({int(band.sum())} bins)")
    ax_top.scatter(xy[edge, 0], xy[edge, 1], s=7, color="tab:red", linewidths=0, zorder=4,
                   label=f"hole edge ({int(edge.sum())} bins)")
    ax_top.add_patch(viz._robot_patch())
    ax_top.set_xlim(-0.5, 4.5)
    ax_top.set_ylim(-2.5, 2.5)
    ax_top.set_aspect("equal")
    ax_top.grid(True, lw=0.3)
    ax_top.set_xlabel("x [m] (forward)")
    ax_top.set_ylabel("y [m] (left)")
    ax_top.set_title("camera slice in base_link with hole detection: the drop is an obstacle",
                     fontsize=9)
    ax_top.legend(loc="upper left", fontsize=7, markerscale=2, framealpha=0.9)
    return viz._save(fig, path)


def _footprint_in(matrix: np.ndarray[Any, Any], rect: tuple[float, float, float, float]
                  ) -> np.ndarray[Any, Any]:
    x0, y0, x1, y1 = rect
    corners = np.array([[x0, y0, 0, 1], [x1, y0, 0, 1], [x1, y1, 0, 1], [x0, y1, 0, 1],
                        [x0, y0, 0, 1]], dtype=np.float64)
    out: np.ndarray[Any, Any] = (corners @ matrix.T)[:, :2]
    return out


def _notes(base_from_odom: np.ndarray[Any, Any], scene: Scene) -> list[tuple[str, float, float]]:
    notes = []
    for name in ("table", "shelf"):
        boxes = [b for b in scene.boxes if b.name == name]
        top = max(boxes, key=lambda b: b.hi[2])
        centre = np.array([(top.lo[0] + top.hi[0]) / 2, (top.lo[1] + top.hi[1]) / 2, 0.0, 1.0])
        x, y = (base_from_odom @ centre)[:2]
        label = f"{name} top {top.lo[2]:.2f}..{top.hi[2]:.2f} m"
        notes.append((label, float(x), float(y)))
    return notes


