"""What the packet decoders (converters.sources.velodyne, converters.sources.hesai.decoder) share: one UDP payload as
``bytes``, whatever buffer type the caller holds."""

from __future__ import annotations

from typing import Any

import numpy as np

from lidarscan.errors import DecodeError


def payload_bytes(packet: Any) -> bytes:
    """``packet`` (bytes, bytearray, memoryview or a 1-D uint8 ndarray) as bytes; the caller's
    buffer is never modified (a copy unless it already is ``bytes``).

    Raises:
        DecodeError: any other type or array shape/dtype.
    """
    if isinstance(packet, bytes):
        return packet
    if isinstance(packet, (bytearray, memoryview)):
        return bytes(packet)
    if isinstance(packet, np.ndarray):
        if packet.ndim != 1 or packet.dtype != np.uint8:
            raise DecodeError("packet", f"{packet.dtype} {packet.shape}", "a 1-D uint8 array")
        return packet.tobytes()
    raise DecodeError("packet", type(packet).__name__,
                      "bytes, bytearray, memoryview or a 1-D uint8 ndarray")
