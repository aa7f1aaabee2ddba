"""Parameter helpers shared by the nodes and the CLI (pure parsing here; rclpy only inside
the functions that take a node).

* :func:`parse_extrinsics`: a parameter list -> 4x4 ``target_from_sensor``;
* :class:`SliceConfig`, :func:`parse_slice_arg`, :func:`slices_from_mapping`,
  :func:`load_slices_file`: LaserScan height slices from ``NAME:ZMIN:ZMAX``, a dict or YAML;
* :class:`ParamSpec`: one parameter's default, description, type, range, choices and whether a
  change needs a restart (``read_only``); the single table each node declares from, checks
  values with (start-up and runtime) and prints ``--help`` from;
* :func:`declare_specs`, :func:`unknown_parameters`, :class:`ParameterGuard`: rclpy glue:
  declare with descriptors, refuse unknown parameters, validate and apply runtime changes;
* :func:`help_text`: usage of a node without starting ROS;
* :func:`qos_profile`: a QoS profile from a short name.
"""

from __future__ import annotations

import difflib
import math
import os
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from lidarscan.errors import ConfigError

__all__ = [
    "QOS_NAMES",
    "ParamSpec",
    "ParameterGuard",
    "SliceConfig",
    "declare_specs",
    "help_text",
    "unknown_parameters",
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
    from converters.edge.nodes.tf import matrix_from_quaternion, matrix_from_xyz_rpy

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
        extra: further options of :class:`converters.slices.converter.SliceSpec` (use_inf,
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
        """The :class:`converters.slices.converter.SliceSpec` of this slice."""
        from converters.slices.converter import SliceSpec

        values = {k: getattr(self, k) for k in ("angle_min", "angle_max", "angle_increment",
                                                 "range_min", "range_max")
                  if getattr(self, k) is not None}
        values.update(self.extra)
        try:
            return SliceSpec(self.min_height, self.max_height, **values)
        except TypeError as err:
            raise ConfigError(f"slices.{self.name}", sorted(self.extra),
                              "options of converters.slices.converter.SliceSpec") from err


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
    from lidarscan import _yaml

    try:
        text = Path(path).read_text(encoding="utf-8")
        data = _yaml.safe_load(text)
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



# ------------------------------------------------------------------------- parameter specs

_KINDS = ("bool", "int", "float", "str", "str_list", "float_list")


@dataclass(frozen=True)
class ParamSpec:
    """One node parameter: the single source of its default, description and rules.

    Attributes:
        name: full parameter name (dots for nesting; ``NAME`` in a family template).
        default: default value; None = optional (no value unless given).
        description: one line for ``ros2 param describe`` and ``--help``.
        kind: one of bool, int, float, str, str_list, float_list ("" = from the default).
        low, high: inclusive range of an int/float (None = open side).
        choices: allowed values of a str.
        read_only: a change needs a restart (topics, QoS, structure): refused at runtime.
    """

    name: str
    default: Any
    description: str
    kind: str = ""
    low: float | None = None
    high: float | None = None
    choices: tuple[str, ...] = ()
    read_only: bool = False

    def __post_init__(self) -> None:
        if not self.kind:
            d = self.default
            kind = ("bool" if isinstance(d, bool) else "int" if isinstance(d, int) else
                    "float" if isinstance(d, float) else "str" if isinstance(d, str) else "")
            if not kind:
                raise ConfigError(f"ParamSpec {self.name}.kind", self.kind, f"one of {_KINDS}")
            object.__setattr__(self, "kind", kind)
        if self.kind not in _KINDS:
            raise ConfigError(f"ParamSpec {self.name}.kind", self.kind, f"one of {_KINDS}")

    def expected(self) -> str:
        """What a value must be, in words."""
        text = {"bool": "true or false", "int": "an integer", "float": "a number",
                "str": "a string", "str_list": "a list of strings",
                "float_list": "a list of numbers"}[self.kind]
        if self.choices:
            text = f"one of {', '.join(self.choices)}"
        if self.low is not None and self.high is not None:
            text += f" in [{self.low:g}, {self.high:g}]"
        elif self.low is not None:
            text += f" >= {self.low:g}"
        elif self.high is not None:
            text += f" <= {self.high:g}"
        return text

    def check(self, value: Any) -> Any:
        """The value as the node uses it (an int accepted for a float).

        Raises:
            ConfigError: naming the parameter, the value and what was expected (None/unset,
                text where a number belongs, out of range, not a choice).
        """
        bad = ConfigError(self.name, value, self.expected())
        if value is None:
            if self.default is None and self.kind != "bool":
                return None
            raise bad
        if self.kind == "bool":
            if not isinstance(value, bool):
                raise bad
            return value
        if self.kind in ("int", "float"):
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise bad
            if self.kind == "int" and not isinstance(value, int):
                raise bad
            if self.kind == "float":
                value = float(value)
                if math.isnan(value):
                    raise bad
            if (self.low is not None and value < self.low) or \
                    (self.high is not None and value > self.high):
                raise bad
            return value
        if self.kind == "str":
            if not isinstance(value, str) or (self.choices and value not in self.choices):
                raise bad
            return value
        if isinstance(value, (str, bytes)) or not isinstance(value, Iterable):
            raise bad
        items = list(value)
        if self.kind == "str_list":
            if not all(isinstance(v, str) for v in items):
                raise bad
            return items
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in items):
            raise bad
        return [float(v) for v in items]

    def for_name(self, name: str) -> ParamSpec:
        """This family template (``slices.NAME.x``) for one member name."""
        return replace(self, name=self.name.replace("NAME", name),
                       description=self.description.replace("NAME", name))

    def descriptor(self) -> Any:
        """The rclpy ``ParameterDescriptor`` (description, read_only, range, choices).

        Scalars are declared with dynamic typing so that the node's own check (:meth:`check`)
        decides, with a reason naming the parameter, and an integer is accepted for a float;
        lists are statically typed.
        """
        from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor

        desc = ParameterDescriptor(description=self.description, read_only=self.read_only,
                                   dynamic_typing=self.kind not in ("str_list", "float_list"))
        constraints = []
        if self.choices:
            constraints.append(f"one of {', '.join(self.choices)}")
        if self.low is not None or self.high is not None:
            if self.kind == "int":
                desc.integer_range = [IntegerRange(
                    from_value=int(self.low if self.low is not None else -2**63),
                    to_value=int(self.high if self.high is not None else 2**63 - 1), step=0)]
            else:
                desc.floating_point_range = [FloatingPointRange(
                    from_value=float(self.low if self.low is not None else -math.inf),
                    to_value=float(self.high if self.high is not None else math.inf), step=0.0)]
            constraints.append(self.expected())
        if self.read_only:
            constraints.append("read-only: a change needs a restart")
        desc.additional_constraints = "; ".join(constraints)
        return desc


def _shown(value: Any) -> str:
    if value is None:
        return "(unset)"
    if isinstance(value, str):
        return repr(value) if value == "" else value
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, float) and math.isinf(value):
        return ".inf" if value > 0 else "-.inf"
    return str(list(value)) if isinstance(value, (list, tuple)) else f"{value:g}" \
        if isinstance(value, float) else str(value)


def help_text(script: str, summary: str, topics: Sequence[tuple[str, str, str]],
              specs: Sequence[ParamSpec], families: Mapping[str, Sequence[ParamSpec]] = {},
              example: str = "") -> str:
    """``--help`` of a node (no ROS needed): usage, topics, every parameter with default,
    rule and description, the per-NAME families.

    Args:
        script: console script name.
        summary: one paragraph.
        topics: (topic, direction and type, note) rows.
        specs: the node's parameters.
        families: heading -> template specs (names with ``NAME``).
        example: the config file of the node.
    """
    lines = [f"usage: {script} [-h] [--ros-args -p NAME:=VALUE ... --params-file FILE "
             "-r FROM:=TO ...]", "", summary, "", "topics (relative names; remap with -r):"]
    width = max((len(t[0]) for t in topics), default=0)
    kinds = max((len(t[1]) for t in topics), default=0)
    lines += [f"  {t:<{width}}  {kind:<{kinds}}  {note}".rstrip() for t, kind, note in topics]

    def rows(items: Sequence[ParamSpec]) -> list[str]:
        out = []
        for spec in items:
            rule = spec.expected() + ("; read-only" if spec.read_only else "; live")
            out.append(f"  {spec.name} [{_shown(spec.default)}]  ({rule})")
            out.append(f"      {spec.description}")
        return out

    lines += ["", "parameters [default] (rule; 'live' = may be changed while running, "
              "'read-only' = needs a restart):"]
    lines += rows(specs)
    for heading, items in families.items():
        lines += ["", heading]
        lines += rows(items)
    lines += ["", "An unknown parameter (e.g. a typo) stops the node at start-up unless "
              "allow_unknown_parameters:=true.", "Diagnostics: /diagnostics "
              "(diagnostic_msgs/DiagnosticArray, 1 Hz)."]
    if example:
        lines.append(f"Example: {script} --ros-args --params-file {example}")
    return "\n".join(lines)


def declare_specs(node: Any, specs: Iterable[ParamSpec]) -> dict[str, Any]:
    """Declare every spec with its descriptor; return name -> checked value.

    Raises:
        ConfigError: a value given at start-up (``-p``, ``--params-file``) that breaks a rule,
            naming the parameter.
    """
    from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
    from rclpy.parameter import Parameter

    kinds = {"str_list": Parameter.Type.STRING_ARRAY, "float_list": Parameter.Type.DOUBLE_ARRAY}
    values: dict[str, Any] = {}
    given = getattr(node, "_parameter_overrides", {}) or {}  # noqa: SLF001 - no public view
    for spec in specs:
        if spec.name in given:  # our rule and message first, rclpy's descriptor checks after
            value = given[spec.name].value
            if value is None and spec.kind in kinds:    # YAML [] has no element type
                value = []
            spec.check(value)
        desc = spec.descriptor()
        try:
            if spec.kind in kinds and not spec.default:
                node.declare_parameter(spec.name, kinds[spec.kind], desc)
                raw = node.get_parameter_or(spec.name, Parameter(spec.name, value=[])).value
                raw = [] if raw is None else raw
            else:
                default = list(spec.default) if isinstance(spec.default, tuple) else spec.default
                raw = node.declare_parameter(spec.name, default, desc).value
        except (InvalidParameterTypeException, InvalidParameterValueException) as err:
            raise ConfigError(spec.name, "the value given", f"{spec.expected()} ({err})") from err
        values[spec.name] = spec.check(raw)
    return values


#: parameters rclpy declares itself (or that the ROS tools set) and that are not unknown.
_ROS_OWN_PREFIXES = ("qos_overrides.",)


def unknown_parameters(node: Any) -> list[str]:
    """Names given to the node (``-p``, ``--params-file``, overrides) that it never declared,
    each with a suggestion ("target_fram (did you mean target_frame?)")."""
    given = getattr(node, "_parameter_overrides", {}) or {}
    declared = [n for n in node._parameters]  # noqa: SLF001 - rclpy keeps no public list
    out = []
    for name in sorted(given):
        if node.has_parameter(name) or name.startswith(_ROS_OWN_PREFIXES):
            continue
        close = difflib.get_close_matches(name, declared, n=1, cutoff=0.6)
        out.append(f"{name} (did you mean {close[0]}?)" if close else name)
    return out


def refuse_unknown(node: Any, allow: bool) -> list[str]:
    """Log each unknown parameter; raise unless ``allow``.

    Raises:
        ConfigError: unknown parameters and ``allow`` false.
    """
    unknown = unknown_parameters(node)
    if unknown:
        line = f"unknown parameter(s): {'; '.join(unknown)}"
        if not allow:
            raise ConfigError("parameters", unknown, "parameters of this node (see --help), "
                              "or allow_unknown_parameters:=true to run anyway")
        node.get_logger().warning(line + " (ignored: allow_unknown_parameters is true)")
    return unknown


class ParameterGuard:
    """Runtime parameter changes: check, validate with the library, apply.

    ``SetParameters`` (``ros2 param set``, a client) runs :meth:`on_set` first: each value is
    checked by its :class:`ParamSpec` (type, None, range, choices; read-only ones are refused by
    rclpy from the descriptor), then ``validate(candidate)`` builds the library objects with
    the candidate values (a :class:`~lidarscan.errors.LidarScanError` becomes the rejection
    reason). Only an accepted change reaches ``apply(values, changed)`` (after rclpy stored it).

    Args:
        node: rclpy node (the callbacks are registered on it).
        specs: name -> spec of every declared parameter.
        values: the current values (updated on apply).
        validate: raises LidarScanError when the candidate values do not make a working node.
        apply: takes effect (rebuild converters, reconfigure the merger).
    """

    def __init__(self, node: Any, specs: Mapping[str, ParamSpec], values: dict[str, Any],
                 validate: Callable[[dict[str, Any]], None],
                 apply: Callable[[dict[str, Any], set[str]], None]) -> None:
        self.specs = dict(specs)
        self.values = values
        self._validate = validate
        self._apply = apply
        self._accepted: tuple[dict[str, Any], set[str]] | None = None
        self.rejected = 0
        node.add_on_set_parameters_callback(self.on_set)
        node.add_post_set_parameters_callback(self.on_applied)

    def candidate(self, changes: Iterable[tuple[str, Any]]) -> tuple[dict[str, Any], set[str]]:
        """(values with the changes, changed names).

        Raises:
            ConfigError: an unknown name or a value that breaks its spec.
        """
        values = dict(self.values)
        changed = set()
        for name, raw in changes:
            spec = self.specs.get(name)
            if spec is None:
                raise ConfigError(name, raw, "a parameter of this node")
            if raw is None and spec.default is None:
                raise ConfigError(name, None, f"{spec.expected()} (an optional parameter cannot "
                                  "be unset while running)")
            values[name] = spec.check(raw)
            changed.add(name)
        return values, changed

    def on_set(self, parameters: list[Any]) -> Any:
        from rcl_interfaces.msg import SetParametersResult

        from lidarscan.errors import LidarScanError

        try:
            values, changed = self.candidate((p.name, p.value) for p in parameters)
            self._validate(values)
        except LidarScanError as err:
            self.rejected += 1
            self._accepted = None
            return SetParametersResult(successful=False, reason=str(err))
        self._accepted = (values, changed)
        return SetParametersResult(successful=True)

    def on_applied(self, parameters: list[Any]) -> None:
        if self._accepted is None:
            return
        values, changed = self._accepted
        self._accepted = None
        self.values.clear()
        self.values.update(values)
        self._apply(values, changed)
