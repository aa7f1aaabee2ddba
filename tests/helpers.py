"""Small helpers shared by several test modules (imported as ``from helpers import ...``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from lidarscan.mcap import BadMessage, read_messages


def messages_by_topic(path: Path) -> dict[str, list[Any]]:
    """Every message of an MCAP file grouped by topic, in file order; fails on a bad record."""
    out: dict[str, list[Any]] = {}
    for item in read_messages(path):
        assert not isinstance(item, BadMessage), item
        out.setdefault(item.topic, []).append(item)
    return out


class Clock:
    """A settable clock for code that takes a ``clock()`` callable: returns ``now`` (int ns)."""

    def __init__(self) -> None:
        self.now = 0

    def __call__(self) -> int:
        return self.now
