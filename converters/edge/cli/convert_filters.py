"""``lidarscan convert``: what is read (``--start``/``--end`` time range, ``--topics``) and how
output topics are named (``--rename-topic OLD=NEW``).

Times (``--start``, ``--end``; compared with each message's log time, the recording's receive
time, int64 ns; an Ouster .pcap/.osf: each scan's stamp):

* ``1713492677.46``: seconds since the epoch (what ``lidarscan info`` prints);
* ``1713492677464078412ns``, or a bare integer of 16 digits or more: nanoseconds since the epoch;
* ``2024-04-19T02:11:17.46Z``: an ISO 8601 date and time (UTC unless it has an offset);
* ``+2.5``: seconds after the first message read.

``--start`` is inclusive, ``--end`` exclusive. Messages logged before ``--start`` are skipped
except the latched ones the later messages need (``LidarInfo`` and ``/tf_static``), which are
kept with their own times; every message from ``--end`` on is skipped.
"""

from __future__ import annotations

import datetime
import decimal
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

_INFO_TYPE = "lidarscan_msgs/msg/LidarInfo"
_TF_TYPE = "tf2_msgs/msg/TFMessage"


@dataclass(frozen=True)
class TimeBound:
    """One ``--start``/``--end`` value: ``ns`` since the epoch, or with ``relative`` ns after
    the first message read; ``text`` as given."""

    text: str
    ns: int
    relative: bool = False


def parse_time(text: str) -> TimeBound:
    """A ``--start``/``--end`` value (see the module docstring) -> :class:`TimeBound`.

    Raises:
        ValueError: naming the value and the accepted forms.
    """
    value = text.strip()
    accepted = ("seconds since the epoch (1713492677.46), nanoseconds (1713492677464078412ns), "
                "an ISO date (2024-04-19T02:11:17Z) or +SECONDS after the first message")
    try:
        if value.startswith("+"):
            return TimeBound(text, _seconds_ns(value[1:]), relative=True)
        if value.endswith("ns") and value[:-2].isdigit():
            return TimeBound(text, int(value[:-2]))
        if value.isdigit() and len(value) >= 16:
            return TimeBound(text, int(value))
        try:
            return TimeBound(text, _seconds_ns(value))
        except ValueError:
            pass
        iso = value[:-1] + "+00:00" if value.endswith(("Z", "z")) else value
        when = datetime.datetime.fromisoformat(iso)
    except ValueError:
        raise ValueError(f"{text!r}: expected {accepted}") from None
    if when.tzinfo is None:
        when = when.replace(tzinfo=datetime.timezone.utc)
    delta = when - datetime.datetime(1970, 1, 1, tzinfo=datetime.timezone.utc)
    return TimeBound(text, (delta.days * 86400 + delta.seconds) * 10**9
                     + delta.microseconds * 1000)


def _seconds_ns(text: str) -> int:
    try:
        seconds = decimal.Decimal(text)
    except decimal.InvalidOperation:
        raise ValueError(text) from None
    if not seconds.is_finite() or seconds < 0:
        raise ValueError(text)
    return int(seconds * 10**9)


@dataclass
class Selection:
    """What ``convert`` reads of IN: a time range and a topic list (each optional).

    :meth:`keep` is called on every message in reading order (the first one resolves the
    relative bounds)."""

    start: TimeBound | None = None
    end: TimeBound | None = None
    topics: tuple[str, ...] = ()
    _bounds: tuple[int, int] | None = field(default=None, repr=False)

    @property
    def active(self) -> bool:
        return self.start is not None or self.end is not None or bool(self.topics)

    def check(self) -> None:
        """ConfigError for an empty range (when both bounds are of one kind)."""
        from lidarscan.errors import ConfigError

        if (self.start is not None and self.end is not None
                and self.start.relative == self.end.relative and self.end.ns <= self.start.ns):
            raise ConfigError("--end", self.end.text, f"a time after --start {self.start.text}")

    def select_topics(self, topics: dict[str, str]) -> dict[str, str]:
        """The topics of IN (topic -> type) that are read; ConfigError for a ``--topics`` name
        IN does not have."""
        from lidarscan.errors import ConfigError

        if not self.topics:
            return topics
        missing = [t for t in self.topics if t not in topics]
        if missing:
            raise ConfigError("--topics", missing[0], "topics of IN (it has "
                              f"{', '.join(sorted(topics)) or 'none'})")
        return {t: k for t, k in topics.items() if t in self.topics}

    def keep(self, item: Any) -> bool:
        """Whether the message ``item`` (a McapMessage: topic, msgtype, log_time_ns) is read."""
        if self.topics and item.topic not in self.topics:
            return False
        return self.keep_time(item.log_time_ns, latched=item.msgtype == _INFO_TYPE or (
            item.msgtype == _TF_TYPE and item.topic.endswith("_static")))

    def keep_time(self, ns: int, *, latched: bool = False) -> bool:
        """Whether a message of time ``ns`` is in the range (``latched``: also before it)."""
        if self.start is None and self.end is None:
            return True
        if self._bounds is None:
            def bound(value: TimeBound | None, default: int) -> int:
                if value is None:
                    return default
                return ns + value.ns if value.relative else value.ns
            self._bounds = (bound(self.start, -(1 << 63)), bound(self.end, 1 << 63))
        start, end = self._bounds
        return ns < end and (ns >= start or latched)


def parse_renames(values: Iterable[str]) -> dict[str, str]:
    """``--rename-topic OLD=NEW`` values -> {OLD: NEW} (ConfigError on a bad one)."""
    from lidarscan.errors import ConfigError

    out: dict[str, str] = {}
    for text in values:
        old, sep, new = text.partition("=")
        old, new = old.strip(), new.strip()
        if not sep or not old or not new or any(c.isspace() for c in old + new):
            raise ConfigError("--rename-topic", text, "OLD=NEW, two topic names without spaces")
        if old in out:
            raise ConfigError("--rename-topic", text, f"each topic renamed once ({old} is "
                              f"already renamed to {out[old]})")
        out[old] = new
    return out


def check_renames(renames: dict[str, str], written: Iterable[str]) -> None:
    """ConfigError for an OLD topic that is not written, or two topics ending up on one name.

    ``written``: the topics of the output before renaming (copied input topics and new ones).
    """
    from lidarscan.errors import ConfigError

    names = set(written)
    for old in renames:
        if old not in names:
            raise ConfigError("--rename-topic", old, "a topic of the output (it has "
                              f"{', '.join(sorted(names)) or 'none'})")
    final: dict[str, str] = {}
    for topic in sorted(names):
        new = renames.get(topic, topic)
        if new in final:
            raise ConfigError("--rename-topic", f"{topic}={new}" if topic in renames else
                              f"{final[new]}={new}", f"a name no other output topic has ({new} "
                              f"is also where {final[new] if topic in renames else topic} "
                              "goes)")
        final[new] = topic


class RenamingWriter:
    """A writer whose :meth:`write` puts each topic under its new name (``renames``); every
    other attribute is the wrapped writer's."""

    def __init__(self, writer: Any, renames: dict[str, str]) -> None:
        self._writer = writer
        self._renames = dict(renames)

    def write(self, topic: str, msg: Any, **options: Any) -> None:
        self._writer.write(self._renames.get(topic, topic), msg, **options)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._writer, name)


def selection_of(args: Any) -> Selection:
    """The :class:`Selection` of the command line (``args.start``, ``args.end``,
    ``args.topics``: lists of comma-separated names)."""
    topics = tuple(dict.fromkeys(t.strip() for value in getattr(args, "topics", None) or ()
                                 for t in value.split(",") if t.strip()))
    selection = Selection(getattr(args, "start", None), getattr(args, "end", None), topics)
    selection.check()
    return selection


