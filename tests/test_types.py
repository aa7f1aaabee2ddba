"""lidarscan.types: the dataclasses agree with msgs/msg/*.msg and with rclpy.

Three sources are compared: the ``.msg`` files read with a tiny parser written here (not
lidarscan.msgdef), the frozen dataclasses of lidarscan.types, and rclpy's
``get_fields_and_field_types()``: same names, same order, compatible types, same constants.
"""

from __future__ import annotations

import dataclasses
import importlib
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import lidarscan
from lidarscan import datatypes, types
from lidarscan.errors import SchemaError
from lidarscan.types import message_class, msgtype_of

MSG_DIR = Path(__file__).resolve().parent.parent / "msgs" / "msg"
OURS = {"LidarChannel": types.LidarChannel, "LidarScan": types.LidarScan,
        "LidarInfo": types.LidarInfo}

# .msg primitive -> rclpy (IDL) name, and -> numpy dtype of array fields
_IDL = {"float32": "float", "float64": "double", "bool": "boolean", "byte": "octet",
        "char": "uint8"}
_NP = {"float32": np.float32, "float64": np.float64, "int8": np.int8, "uint8": np.uint8,
       "int16": np.int16, "uint16": np.uint16, "int32": np.int32, "uint32": np.uint32,
       "int64": np.int64, "uint64": np.uint64, "bool": np.bool_}


def read_msg(path: Path) -> tuple[list[tuple[str, str]], dict[str, int]]:
    """Minimal .msg reader: ([(type, name)], {CONSTANT: value}) (integer constants only)."""
    fields, constants = [], {}
    for line in path.read_text().splitlines():
        line = line.split("#")[0].strip()
        if not line:
            continue
        ftype, rest = line.split(None, 1)
        if "=" in rest:
            name, value = (p.strip() for p in rest.split("=", 1))
            constants[name] = int(value)
        else:
            fields.append((ftype, rest.split()[0]))
    return fields, constants


def idl_name(msg_type: str, package: str) -> str:
    """The rclpy type string of a .msg field type (``float64[]`` -> ``sequence<double>``)."""
    match = re.fullmatch(r"([\w/]+)(<=\d+)?(?:\[(<=)?(\d*)\])?", msg_type)
    assert match, msg_type
    base, strbound, bounded, size = match.groups()
    if "/" in base:
        base = base.replace("/msg/", "/")
    elif base == "Header":
        base = "std_msgs/Header"
    elif base[0].isupper():
        base = f"{package}/{base}"
    else:
        base = _IDL.get(base, base) + (f"<{strbound[2:]}>" if strbound else "")
    if size is None and "[" not in msg_type:
        return base
    if bounded:
        return f"sequence<{base}, {size}>"
    return f"sequence<{base}>" if not size else f"{base}[{size}]"


# The dataclass default differs from the .msg/rclpy default (0, an invalid count). The .msg
# should declare ``uint32 count 1``; when it does, read_msg sees the default and this entry must go.
KNOWN_DEFAULT_DIFFERENCES = {("LidarChannel", "count"): 1}


def test_known_default_differences_are_still_real() -> None:
    for (name, fname), value in KNOWN_DEFAULT_DIFFERENCES.items():
        assert getattr(OURS[name](), fname) == value
        assert msg_defaults(MSG_DIR / f"{name}.msg").get(fname) is None  # .msg declares none


def msg_defaults(path: Path) -> dict[str, str]:
    """Field name -> default value text, for fields that declare one."""
    out = {}
    for line in path.read_text().splitlines():
        parts = line.split("#")[0].split()
        if len(parts) >= 3 and "=" not in line.split("#")[0]:
            out[parts[1]] = " ".join(parts[2:])
    return out


@pytest.mark.parametrize("name", sorted(OURS))
def test_dataclass_fields_follow_the_msg_file(name: str) -> None:
    fields, _ = read_msg(MSG_DIR / f"{name}.msg")
    cls = OURS[name]
    assert [f.name for f in dataclasses.fields(cls)] == [n for _, n in fields]
    assert cls.__msgtype__ == f"lidarscan_msgs/msg/{name}"
    default = cls()
    for ftype, fname in fields:
        value = getattr(default, fname)
        base = ftype.split("[")[0]
        if "[" in ftype:
            assert isinstance(value, (np.ndarray, tuple)), fname
            if base in _NP:
                assert isinstance(value, np.ndarray) and value.dtype == _NP[base], fname
                assert not value.flags.writeable, fname  # defaults are shared: read-only
                size = ftype.split("[")[1].rstrip("]")
                assert value.size == (int(size) if size else 0), fname
        elif base == "string":
            assert value == "", fname
        elif base == "bool":
            assert value is False, fname
        elif base in _NP:
            declared = msg_defaults(MSG_DIR / f"{name}.msg").get(fname)
            expected = KNOWN_DEFAULT_DIFFERENCES.get((name, fname), 0) if declared is None \
                else float(declared)
            assert value == expected, fname
            assert isinstance(value, float if "float" in base else int), fname
        else:
            assert msgtype_of(value).endswith("/" + base.split("/")[-1]), fname


@pytest.mark.parametrize("name", sorted(OURS))
def test_dataclasses_are_frozen_and_slotted(name: str) -> None:
    cls = OURS[name]
    obj = cls()
    assert hasattr(cls, "__slots__") and not hasattr(obj, "__dict__")
    with pytest.raises(dataclasses.FrozenInstanceError):
        setattr(obj, dataclasses.fields(cls)[0].name, None)


@pytest.mark.ros
@pytest.mark.parametrize("name", sorted(OURS))
def test_rclpy_fields_match(name: str) -> None:
    module = pytest.importorskip("lidarscan_msgs.msg")
    fields, _ = read_msg(MSG_DIR / f"{name}.msg")
    rclpy_fields = getattr(module, name).get_fields_and_field_types()
    assert list(rclpy_fields) == [n for _, n in fields]
    assert list(rclpy_fields.values()) == [idl_name(t, "lidarscan_msgs") for t, _ in fields]
    assert msgtype_of(getattr(module, name)()) == f"lidarscan_msgs/msg/{name}"


def test_channel_constants_agree_everywhere() -> None:
    _, constants = read_msg(MSG_DIR / "LidarChannel.msg")
    assert constants == {n: getattr(datatypes, n) for n in datatypes.DATATYPE_NAMES.values()}
    assert constants == {n: getattr(types.LidarChannel, n) for n in constants}
    assert constants == {n: i for i, n in datatypes.DATATYPE_NAMES.items()}
    assert "INT8" not in [f.name for f in dataclasses.fields(types.LidarChannel)]


@pytest.mark.ros
def test_channel_constants_equal_rclpy_and_pointfield() -> None:
    lidarscan_msgs = pytest.importorskip("lidarscan_msgs.msg")
    from sensor_msgs.msg import PointField
    _, constants = read_msg(MSG_DIR / "LidarChannel.msg")
    for name, value in constants.items():
        assert getattr(lidarscan_msgs.LidarChannel, name) == value == getattr(PointField, name)


@pytest.mark.parametrize(("cls", "msgtype"), [(types.Time, "builtin_interfaces/msg/Time"),
                                              (types.Header, "std_msgs/msg/Header")])
def test_time_and_header_match_their_definitions(cls: Any, msgtype: str) -> None:
    from lidarscan.msgdef import get_msgdef
    assert [f.name for f in dataclasses.fields(cls)] == [f.name for f in
                                                         get_msgdef(msgtype).fields]
    assert cls.__msgtype__ == msgtype
    assert message_class(msgtype) is cls


def _share_msg_files() -> list[tuple[str, Path]]:
    import sys
    share = Path(sys.prefix) / "share"
    found = []
    for path in sorted(share.glob("*/msg/*.msg")):
        found.append((f"{path.parent.parent.name}/msg/{path.stem}", path))
    return found


@pytest.mark.ros
def test_every_installed_msg_parses_like_rclpy() -> None:
    """lidarscan.msgdef and message_class agree with rclpy on every installed message type."""
    from lidarscan.msgdef import get_msgdef
    checked = 0
    for msgtype, path in _share_msg_files():
        pkg, _, name = msgtype.split("/")
        try:
            rclpy_cls = getattr(importlib.import_module(f"{pkg}.msg"), name)
        except (ImportError, AttributeError):
            continue
        expected = rclpy_cls.get_fields_and_field_types()
        msgdef = get_msgdef(msgtype)
        assert [f.name for f in msgdef.fields] == list(expected), msgtype
        fields, _ = read_msg(path)
        assert [idl_name(t, pkg) for t, _ in fields] == list(expected.values()), msgtype
        cls = message_class(msgtype)
        assert [f.name for f in dataclasses.fields(cls)] == list(expected), msgtype
        assert msgtype_of(rclpy_cls()) == msgtype == msgtype_of(cls())
        checked += 1
    assert checked > 100  # std, geometry, sensor, nav, visualization, ... msgs


def test_generated_classes_are_cached_frozen_dataclasses() -> None:
    cls = message_class("sensor_msgs/PointField")
    assert cls is message_class("sensor_msgs/msg/PointField")
    assert cls.__msgtype__ == "sensor_msgs/msg/PointField"
    point = cls(name="x", offset=0, datatype=7, count=1)
    with pytest.raises(dataclasses.FrozenInstanceError):
        point.name = "y"  # type: ignore[attr-defined]
    assert message_class("lidarscan_msgs/LidarScan") is types.LidarScan


def test_msgtype_of_rejects_other_objects() -> None:
    with pytest.raises(SchemaError, match="msg='object'"):
        msgtype_of(object())


def test_decode_returns_these_classes() -> None:
    info = lidarscan.make_info(stamp_ns=1, frame_id="f", vertical_angles=[0.0],
                               horizontal_angles=[0.0, 1.0], as_dataclass=True)
    scan = lidarscan.make_scan(info, {"range": np.zeros((1, 2), np.float32)}, 2, as_dataclass=True)
    decoded = lidarscan.decode_scan(lidarscan.encode(scan))
    assert type(decoded) is types.LidarScan
    assert type(decoded.header) is types.Header and type(decoded.header.stamp) is types.Time
    assert all(type(c) is types.LidarChannel for c in decoded.channels)
    assert type(lidarscan.decode_info(lidarscan.encode(info))) is types.LidarInfo
