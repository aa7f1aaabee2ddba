"""The simulated world of ``lidarscan demo`` (:mod:`converters.edge.demo.run`): the room and its ray
casting, the three sensors and the robot's trajectory.

Everything is deterministic and offline. Frames: the scene and the trajectory are in ``odom``
(metres, REP 103, z up); each sensor casts rays given its own pose in ``odom`` as a 4x4
``world_from_sensor`` (float64, parent_from_child); times are int64 ns.

* :func:`room_scene`: floor, walls with a doorway, table, overhanging shelf, crate, pillar and
  the stairwell :data:`STAIRWELL` going down; every object an axis-aligned :class:`Box`;
  :meth:`Scene.cast` intersects rays exactly with them;
* :class:`SimulatedLidar3D` (any LidarInfo geometry), :class:`SimulatedLaser2D` (a 270 degree
  scanner), :class:`SimulatedDepthCamera` (a pinhole camera, 16UC1 millimetres, REP 118; its
  optical frame: :data:`LINK_FROM_OPTICAL`);
* :func:`trajectory`: the robot's slow arc through the room (:class:`Pose2D`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = [
    "LINK_FROM_OPTICAL",
    "STAIRWELL",
    "START_NS",
    "Box",
    "Hits",
    "Pose2D",
    "Scene",
    "SimulatedDepthCamera",
    "SimulatedLaser2D",
    "SimulatedLidar3D",
    "pose_matrix",
    "room_scene",
    "trajectory",
]

START_NS = 1_700_000_000 * 1_000_000_000  # 2023-11-14, a fixed epoch: reproducible files

#: The opening of the stairwell in the floor, ``odom`` frame: (x0, y0, x1, y1) metres. The stairs
#: go down towards +x from its edge x = x0, in four steps of 0.18 m (0.25 m treads).
STAIRWELL = (-1.4, -2.0, -0.4, -0.8)


# ------------------------------------------------------------------------------------ geometry

def pose_matrix(x: float = 0.0, y: float = 0.0, z: float = 0.0, roll: float = 0.0,
                pitch: float = 0.0, yaw: float = 0.0) -> np.ndarray[Any, np.dtype[np.float64]]:
    """4x4 float64 homogeneous transform (parent_from_child) from a translation (m) and
    roll/pitch/yaw (rad), R = Rz(yaw) Ry(pitch) Rx(roll) as in tf2."""
    from converters.edge.nodes.tf import matrix_from_xyz_rpy

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
        info: the sensor's LidarInfo (e.g. from :func:`converters.sources.ouster.metadata.info_from_metadata`).
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
