"""Ouster sensors: metadata JSON -> LidarInfo and ouster-sdk frames -> LidarScan
(:mod:`.metadata`); lidar packets -> LidarScan (:mod:`.decoder`, layouts in
:mod:`.packet_format`) from pcap/pcapng captures (:mod:`.pcap`) and ouster-ros recordings
(:mod:`.bag`)."""

from converters.sources.ouster.bag import scans_from_bag
from converters.sources.ouster.decoder import PacketDecoder, decode_packets
from converters.sources.ouster.metadata import *  # noqa: F401,F403  (the public names)
from converters.sources.ouster.metadata import __all__ as _metadata_all
from converters.sources.ouster.packet_format import PROFILES, PacketLayout, layout_from_metadata
from converters.sources.ouster.pcap import lidar_packets, read_pcap, scans_from_pcap

#: the packet decoder under the name of its vendor
OusterDecoder = PacketDecoder

__all__ = [*_metadata_all, "OusterDecoder", "PROFILES", "PacketDecoder", "PacketLayout",
           "decode_packets", "layout_from_metadata", "lidar_packets", "read_pcap",
           "scans_from_bag", "scans_from_pcap"]
