"""lidarscan.msgdef: .msg parsing, definition lookup and MCAP ``ros2msg`` schema text."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import lidarscan
from lidarscan import msgdef
from lidarscan.errors import DecodeError, SchemaError
from lidarscan.msgdef import (
    FieldDef,
    find_msg_text,
    get_msgdef,
    normalize_type,
    parse_msg,
    schema_text,
    split_schema_text,
)

MSG_DIR = Path(__file__).resolve().parent.parent / "msgs" / "msg"

TRICKY = """\
# leading comment
Header header            # bare Header means std_msgs/Header
int32 plain
int32 with_default 5     # default values are ignored
string greeting "hi # not a comment?"
string<=10 bounded_string
float64[9] fixed
float32[] seq
int16[<=4] bounded_seq
geometry_msgs/Point point
geometry_msgs/msg/Vector3[] vectors
Other local
Other[3] locals
uint8 CONSTANT_A = 7
string CONSTANT_B="x"
int32 CONSTANT_C=-3

bool flag
"""


def test_parse_tricky_definition() -> None:
    parsed = parse_msg(TRICKY, "my_pkg/Thing")
    assert parsed.name == "my_pkg/msg/Thing"
    assert parsed.fields == (
        FieldDef("header", "std_msgs/msg/Header"),
        FieldDef("plain", "int32"),
        FieldDef("with_default", "int32"),
        FieldDef("greeting", "string"),
        FieldDef("bounded_string", "string"),
        FieldDef("fixed", "float64", 9),
        FieldDef("seq", "float32", -1),
        FieldDef("bounded_seq", "int16", -(4 + 2)),
        FieldDef("point", "geometry_msgs/msg/Point"),
        FieldDef("vectors", "geometry_msgs/msg/Vector3", -1),
        FieldDef("local", "my_pkg/msg/Other"),
        FieldDef("locals", "my_pkg/msg/Other", 3),
        FieldDef("flag", "bool"),
    )
    assert [c[:2] for c in parsed.constants] == [("uint8", "CONSTANT_A"), ("string", "CONSTANT_B"),
                                                ("int32", "CONSTANT_C")]
    assert parsed.constants[0][2] == "7" and parsed.constants[2][2] == "-3"
    assert parsed.fields[0].is_primitive is False and parsed.fields[1].is_primitive is True


@pytest.mark.parametrize("line", ["int32", "int32 1bad", "int32[x] bad", "= 5"])
def test_parse_rejects_garbage_with_line_number(line: str) -> None:
    with pytest.raises(SchemaError) as err:
        parse_msg("int32 ok\n" + line + "\n", "p/msg/T")
    assert "p/msg/T line 2" in str(err.value) and repr(line) in str(err.value)


@pytest.mark.parametrize(("name", "package", "expected"), [
    ("float64", "", "float64"), ("string", "x", "string"),
    ("std_msgs/Header", "", "std_msgs/msg/Header"),
    ("std_msgs/msg/Header", "", "std_msgs/msg/Header"),
    ("Header", "sensor_msgs", "std_msgs/msg/Header"),
    ("Header", "std_msgs", "std_msgs/msg/Header"),
    ("Point", "geometry_msgs", "geometry_msgs/msg/Point"),
])
def test_normalize_type(name: str, package: str, expected: str) -> None:
    assert normalize_type(name, package) == expected


@pytest.mark.parametrize("name", ["Point", "a/b/c", "a/srv/B", "a/msg/B/c"])
def test_normalize_type_rejects(name: str) -> None:
    with pytest.raises(SchemaError) as err:
        normalize_type(name)
    assert repr(name) in str(err.value)


@pytest.mark.parametrize("name", ["LidarScan", "LidarInfo", "LidarChannel"])
def test_find_msg_text_of_our_messages_is_the_source_file(name: str) -> None:
    assert find_msg_text(f"lidarscan_msgs/msg/{name}") == (MSG_DIR / f"{name}.msg").read_text()


def test_find_msg_text_unknown_type() -> None:
    with pytest.raises(SchemaError) as err:
        find_msg_text("no_such_pkg/msg/Nothing")
    assert "no_such_pkg/msg/Nothing" in str(err.value) and "share/no_such_pkg/msg" in str(err.value)


def test_get_msgdef_is_cached_and_normalised() -> None:
    assert get_msgdef("sensor_msgs/PointField") == get_msgdef("sensor_msgs/msg/PointField")
    assert get_msgdef("sensor_msgs/msg/PointField") is get_msgdef("sensor_msgs/msg/PointField")
    names = [f.name for f in get_msgdef("sensor_msgs/msg/PointField").fields]
    assert names == ["name", "offset", "datatype", "count"]


def test_schema_text_lists_every_dependency_once() -> None:
    text = schema_text("lidarscan_msgs/msg/LidarScan")
    assert text.startswith(find_msg_text("lidarscan_msgs/msg/LidarScan").rstrip("\n") + "\n")
    separator = "=" * 80
    sections = text.split(separator + "\n")
    assert len(sections) == 4
    headers = [s.splitlines()[0] for s in sections[1:]]
    assert sorted(headers) == ["MSG: builtin_interfaces/Time", "MSG: lidarscan_msgs/LidarChannel",
                               "MSG: std_msgs/Header"]
    # a dependency is listed after the type that first uses it (rosbag2's order)
    assert headers.index("MSG: std_msgs/Header") < headers.index("MSG: builtin_interfaces/Time")
    assert text.endswith("\n") and not text.endswith("\n\n")


@pytest.mark.parametrize("msgtype", ["lidarscan_msgs/msg/LidarScan", "lidarscan_msgs/msg/LidarInfo",
                                     "sensor_msgs/msg/PointCloud2", "nav_msgs/msg/Odometry",
                                     "std_msgs/msg/Empty"])
def test_split_schema_text_inverts_schema_text(msgtype: str) -> None:
    parts = split_schema_text(msgtype, schema_text(msgtype))
    assert parts[msgtype].rstrip("\n") == find_msg_text(msgtype).rstrip("\n")
    for name, text in parts.items():
        assert text.rstrip("\n") == find_msg_text(name).rstrip("\n"), name
        assert parse_msg(text, name) == get_msgdef(name)


def test_split_schema_text_rejects_missing_msg_line() -> None:
    bad = "int32 a\n" + "=" * 80 + "\nint32 b\n"
    with pytest.raises(SchemaError, match="schema='int32 b'"):
        split_schema_text("p/msg/T", bad)


@pytest.mark.parametrize("msgtype", ["lidarscan_msgs/msg/LidarScan", "lidarscan_msgs/msg/LidarInfo",
                                     "nav_msgs/msg/Odometry"])
def test_independent_parsers_read_our_schema_text(msgtype: str) -> None:
    typesys = pytest.importorskip("rosbags.typesys")
    found = typesys.get_types_from_msg(schema_text(msgtype), msgtype)
    assert msgtype in found
    ours = [f.name for f in get_msgdef(msgtype).fields]
    assert [f[0] for f in found[msgtype][1]] == ours


def test_register_msg_text_makes_a_new_type_usable(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(msgdef, "_registered", {})
    name = "test_pkg/msg/Sample"
    msgdef.register_msg_text(name, "uint16 a\nfloat64[] b\nstring c\n")
    cls = lidarscan.types.message_class(name)
    value = cls(a=7, b=np.array([1.5]), c="z")
    payload = lidarscan.encode(value)
    assert payload.hex() == ("00010000"            # encapsulation
                             "0700" "0000"          # 0 a = 7, padding to 4
                             "01000000"             # 4 b count = 1 (8 is 8-aligned)
                             "000000000000f83f"     # 8 b[0] = 1.5
                             "02000000" "7a00")     # 16 c = "z"
    back = lidarscan.decode(payload, name)
    assert back.a == 7 and back.b.tolist() == [1.5] and back.c == "z"
    # registering a changed definition takes effect everywhere (no stale cached codecs)
    msgdef.register_msg_text(name, "uint16 a\nuint8 extra\nfloat64[] b\nstring c\n")
    cls2 = lidarscan.types.message_class(name)
    assert cls2 is not cls
    assert [f.name for f in get_msgdef(name).fields] == ["a", "extra", "b", "c"]
    payload2 = lidarscan.encode(cls2(a=7, extra=1, b=np.array([1.5]), c="z"))
    assert payload2 != payload and lidarscan.decode(payload2, name).extra == 1
    # the same text again keeps the caches
    msgdef.register_msg_text(name, "uint16 a\nuint8 extra\nfloat64[] b\nstring c\n")
    assert lidarscan.types.message_class(name) is cls2


def test_bounded_sequences_decode_up_to_their_bound(monkeypatch: pytest.MonkeyPatch) -> None:
    """``T[<=N]``: a primitive array and a list of strings with N elements decode, N + 1 is a
    DecodeError naming the field and the bound (not an allocation of the declared count)."""
    monkeypatch.setattr(msgdef, "_registered", {})
    name = "test_pkg/msg/Bounded"
    msgdef.register_msg_text(name, "int32[<=2] a\nstring[<=1] b\n")
    ok = bytes.fromhex("00010000" "02000000" "0100000002000000" "01000000" "020000007a00")
    back = lidarscan.decode(ok, name)
    assert back.a.tolist() == [1, 2] and list(back.b) == ["z"]
    too_many_a = bytes.fromhex("00010000" "03000000" "010000000200000003000000" "00000000")
    with pytest.raises(DecodeError, match=r"=3: expected at most 2 elements \(bounded"):
        lidarscan.decode(too_many_a, name)
    too_many_b = bytes.fromhex("00010000" "00000000" "02000000" "020000007a00" "0000"
                               "020000007a00")
    with pytest.raises(DecodeError, match=r"=2: expected at most 1 elements \(bounded"):
        lidarscan.decode(too_many_b, name)


def test_registering_a_new_type_keeps_other_generated_classes(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(msgdef, "_registered", {})
    laser = lidarscan.types.message_class("sensor_msgs/msg/LaserScan")
    msgdef.register_msg_text("test_pkg/msg/Other", "int8 x\n")
    assert lidarscan.types.message_class("sensor_msgs/msg/LaserScan") is laser
    assert lidarscan.decode(b"\x00\x01\x00\x00\x05", "test_pkg/msg/Other").x == 5
