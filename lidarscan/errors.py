"""The project's exception hierarchy (one module, one base class).

Every error is built from structured context: the field (or input) that is wrong, the bad value
and what was expected, so the message reads ``field=value: expected ...`` and code can inspect
``err.field`` / ``err.value`` / ``err.expected``. Catch :class:`LidarScanError` to catch them all.

The classes also derive from the closest built-in (``ValueError``, ``KeyError``) so existing
``except ValueError`` code keeps working.
"""

from __future__ import annotations

from typing import Any

__all__ = [
    "LidarScanError",
    "ValidationError",
    "ChannelLayoutError",
    "UnknownDatatypeError",
    "UnknownChannelError",
    "InfoMismatchError",
    "LinkageError",
    "DecodeError",
    "EncodeError",
    "SchemaError",
    "McapFormatError",
    "ConfigError",
    "ConversionError",
]


def _short(value: Any, limit: int = 120) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


class LidarScanError(Exception):
    """Base class of every error raised by lidarscan and converters.

    Attributes:
        field: name of the offending field or input (``"channels[1].offset"``).
        value: the bad value (may be ``None`` when there is no single value).
        expected: human-readable statement of what was expected.
    """

    def __init__(self, field: str, value: Any, expected: str, *, hint: str = "") -> None:
        self.field = field
        self.value = value
        self.expected = expected
        self.hint = hint
        message = f"{field}={_short(value)}: expected {expected}"
        if hint:
            message += f" ({hint})"
        super().__init__(message)

    def __str__(self) -> str:  # KeyError would otherwise quote the message
        return str(self.args[0]) if self.args else ""


class ValidationError(LidarScanError, ValueError):
    """A message or argument is internally inconsistent."""


class ChannelLayoutError(ValidationError):
    """A channel block is out of bounds, overlaps another, or ``data`` has the wrong length."""


class UnknownDatatypeError(ValidationError):
    """A datatype id is not one of the PointField ids 1..8."""


class UnknownChannelError(LidarScanError, KeyError):
    """A channel name was requested that the scan does not have."""


class InfoMismatchError(ValidationError):
    """A LidarInfo is malformed or does not fit the scan (sizes, angle-array lengths, NaN)."""


class LinkageError(ValidationError):
    """A scan's ``lidar_info_time`` does not name the LidarInfo it is used with."""


class DecodeError(LidarScanError, ValueError):
    """Bytes (CDR, MCAP record, JSON, ...) could not be decoded."""


class EncodeError(LidarScanError, ValueError):
    """A message could not be encoded (value out of range for its field type, ...)."""


class SchemaError(LidarScanError, ValueError):
    """A ROS message definition could not be parsed or found."""


class McapFormatError(DecodeError):
    """An MCAP file or one of its records is malformed or lacks a schema we can decode."""


class ConfigError(LidarScanError, ValueError):
    """An option or parameter has an invalid value (e.g. ``angle_increment=0``)."""


class ConversionError(LidarScanError, ValueError):
    """Input could be decoded but cannot be converted (e.g. a cloud without x/y/z)."""
