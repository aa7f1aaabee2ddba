"""lidarscan: structured lidar scans (LidarScan + LidarInfo) as numpy, CDR and MCAP.

Importing this package never imports rclpy. The public API:

* build and view: :func:`make_scan`, :func:`make_info`, :func:`channel`, :func:`range_m`;
* check: :func:`validate`, :func:`validate_info` (errors in :mod:`lidarscan.errors`);
* bytes: :func:`encode`, :func:`decode`, :func:`decode_scan`, :func:`decode_info`;
* geometry: :func:`make_projector` (direction/offset tables, destagger, pixel times).

Two forms of each message, same fields, taken alike by every function here and in
``converters``: the rclpy messages ``lidarscan_msgs.msg.LidarScan`` / ``LidarInfo`` (what
:func:`make_scan` / :func:`make_info` return, to publish) and the frozen dataclasses
``lidarscan.types.LidarScan`` / ``LidarInfo`` (what the decoders return, and what ``make_*``
return with ``as_dataclass=True`` or where ``lidarscan_msgs`` is not built, as after a plain
``pip install``: see :mod:`lidarscan._install`).
"""

from lidarscan import errors
from lidarscan.cdr import decode, decode_info, decode_scan, encode
from lidarscan.geometry import Projector, make_projector
from lidarscan.scan import (
    channel,
    channel_names,
    make_info,
    make_scan,
    range_m,
    validate,
    validate_info,
)
from lidarscan.stamps import split_ns, to_ns

__all__ = [
    "errors",
    "encode",
    "decode",
    "decode_scan",
    "decode_info",
    "make_scan",
    "make_info",
    "channel",
    "channel_names",
    "range_m",
    "validate",
    "validate_info",
    "Projector",
    "make_projector",
    "to_ns",
    "split_ns",
]
