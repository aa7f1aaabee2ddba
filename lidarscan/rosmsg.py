"""Building rclpy messages of known-good values without the generated constructors' costs.

No rclpy import here: the message classes are passed in by the callers.
"""

from __future__ import annotations

import sys
from typing import Any

from lidarscan.errors import ConversionError

__all__ = ["bare_message"]

_SLOTS: dict[type, tuple[frozenset[str], bool]] = {}


def bare_message(cls: type, **fields: Any) -> Any:
    """An rclpy message of ``cls`` with exactly these field values, built without the generated
    constructor, which first builds a default for every field (for a PointCloud2 a Header, a
    Time and an empty array: ~6 us) and copies ``data`` given as an argument.

    The values must already have the field types (the converter's own, checked values:
    ``data`` an ``array.array('B')``, which the message then holds without a copy) and every
    field must be given; rosidl's generated classes keep field ``f`` in the slot ``_f``.
    ``tests/test_pointcloud2.py`` and ``tests/test_laserscan.py`` compare the results with
    normally built messages.
    """
    known = _SLOTS.get(cls)
    if known is None:
        # what the generated constructor would set: field checks only when the environment
        # asks for them (ROS_PYTHON_CHECK_FIELDS=1, read by the generated module)
        module = sys.modules[cls.__module__]
        known = (frozenset(cls.get_fields_and_field_types()),  # type: ignore[attr-defined]
                 getattr(module, "ros_python_check_fields", "") == "1")
        _SLOTS[cls] = known
    names, check = known
    if fields.keys() != names:
        raise ConversionError(f"{cls.__name__} fields", sorted(fields), sorted(names))
    msg = cls.__new__(cls)
    msg._check_fields = check
    for name, value in fields.items():
        setattr(msg, "_" + name, value)
    return msg
