"""rosbag2 conventions for the MCAP files the project writes (no rclpy).

What makes an MCAP file a rosbag2 recording that ``ros2 bag play`` replays faithfully
(rosbag2 metadata version 9, as ROS 2 Jazzy's ``rosbag2_storage_mcap`` writes it):

* every channel's metadata has ``offered_qos_profiles``: the QoS the recorded publishers offered,
  as YAML text of a list of maps ``history, depth, reliability, durability, deadline, lifespan,
  liveliness, liveliness_lease_duration, avoid_ros_namespace_conventions``; policies are
  lower-case names (``keep_last``, ``best_effort``, ``transient_local``, ``automatic``),
  durations ``{sec, nsec}`` with ``sec: 9223372036, nsec: 854775807`` meaning infinite.
  The player offers this QoS. A channel without it is replayed reliable + volatile, so a
  latched topic (``LidarInfo``, ``/tf_static``) never reaches a subscriber that asks for
  transient local durability (the converter node's LidarInfo input);
* one MCAP ``Metadata`` record named ``rosbag2`` whose key ``serialized_metadata`` is the bag
  metadata (what ``metadata.yaml`` holds under its root key ``rosbag2_bagfile_information``);
* a bag is a directory with ``metadata.yaml`` and the ``.mcap`` file(s) it lists
  (:class:`BagWriter`).

Default QoS by topic (what the project's nodes and the usual drivers offer): ``LidarInfo`` and
``/tf_static`` latched (reliable, transient local, depth 1); scans, clouds, images and IMU data
sensor-data (best effort, volatile, depth 5); everything else reliable, volatile, depth 10.
Times are int64 nanoseconds.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from lidarscan.errors import ConfigError
from lidarscan.mcap import McapWriter
from lidarscan.mcap._rosbag2 import (
    METADATA_VERSION as METADATA_VERSION,
    QOS_PROFILES,
    ROS_DISTRO as ROS_DISTRO,
    QosProfile,
    TopicRecord,
    bag_metadata,
    default_qos,
    dump_qos,
    metadata_yaml,
    parse_qos,
    qos_profile,
)

__all__ = [
    "QosProfile",
    "QOS_PROFILES",
    "BagWriter",
    "TopicRecord",
    "bag_metadata",
    "default_qos",
    "dump_qos",
    "metadata_yaml",
    "parse_qos",
    "qos_profile",
]


class BagWriter(McapWriter):
    """Write a rosbag2 directory: ``<directory>/<name>_0.mcap`` and ``metadata.yaml``.

        with BagWriter("run1") as bag:                 # run1/run1_0.mcap, run1/metadata.yaml
            bag.write("/lidar/info", info)
            bag.write("/lidar/scan", scan)

    ``ros2 bag info run1`` / ``ros2 bag play run1`` accept it. Keyword arguments are those of
    :class:`lidarscan.mcap.McapWriter` (``qos`` overrides the recorded QoS per topic).
    ``metadata.yaml`` is written last, on close: a run interrupted before it leaves a plain
    MCAP file (``ros2 bag reindex`` rebuilds the metadata).

    Raises:
        ConfigError: ``directory`` exists and is not empty.
    """

    def __init__(self, directory: str | os.PathLike[str], **options: Any) -> None:
        path = Path(directory)
        if path.exists() and (not path.is_dir() or any(path.iterdir())):
            raise ConfigError("directory", str(path), "a new or empty directory for the bag")
        path.mkdir(parents=True, exist_ok=True)
        self.directory = path
        self.mcap_path = path / f"{path.name}_0.mcap"
        super().__init__(self.mcap_path, **options)

    def close(self) -> None:
        """Finish the MCAP file, then write ``metadata.yaml``."""
        if self._closed:
            return
        super().close()
        text = metadata_yaml(self.bag_metadata())
        tmp = self.directory / "metadata.yaml.tmp"
        tmp.write_text(text, encoding="utf-8")
        tmp.replace(self.directory / "metadata.yaml")
