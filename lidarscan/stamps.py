"""Time stamps as int64 nanoseconds (the project's internal time representation)."""

from __future__ import annotations

from typing import Any

from lidarscan.errors import ValidationError

__all__ = ["to_ns", "split_ns", "time_msg"]

_NS = 1_000_000_000


def to_ns(stamp: Any, *, field: str = "stamp") -> int:
    """int64 ns of a ``builtin_interfaces/Time`` (rclpy or dataclass) or of an int.

    Raises:
        ValidationError: ``nanosec`` outside [0, 1e9).
    """
    if isinstance(stamp, int):
        return stamp
    sec, nanosec = int(stamp.sec), int(stamp.nanosec)
    if not 0 <= nanosec < _NS:
        raise ValidationError(f"{field}.nanosec", nanosec, "0 <= nanosec < 1000000000")
    return sec * _NS + nanosec


def split_ns(ns: int, *, field: str = "stamp_ns") -> tuple[int, int]:
    """(sec, nanosec) of int ns, with ``sec`` in int32 range and 0 <= nanosec < 1e9."""
    sec, nanosec = divmod(int(ns), _NS)
    if not -(2**31) <= sec < 2**31:
        raise ValidationError(field, ns, "a time whose seconds fit in int32 (1901..2038)")
    return sec, nanosec


def time_msg(ns: int, cls: Any = None, *, field: str = "stamp_ns") -> Any:
    """A Time message for int ns: ``builtin_interfaces.msg.Time`` by default, or ``cls``."""
    sec, nanosec = split_ns(ns, field=field)
    if cls is None:
        from builtin_interfaces.msg import Time  # no rclpy import
        return Time(sec=sec, nanosec=nanosec)
    return cls(sec=sec, nanosec=nanosec)
