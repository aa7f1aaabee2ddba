"""Parameter helpers shared by the nodes and the CLI (pure parsing here; rclpy only inside
the functions that take a node).

* :func:`parse_extrinsics`: a parameter list -> 4x4 ``target_from_sensor``;
* :class:`SliceConfig`, :func:`parse_slice_arg`, :func:`slices_from_mapping`,
  :func:`load_slices_file`: LaserScan height slices from ``NAME:ZMIN:ZMAX``, a dict or YAML;
* :func:`declare`: declare one ROS parameter with its default and description, return its value;
* :func:`qos_profile`: a QoS profile from a short name.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from lidarscan.errors import ConfigError

__all__ = [
    "QOS_NAMES",
    "SliceConfig",
    "declare",
    "load_slices_file",
    "parse_extrinsics",
    "parse_slice_arg",
    "qos_profile",
    "slices_from_mapping",
    "with_topic",
]


def parse_extrinsics(values: Any, field_name: str = "extrinsics"
                     ) -> np.ndarray[Any, np.dtype[np.float64]]:
    """4x4 float64 ``target_from_sensor`` from a flat parameter list.

    Accepted lengths: 0 (identity), 6 (x, y, z, roll, pitch, yaw: metres and radians, fixed axes
    as in tf2: R = Rz(yaw) Ry(pitch) Rx(roll)), 7 (x, y, z, qx, qy, qz, qw) or 16 (row-major 4x4,
    last row 0 0 0 1).

    Raises:
        ConfigError: another length, non-finite values, a bad last row or a zero quaternion.
    """
    from converters.nodes.tf import matrix_from_quaternion, matrix_from_xyz_rpy

    arr = np.asarray(list(values) if values is not None else [], dtype=np.float64).reshape(-1)
    if arr.size and not np.all(np.isfinite(arr)):
        raise ConfigError(field_name, arr.tolist(), "finite numbers")
    if arr.size == 0:
        return np.eye(4)
    if arr.size == 6:
        return matrix_from_xyz_rpy(*(float(v) for v in arr))
    if arr.size == 7:
        try:
            return matrix_from_quaternion(arr[3:], arr[:3])
        except ValueError as err:
            raise ConfigError(field_name, arr.tolist(), "x y z qx qy qz qw with a non-zero "
                              "quaternion") from err
    if arr.size == 16:
        m = arr.reshape(4, 4)
        if not np.allclose(m[3], (0, 0, 0, 1)):
            raise ConfigError(f"{field_name}[12:16]", m[3].tolist(), "0 0 0 1 (a rigid 4x4)")
        return m.copy()
    raise ConfigError(field_name, f"{arr.size} values",
                      "0 (identity), 6 (x y z roll pitch yaw), 7 (x y z qx qy qz qw) or 16 "
                      "(row-major 4x4)")


@dataclass(frozen=True)
class SliceConfig:
    """One named LaserScan height slice as configured (parameters, YAML or ``--slice``).

    Attributes:
        name: slice name (also the default topic suffix).
        min_height, max_height: inclusive band of z in the target frame, metres (-inf / inf
            allowed for an open side).
        topic: output topic ("" = ``slices/<name>``, filled in by the node).
        angle_min, angle_max, angle_increment, range_min, range_max: grid (radians) and planar
            range limits (metres); None = the converter's default (full circle from -pi at the
            sensor's column resolution; the LidarInfo's range limits).
        extra: further options of :class:`converters.laserscan.SliceSpec` (use_inf,
            inf_epsilon, fill), passed unchanged.
    """

    name: str
    min_height: float
    max_height: float
    topic: str = ""
    angle_min: float | None = None
    angle_max: float | None = None
    angle_increment: float | None = None
    range_min: float | None = None
    range_max: float | None = None
    extra: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.name or "/" in self.name or ":" in self.name:
            raise ConfigError("slice name", self.name, "a non-empty name without '/' or ':'")
        for attr in ("min_height", "max_height"):
            value = getattr(self, attr)
            if not isinstance(value, (int, float)) or math.isnan(value):
                raise ConfigError(f"slices.{self.name}.{attr}", value, "a number of metres")
        if not self.min_height <= self.max_height:
            raise ConfigError(f"slices.{self.name}.max_height", self.max_height,
                              f">= min_height ({self.min_height})")

    def spec(self) -> Any:
        """The :class:`converters.laserscan.SliceSpec` of this slice."""
        from converters.laserscan import SliceSpec

        values = {k: getattr(self, k) for k in ("angle_min", "angle_max", "angle_increment",
                                                 "range_min", "range_max")
                  if getattr(self, k) is not None}
        values.update(self.extra)
        try:
            return SliceSpec(self.min_height, self.max_height, **values)
        except TypeError as err:
            raise ConfigError(f"slices.{self.name}", sorted(self.extra),
                              "options of converters.laserscan.SliceSpec") from err


_SLICE_KEYS = {f.name for f in fields(SliceConfig)} - {"name", "extra"}


def parse_slice_arg(text: str) -> SliceConfig:
    """``NAME:ZMIN:ZMAX`` (metres) -> :class:`SliceConfig` (other settings default).

    Raises:
        ConfigError: not three fields, or heights that are not numbers.
    """
    parts = str(text).split(":")
    if len(parts) != 3:
        raise ConfigError("slice", text, "NAME:ZMIN:ZMAX, e.g. table:0.5:1.0")
    name, lo, hi = parts
    try:
        return SliceConfig(name.strip(), float(lo), float(hi))
    except ValueError as err:
        if isinstance(err, ConfigError):
            raise
        raise ConfigError("slice", text, "numeric ZMIN and ZMAX in metres") from err


def slices_from_mapping(data: Any, *, defaults: Mapping[str, Any] | None = None
                        ) -> list[SliceConfig]:
    """Slices from ``{name: {min_height: .., max_height: .., ...}, ...}`` (a YAML document).

    Unknown keys go to :attr:`SliceConfig.extra`. ``defaults`` apply to every slice first.

    Raises:
        ConfigError: not a mapping, a slice without min_height/max_height, bad values.
    """
    if isinstance(data, Mapping) and "slices" in data and isinstance(data["slices"], Mapping):
        data = data["slices"]
    if not isinstance(data, Mapping):
        raise ConfigError("slices", type(data).__name__, "a mapping name -> settings")
    out = []
    for name, settings in data.items():
        merged = dict(defaults or {})
        if settings is not None and not isinstance(settings, Mapping):
            raise ConfigError(f"slices.{name}", settings, "a mapping of settings")
        merged.update(settings or {})
        for key in ("min_height", "max_height"):
            if key not in merged:
                raise ConfigError(f"slices.{name}.{key}", None, "a height in metres")
        known: dict[str, Any] = {
            k: (_number(name, k, v) if k != "topic" else str(v)) if v is not None else None
            for k, v in merged.items() if k in _SLICE_KEYS}
        extra = {k: v for k, v in merged.items() if k not in _SLICE_KEYS}
        out.append(SliceConfig(str(name), extra=extra, **known))
    return out


def _number(name: str, key: str, value: Any) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError) as err:
        raise ConfigError(f"slices.{name}.{key}", value, "a number") from err
    if math.isnan(out):
        raise ConfigError(f"slices.{name}.{key}", value, "a number (not NaN)")
    return out


def load_slices_file(path: str | os.PathLike[str], *,
                     defaults: Mapping[str, Any] | None = None) -> list[SliceConfig]:
    """Slices from a YAML file (see ``config/slices.yaml``).

    Raises:
        ConfigError: unreadable file, invalid YAML or invalid slices.
    """
    import yaml

    try:
        text = Path(path).read_text(encoding="utf-8")
        data = yaml.safe_load(text)
    except (OSError, yaml.YAMLError) as err:
        raise ConfigError("slices_file", os.fspath(path), f"a readable YAML file ({err})") from err
    return slices_from_mapping(data, defaults=defaults)


def with_topic(spec: SliceConfig, namespace: str) -> SliceConfig:
    """The spec with its default topic ``<namespace>/<name>`` filled in."""
    if spec.topic:
        return spec
    prefix = namespace.rstrip("/")
    return replace(spec, topic=f"{prefix}/{spec.name}" if prefix else spec.name)


# ----------------------------------------------------------------------------- rclpy helpers

def declare(node: Any, name: str, default: Any, description: str, *,
            type_name: str | None = None) -> Any:
    """Declare a parameter with a default and description; return its (possibly overridden)
    value.

    Args:
        node: rclpy node.
        name: parameter name (dots for nesting, as YAML maps them).
        default: default value; an empty list needs ``type_name``.
        description: shown by ``ros2 param describe``.
        type_name: ``"string_array"``, ``"double_array"``, ``"integer_array"`` for empty lists.
    """
    from rcl_interfaces.msg import ParameterDescriptor
    from rclpy.parameter import Parameter

    descriptor = ParameterDescriptor(description=description)
    if isinstance(default, (list, tuple)) and not default:
        kinds = {"string_array": Parameter.Type.STRING_ARRAY,
                 "double_array": Parameter.Type.DOUBLE_ARRAY,
                 "integer_array": Parameter.Type.INTEGER_ARRAY}
        if type_name not in kinds:
            raise ConfigError(name, type_name, f"one of {sorted(kinds)} for an empty default")
        node.declare_parameter(name, kinds[type_name], descriptor)
        value = node.get_parameter_or(name, Parameter(name, value=[])).value
        return list(value) if value is not None else []
    value = node.declare_parameter(name, default, descriptor).value
    return list(value) if isinstance(value, (list, tuple)) else value


#: QoS names accepted by :func:`qos_profile`.
QOS_NAMES = ("sensor_data", "best_effort", "reliable", "latched")


def qos_profile(name: str, depth: int | None = None) -> Any:
    """QoS from a short name.

    * ``sensor_data``: best effort, volatile, keep last ``depth`` (default 5);
    * ``best_effort``: same as sensor_data;
    * ``reliable``: reliable, volatile, keep last ``depth`` (default 10);
    * ``latched``: reliable, transient local, keep last ``depth`` (default 1): late joiners
      get the last message (LidarInfo, /tf_static).

    Raises:
        ConfigError: an unknown name or a depth < 1.
    """
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    if name not in QOS_NAMES:
        raise ConfigError("qos", name, f"one of {', '.join(QOS_NAMES)}")
    if depth is not None and int(depth) < 1:
        raise ConfigError("qos depth", depth, ">= 1")
    if name in ("sensor_data", "best_effort"):
        return QoSProfile(depth=int(depth or 5), history=HistoryPolicy.KEEP_LAST,
                          reliability=ReliabilityPolicy.BEST_EFFORT,
                          durability=DurabilityPolicy.VOLATILE)
    if name == "reliable":
        return QoSProfile(depth=int(depth or 10), history=HistoryPolicy.KEEP_LAST,
                          reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.VOLATILE)
    return QoSProfile(depth=int(depth or 1), history=HistoryPolicy.KEEP_LAST,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)
