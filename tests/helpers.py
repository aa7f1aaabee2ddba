"""Small helpers shared by several test modules (imported as ``from helpers import ...``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from lidarscan.mcap import BadMessage, read_messages


def assert_document_current(problems: list[str]) -> None:
    """Fail on every difference :func:`converters.evidence.check` reports; then, when some
    block could be compared within a tolerance only (its third-party library versions differ
    from the document's: lines "skipped: ..."), skip visibly with those lines as the reason."""
    real = [p for p in problems if not p.startswith("skipped:")]
    assert real == [], "docs/proposal.md is stale; run `make evidence`:\n" + "\n".join(real)
    skipped = [p for p in problems if p.startswith("skipped:")]
    if skipped:
        pytest.skip("exact comparison not possible with these library versions:\n"
                    + "\n".join(skipped))


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
