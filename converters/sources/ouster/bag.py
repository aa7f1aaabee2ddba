"""ouster-ros recordings (rosbag2, MCAP or .db3): lidar packets + the sensor's metadata.

ouster-ros publishes, under its namespace (default ``/ouster``):

* ``<ns>/lidar_packets``: ``ouster_sensor_msgs/msg/PacketMsg`` (one field ``uint8[] buf``, one
  UDP payload per message; older releases name the package ``ouster_msgs``);
* ``<ns>/metadata``: ``std_msgs/msg/String``, the sensor's metadata JSON (latched, so a
  recording has it once, usually first);
* ``<ns>/imu_packets``: the IMU's packets, the same PacketMsg type (not lidar data: never
  decoded; ``lidarscan convert`` copies them like any other topic).

The metadata is taken from the recording itself (the ``metadata`` topic of the packets'
namespace, else the only String topic named ``.../metadata``); without one the caller passes
it (``lidarscan convert --metadata``). CDR: 4-byte encapsulation header, then a uint32 length
and the bytes (String: with a terminating NUL), alignment relative to the payload.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from typing import Any

from converters.sources.bags import _Cdr
from lidarscan.errors import ConfigError

__all__ = ["STRING_TYPE", "find_metadata", "metadata_topic", "scans_from_bag",
           "string_payload"]

STRING_TYPE = "std_msgs/msg/String"


def string_payload(cdr: Any) -> str:
    """The ``data`` of a std_msgs/String's CDR bytes (a uint32 length, then the text and its
    terminating NUL).

    Raises:
        DecodeError: bad encapsulation, a length beyond the message.
    """
    reader = _Cdr(cdr, "String")
    raw = bytes(reader.take(reader.count("data", 1), "data"))
    return raw[:-1].decode("utf-8", errors="replace") if raw.endswith(b"\x00") else \
        raw.decode("utf-8", errors="replace")


def _namespace(topic: str) -> str:
    return topic.rsplit("/", 1)[0]


def metadata_topic(topics: dict[str, str], packet_topic: str) -> str | None:
    """The metadata topic for ``packet_topic`` among ``topics`` (name -> type), or None."""
    same = f"{_namespace(packet_topic)}/metadata"
    if topics.get(same) == STRING_TYPE:
        return same
    others = [t for t, k in topics.items() if k == STRING_TYPE and t.endswith("/metadata")]
    return others[0] if len(others) == 1 else None


def find_metadata(bag: Any, packet_topic: str) -> str | None:
    """The metadata JSON recorded next to ``packet_topic`` in an open bag
    (:func:`converters.sources.bags.open_bag`), or None when the recording has none."""
    from lidarscan.mcap import McapMessage

    topics = {name: t.msgtype for name, t in bag.topics.items()}
    topic = metadata_topic(topics, packet_topic)
    if topic is None:
        return None
    for item in bag.messages([topic]):
        if isinstance(item, McapMessage):
            text = string_payload(item.payload)
            if text.strip():
                return text
    return None


def scans_from_bag(path: str | os.PathLike[str], metadata: Any = None, *,
                   topic: str | None = None, **kw: Any) -> Iterator[tuple[Any, Any]]:
    """(LidarScan, LidarInfo) per frame of an ouster-ros recording.

    Args:
        path: rosbag2 directory, ``.db3`` or ``.mcap`` file.
        metadata: the sensor's metadata; default the one recorded next to the packets.
        topic: the packet topic; default the recording's only PacketMsg topic of lidar
            packets (``<ns>/imu_packets`` are IMU packets: never decoded).
        kw: options of :class:`converters.sources.ouster.decoder.PacketDecoder`.

    Raises:
        ConfigError: no (or several) packet topics, no metadata in the recording and none given.
    """
    from converters.sources.bags import (OUSTER_PACKET_TYPES, is_packet_topic, open_bag,
                                         ouster_packets)
    from converters.sources.ouster.decoder import decode_packets
    from lidarscan.mcap import McapMessage

    bag = open_bag(path)
    packet_topics = sorted(t for t, info in bag.topics.items()
                           if info.msgtype in OUSTER_PACKET_TYPES
                           and is_packet_topic(t, info.msgtype))
    if topic is None:
        if len(packet_topics) != 1:
            raise ConfigError("topic", packet_topics or None,
                              f"one {OUSTER_PACKET_TYPES[0]} topic in {path} (name it)")
        topic = packet_topics[0]
    elif topic not in packet_topics:
        raise ConfigError("topic", topic, f"a PacketMsg topic of {path}: {packet_topics}")
    if metadata is None:
        metadata = find_metadata(bag, topic)
        if metadata is None:
            raise ConfigError("metadata", None, f"the sensor's metadata JSON: {path} has no "
                              f"{_namespace(topic)}/metadata (std_msgs/String) topic")
    # decoded in runs of a few hundred packets (the decoder's batch entry), read lazily
    yield from decode_packets(((item.log_time_ns, ouster_packets(item.payload).data[0])
                               for item in bag.messages([topic])
                               if isinstance(item, McapMessage)), metadata, **kw)

