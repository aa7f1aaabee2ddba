"""ROS 2 ``.msg`` definitions: find them, parse them, and build MCAP ``ros2msg`` schema text.

``msgs/msg/*.msg`` is the single source of truth for lidarscan_msgs; sensor_msgs and friends come
from the ROS 2 wheels' ``share/<pkg>/msg`` folders. Definitions are searched, in order, in every
prefix of ``AMENT_PREFIX_PATH``, in ``sys.prefix`` and, for lidarscan_msgs, first in the source tree
(``msgs/msg`` next to this package) so that a checkout works before the build, then in the copy
an installed package carries (``lidarscan/_msgs``, made by setup.py) so that a plain
``pip install`` reads and writes recordings without the built interface package.
"""

from __future__ import annotations

import os
import re
import sys
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

from lidarscan.errors import SchemaError

__all__ = [
    "PRIMITIVE_TYPES",
    "FieldDef",
    "MsgDef",
    "normalize_type",
    "parse_msg",
    "find_msg_text",
    "get_msgdef",
    "schema_text",
    "split_schema_text",
    "register_msg_text",
    "on_definitions_changed",
]

# ROS 2 primitive type -> struct/numpy code (little-endian) ; char and byte are 1-byte unsigned.
PRIMITIVE_TYPES: dict[str, str] = {
    "bool": "?", "byte": "B", "char": "B", "int8": "b", "uint8": "B",
    "int16": "h", "uint16": "H", "int32": "i", "uint32": "I",
    "int64": "q", "uint64": "Q", "float32": "f", "float64": "d",
    "string": "", "wstring": "",
}

_SOURCE_MSGS = Path(__file__).resolve().parent.parent / "msgs"
_SHIPPED_MSGS = Path(__file__).resolve().parent / "_msgs"   # msgs/msg copied by setup.py
_registered: dict[str, str] = {}


@dataclass(frozen=True, slots=True)
class FieldDef:
    """One field of a message.

    Attributes:
        name: field name.
        type: a primitive name (``"float32"``, ``"string"``) or a full ``pkg/msg/Name``.
        array: ``None`` for a scalar, ``-1`` for an unbounded sequence, ``N > 0`` for a fixed
            array of N elements, ``-(N + 2)`` for a sequence bounded by N (``T[<=N]``).
    """

    name: str
    type: str
    array: int | None = None

    @property
    def is_primitive(self) -> bool:
        return self.type in PRIMITIVE_TYPES


@dataclass(frozen=True, slots=True)
class MsgDef:
    """A parsed message: full type name, fields in order, constants (name -> (type, value))."""

    name: str
    fields: tuple[FieldDef, ...]
    constants: tuple[tuple[str, str, str], ...]


def normalize_type(name: str, package: str = "") -> str:
    """``pkg/Name``, ``pkg/msg/Name`` or bare ``Name`` (resolved in ``package``) -> full name."""
    if name in PRIMITIVE_TYPES:
        return name
    parts = name.split("/")
    if len(parts) == 1:
        if name == "Header" and package != "std_msgs":  # ROS 1 habit, still seen in .msg files
            return "std_msgs/msg/Header"
        if not package:
            raise SchemaError("type", name, "a type with its package, like 'pkg/msg/Name'")
        return f"{package}/msg/{name}"
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    if len(parts) == 3 and parts[1] == "msg":
        return name
    raise SchemaError("type", name, "'pkg/msg/Name' or 'pkg/Name'")


_FIELD_RE = re.compile(
    r"^([A-Za-z][\w/]*)(<=\d+)?(\[(<=)?(\d*)\])?\s+([A-Za-z]\w*)(\s*=\s*.+|\s+.*)?$")


def parse_msg(text: str, name: str) -> MsgDef:
    """Parse ``.msg`` text of type ``name`` (``pkg/msg/Name``) into a :class:`MsgDef`.

    Comments, blank lines and default values are ignored; constants are kept apart.

    Raises:
        SchemaError: a line is not a field or constant definition.
    """
    full = normalize_type(name)
    package = full.split("/")[0]
    fields: list[FieldDef] = []
    constants: list[tuple[str, str, str]] = []
    for lineno, raw in enumerate(text.splitlines(), 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        match = _FIELD_RE.match(line)
        if match is None:
            raise SchemaError(f"{full} line {lineno}", raw,
                              "'<type> <name>' or '<type> <NAME>=<value>'")
        ftype, _strbound, arr, bounded, size, fname, rest = match.groups()
        if rest is not None and rest.lstrip().startswith("="):
            constants.append((ftype, fname, rest.split("=", 1)[1].strip()))
            continue
        array: int | None = None
        if arr is not None:
            if not size:
                array = -1
            elif bounded:
                array = -(int(size) + 2)
            else:
                array = int(size)
        fields.append(FieldDef(fname, normalize_type(ftype, package), array))
    return MsgDef(full, tuple(fields), tuple(constants))


def _prefixes() -> list[Path]:
    found = [Path(p) for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    found.append(Path(sys.prefix))
    return found


def register_msg_text(name: str, text: str) -> None:
    """Make a definition known without a ``share/`` folder (e.g. one read from an MCAP schema).

    A new name only adds a definition. A different text for a name already defined (registered
    before, or found under ``share/``) replaces it and drops every cached parse, schema, codec
    and generated class built from the old one (see :func:`on_definitions_changed`). The same
    text again is a no-op.
    """
    full = normalize_type(name)
    if _registered.get(full) == text:
        return
    try:
        replaces = find_msg_text(full) != text
    except SchemaError:
        replaces = False
    _registered[full] = text
    if replaces:
        get_msgdef.cache_clear()
        schema_text.cache_clear()
        for hook in _hooks:
            hook()


_hooks: list[Callable[[], None]] = []


def on_definitions_changed(hook: Callable[[], None]) -> None:
    """Call ``hook`` whenever :func:`register_msg_text` changes a definition (cache owners)."""
    _hooks.append(hook)


def find_msg_text(name: str) -> str:
    """The ``.msg`` text of ``name`` (``pkg/msg/Name``).

    Raises:
        SchemaError: no definition found in any prefix.
    """
    full = normalize_type(name)
    if full in _registered:
        return _registered[full]
    package, _, short = full.split("/")
    candidates = [p / "share" / package / "msg" / f"{short}.msg" for p in _prefixes()]
    if package == "lidarscan_msgs":
        candidates[:0] = [_SOURCE_MSGS / "msg" / f"{short}.msg", _SHIPPED_MSGS / f"{short}.msg"]
    for path in candidates:
        if path.is_file():
            return path.read_text(encoding="utf-8")
    raise SchemaError("type", full, "a message definition under <prefix>/share/"
                      f"{package}/msg/ (searched {', '.join(str(p) for p in _prefixes())})",
                      hint="run `make install` (ROS 2 wheels + lidarscan_msgs)"
                      if package in ("lidarscan_msgs", "std_msgs", "sensor_msgs",
                                     "builtin_interfaces") else "")


@lru_cache(maxsize=None)
def get_msgdef(name: str) -> MsgDef:
    """Parsed definition of ``name`` (cached)."""
    full = normalize_type(name)
    return parse_msg(find_msg_text(full), full)


def _dependencies(name: str) -> list[str]:
    order: list[str] = []

    def visit(type_name: str) -> None:
        for field in get_msgdef(type_name).fields:
            if not field.is_primitive and field.type not in order:
                order.append(field.type)
                visit(field.type)

    visit(normalize_type(name))
    return order


@lru_cache(maxsize=None)
def schema_text(name: str) -> str:
    """MCAP ``ros2msg`` schema text: the type's ``.msg`` followed by every dependency.

    Each dependency is introduced by a line of 80 ``=`` and ``MSG: pkg/Name``, as rosbag2 writes it.
    """
    full = normalize_type(name)
    parts = [find_msg_text(full).rstrip("\n")]
    for dep in _dependencies(full):
        pkg, _, short = dep.split("/")
        parts.append("=" * 80 + f"\nMSG: {pkg}/{short}\n" + find_msg_text(dep).rstrip("\n"))
    return "\n".join(parts) + "\n"


def split_schema_text(name: str, text: str) -> dict[str, str]:
    """Inverse of :func:`schema_text`: ``{pkg/msg/Name: msg text}`` for the type and its deps."""
    out: dict[str, str] = {}
    current = normalize_type(name)
    lines: list[str] = []
    for line in text.splitlines():
        if line.startswith("=" * 10) and set(line.strip()) == {"="}:
            out[current] = "\n".join(lines) + "\n"
            lines = []
            current = ""
            continue
        if not current:
            if line.startswith("MSG:"):
                current = normalize_type(line[4:].strip())
                continue
            if not line.strip():
                continue
            raise SchemaError("schema", line, "'MSG: pkg/Name' after a separator line")
        lines.append(line)
    if current:
        out[current] = "\n".join(lines) + "\n"
    return out

