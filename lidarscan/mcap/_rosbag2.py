"""The rosbag2 metadata of the MCAP files the project writes (no rclpy): recorded QoS profiles,
their YAML forms, the bag metadata (version 9) and its YAML text.

Below the writer (:mod:`lidarscan.mcap._writer` records them in every file) and re-exported by
:mod:`lidarscan.rosbag2`, whose docstring states the conventions.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from lidarscan.errors import ConfigError, McapFormatError
from lidarscan.mcap._records import INFO_TYPE

__all__ = [
    "QosProfile",
    "QOS_PROFILES",
    "TopicRecord",
    "bag_metadata",
    "default_qos",
    "dump_qos",
    "metadata_yaml",
    "parse_qos",
    "qos_profile",
]

METADATA_VERSION = 9
ROS_DISTRO = "jazzy"
_INFINITE = (9223372036, 854775807)   # RMW_DURATION_INFINITE as rosbag2 stores it

# enum values of rmw (and of rosbag2 metadata version <= 8, which stores them as integers)
_HISTORY = {0: "system_default", 1: "keep_last", 2: "keep_all", 3: "unknown"}
_RELIABILITY = {0: "system_default", 1: "reliable", 2: "best_effort", 3: "unknown",
                4: "best_available"}
_DURABILITY = {0: "system_default", 1: "transient_local", 2: "volatile", 3: "unknown",
               4: "best_available"}
_LIVELINESS = {0: "system_default", 1: "automatic", 3: "manual_by_topic", 4: "unknown",
               5: "best_available"}


@dataclass(frozen=True)
class QosProfile:
    """One recorded QoS profile (rmw's policies by name; durations in ns, None = infinite).

    Attributes:
        history: ``keep_last`` | ``keep_all`` | ``system_default``.
        depth: queue depth (keep_last).
        reliability: ``reliable`` | ``best_effort`` | ``system_default`` | ``best_available``.
        durability: ``volatile`` | ``transient_local`` | ``system_default`` | ``best_available``.
        deadline_ns, lifespan_ns, liveliness_lease_duration_ns: None = infinite.
        liveliness: ``automatic`` | ``manual_by_topic`` | ``system_default``.
        avoid_ros_namespace_conventions: rmw flag.
    """

    history: str = "keep_last"
    depth: int = 10
    reliability: str = "reliable"
    durability: str = "volatile"
    deadline_ns: int | None = None
    lifespan_ns: int | None = None
    liveliness: str = "automatic"
    liveliness_lease_duration_ns: int | None = None
    avoid_ros_namespace_conventions: bool = False

    def __post_init__(self) -> None:
        for name, table in (("history", _HISTORY), ("reliability", _RELIABILITY),
                            ("durability", _DURABILITY), ("liveliness", _LIVELINESS)):
            value = getattr(self, name)
            if value not in table.values():
                raise ConfigError(f"qos.{name}", value,
                                  f"one of {', '.join(sorted(set(table.values())))}")
        if isinstance(self.depth, bool) or not isinstance(self.depth, int) or self.depth < 0:
            raise ConfigError("qos.depth", self.depth, "an integer >= 0")

    def to_dict(self) -> dict[str, Any]:
        """The profile in rosbag2's YAML form (metadata version 9)."""
        return {
            "history": self.history,
            "depth": self.depth,
            "reliability": self.reliability,
            "durability": self.durability,
            "deadline": _duration(self.deadline_ns),
            "lifespan": _duration(self.lifespan_ns),
            "liveliness": self.liveliness,
            "liveliness_lease_duration": _duration(self.liveliness_lease_duration_ns),
            "avoid_ros_namespace_conventions": self.avoid_ros_namespace_conventions,
        }

    @classmethod
    def from_dict(cls, item: Mapping[str, Any]) -> QosProfile:
        """Parse one profile of rosbag2's YAML form: names (version 9) or integers (<= 8).

        Raises:
            McapFormatError: a missing key or an unknown policy value.
        """
        try:
            return cls(
                history=_policy("history", item["history"], _HISTORY),
                depth=int(item["depth"]),
                reliability=_policy("reliability", item["reliability"], _RELIABILITY),
                durability=_policy("durability", item["durability"], _DURABILITY),
                deadline_ns=_parse_duration(item.get("deadline")),
                lifespan_ns=_parse_duration(item.get("lifespan")),
                liveliness=_policy("liveliness", item.get("liveliness", "automatic"),
                                   _LIVELINESS),
                liveliness_lease_duration_ns=_parse_duration(
                    item.get("liveliness_lease_duration")),
                avoid_ros_namespace_conventions=bool(
                    item.get("avoid_ros_namespace_conventions", False)),
            )
        except (KeyError, TypeError, ValueError, ConfigError) as err:
            raise McapFormatError("offered_qos_profiles", dict(item) if isinstance(
                item, Mapping) else item, "a rosbag2 QoS profile (history, depth, "
                "reliability, durability, ...)", hint=str(err)) from err


def _duration(ns: int | None) -> dict[str, int]:
    if ns is None:
        return {"sec": _INFINITE[0], "nsec": _INFINITE[1]}
    return {"sec": int(ns) // 1_000_000_000, "nsec": int(ns) % 1_000_000_000}


def _parse_duration(node: Any) -> int | None:
    if node is None:
        return None
    sec, nsec = int(node["sec"]), int(node["nsec"])
    # the infinite value of rmw, and those of Foxy-era recordings (Fast DDS, Connext, Cyclone)
    if (sec, nsec) in (_INFINITE, (0x7FFFFFFF, 0xFFFFFFFF), (0x7FFFFFFF, 0x7FFFFFFF)) \
            or sec * 1_000_000_000 + nsec >= 0x7FFFFFFFFFFFFFFF:
        return None
    return sec * 1_000_000_000 + nsec


def _policy(name: str, value: Any, table: Mapping[int, str]) -> str:
    if isinstance(value, bool):
        raise ValueError(f"{name}: {value!r}")
    if isinstance(value, int):
        return table[value]
    text = str(value).lower()
    if text not in table.values():
        raise ValueError(f"{name}: {value!r}")
    return text


QOS_PROFILES: dict[str, QosProfile] = {
    "sensor_data": QosProfile(depth=5, reliability="best_effort"),
    "best_effort": QosProfile(depth=5, reliability="best_effort"),
    "reliable": QosProfile(depth=10),
    "latched": QosProfile(depth=1, durability="transient_local"),
}
"""The project's QoS names (those of the nodes' ``*_qos`` parameters) as recorded profiles."""

_SENSOR_TYPES = frozenset({
    "lidarscan_msgs/msg/LidarScan", "sensor_msgs/msg/PointCloud2", "sensor_msgs/msg/LaserScan",
    "sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage", "sensor_msgs/msg/Imu",
    "sensor_msgs/msg/PointCloud", "sensor_msgs/msg/Range",
})
_LATCHED_TOPICS = ("/tf_static",)


def qos_profile(value: str | QosProfile | Mapping[str, Any]) -> QosProfile:
    """A QoS profile from a name of :data:`QOS_PROFILES`, a profile, or rosbag2's dict form.

    A dict may give only some keys: the rest are those of the ``reliable`` profile.

    Raises:
        ConfigError: an unknown name or an invalid value.
    """
    if isinstance(value, QosProfile):
        return value
    if isinstance(value, str):
        if value not in QOS_PROFILES:
            raise ConfigError("qos", value, f"one of {', '.join(QOS_PROFILES)}")
        return QOS_PROFILES[value]
    if isinstance(value, Mapping):
        full = {**QOS_PROFILES["reliable"].to_dict(), **value}
        try:
            return QosProfile.from_dict(full)
        except McapFormatError as err:
            raise ConfigError("qos", dict(value), "a QoS profile in rosbag2's form",
                              hint=err.hint) from err
    raise ConfigError("qos", value, "a QoS name, a QosProfile or a mapping")


def default_qos(topic: str, msgtype: str) -> QosProfile:
    """The QoS recorded for ``topic`` when the writer is not told otherwise (module docstring)."""
    if msgtype == INFO_TYPE or topic in _LATCHED_TOPICS:
        return QOS_PROFILES["latched"]
    if msgtype in _SENSOR_TYPES:
        return QOS_PROFILES["sensor_data"]
    return QOS_PROFILES["reliable"]


def dump_qos(profiles: Iterable[QosProfile]) -> str:
    """Channel metadata value ``offered_qos_profiles``: YAML text of the profiles' list."""
    import yaml

    items = [p.to_dict() for p in profiles]
    if not items:
        return ""
    return str(yaml.safe_dump(items, sort_keys=False, default_flow_style=False)).strip()


def parse_qos(text: str | Sequence[Mapping[str, Any]]) -> list[QosProfile]:
    """Profiles from ``offered_qos_profiles``: YAML text (channel metadata) or the list of a
    ``metadata.yaml`` of version 9; "" gives [].

    Raises:
        McapFormatError: text that is not a list of profiles.
    """
    import yaml
    from lidarscan import _yaml

    if isinstance(text, str):
        if not text.strip():
            return []
        try:
            items = _yaml.safe_load(text)
        except yaml.YAMLError as err:
            raise McapFormatError("offered_qos_profiles", text[:80], "YAML text") from err
    else:
        items = text
    if not isinstance(items, list) or not all(isinstance(i, Mapping) for i in items):
        raise McapFormatError("offered_qos_profiles", items, "a list of QoS profiles")
    return [QosProfile.from_dict(i) for i in items]


@dataclass(frozen=True)
class TopicRecord:
    """One recorded topic of a bag: name, type, offered QoS and message count."""

    name: str
    msgtype: str
    qos: tuple[QosProfile, ...]
    message_count: int
    serialization_format: str = "cdr"
    type_description_hash: str = ""


def bag_metadata(topics: Iterable[TopicRecord], *, file_name: str, start_ns: int,
                 end_ns: int, custom_data: Mapping[str, str] | None = None) -> dict[str, Any]:
    """The bag metadata (version 9) of one MCAP file named ``file_name``.

    ``start_ns`` / ``end_ns``: first and last message log time (0, 0 for an empty file).
    """
    topics = list(topics)
    count = sum(t.message_count for t in topics)
    duration = max(0, int(end_ns) - int(start_ns))
    return {
        "version": METADATA_VERSION,
        "storage_identifier": "mcap",
        "duration": {"nanoseconds": duration},
        "starting_time": {"nanoseconds_since_epoch": int(start_ns)},
        "message_count": count,
        "topics_with_message_count": [
            {"topic_metadata": {"name": t.name, "type": t.msgtype,
                                "serialization_format": t.serialization_format,
                                "offered_qos_profiles": [q.to_dict() for q in t.qos],
                                "type_description_hash": t.type_description_hash},
             "message_count": t.message_count}
            for t in topics],
        "compression_format": "",
        "compression_mode": "",
        "relative_file_paths": [file_name],
        "files": [{"path": file_name, "starting_time": {"nanoseconds_since_epoch": int(start_ns)},
                   "duration": {"nanoseconds": duration}, "message_count": count}],
        "custom_data": dict(custom_data or {}),
        "ros_distro": ROS_DISTRO,
    }


def metadata_yaml(metadata: Mapping[str, Any], *, root: bool = True) -> str:
    """YAML text of :func:`bag_metadata`: with the root key of ``metadata.yaml``, or without it
    (the ``serialized_metadata`` of the MCAP ``rosbag2`` record)."""
    import yaml

    node = {"rosbag2_bagfile_information": dict(metadata)} if root else dict(metadata)
    return str(yaml.safe_dump(node, sort_keys=False, default_flow_style=False))
