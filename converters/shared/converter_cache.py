"""The converter caches behind the one-call APIs (:func:`converters.slices.converter.to_laserscan`,
:func:`converters.pointcloud2.converter.to_pointcloud2`).

A converter (with its per-pixel tables) is kept per LidarInfo version and options. It is found
by its *content key*: :func:`lidarscan.geometry.info_key` (stamp and a digest of the geometry)
and the options, so a new info object with the same content (an info decoded again from a
recording) finds it too. Hashing the geometry on every call would cost more than the lookup
saves, so each info object's content key is remembered (:attr:`ConverterCache.keys`, by
``id`` while the cache holds the object, with its ``header.stamp``: the version key of a
LidarInfo; an info changed in place must get a new stamp, as the proposal requires of every
new version). The callers read that table inline before asking :meth:`ConverterCache.key`.

A converter is checked out while it converts (:attr:`ConverterCache.idle` ``pop``): a
concurrent call with the same key builds its own, so converters are never shared by threads.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Hashable
from typing import Any

from lidarscan.geometry import info_key

__all__ = ["ConverterCache"]


class ConverterCache:
    """Idle converters by content key, at most ``size`` of them (least recently used dropped).

    Attributes:
        keys: ``(id(info), options)`` -> ``(info, (sec, nanosec), content key)``: the content
            key of an info object seen with those options, valid while ``entry[0] is info`` and
            its stamp is unchanged.
        idle: content key -> converter not converting now (``pop`` under :attr:`lock` to
            check one out).
        lock: guards :attr:`idle`.
    """

    def __init__(self, size: int = 8) -> None:
        self.size = int(size)
        self.lock = threading.Lock()
        self.keys: dict[tuple[int, Hashable], tuple[Any, tuple[int, int], Hashable]] = {}
        self.idle: OrderedDict[Hashable, Any] = OrderedDict()

    def key(self, info: Any, options: Hashable) -> Hashable | None:
        """The content key of ``info`` with ``options`` (remembered for the object), or None
        when the info cannot be keyed (the converter's constructor then says what is wrong)."""
        try:
            key = (info_key(info), options)
            stamp = (int(info.header.stamp.sec), int(info.header.stamp.nanosec))
            hash(key)
        except (AttributeError, TypeError, ValueError):   # ValidationError included
            return None
        with self.lock:
            if len(self.keys) >= 4 * self.size:       # holds the info objects: keep it small
                self.keys.clear()
            self.keys[(id(info), options)] = (info, stamp, key)
        return key

    def give(self, key: Hashable, converter: Any) -> None:
        """Return a checked-out converter (the most recently used)."""
        with self.lock:
            self.idle[key] = converter
            self.idle.move_to_end(key)
            while len(self.idle) > self.size:
                self.idle.popitem(last=False)
