"""C++ <-> Python interoperability of LidarScan through the generated lidarscan_msgs headers.

A small C++ program (tests/cpp/roundtrip.cpp) is built once per session against the
lidarscan_msgs installed in this environment (``make install`` builds it into the venv; a ROS
install provides it through AMENT_PREFIX_PATH) and serializes with rmw_fastrtps_cpp's
``rmw_serialize`` / ``rmw_deserialize``, the bytes a C++ node sends and receives:

* C++ ``rmw_serialize`` -> ``lidarscan.decode_scan``: every field equals what the program set
  (constants below, written independently in the C++ source), the scan validates and the
  channel views hold the values the program copied in;
* ``lidarscan.encode`` -> C++ ``rmw_deserialize``: every field the program prints equals the
  Python scan's;
* Python's bytes are C++'s without the up to 8 trailing zero bytes C++ appends;
* real scans (the Ouster frames of tests/data decoded by ``converters.ouster``, float32 metres
  and UINT32 millimetres, single and dual return, both byte orders), written by
  ``lidarscan.encode`` and by ``lidarscan.mcap.McapWriter`` (the message's bytes taken from the
  MCAP file), are read by C++ ``rmw_deserialize``: the header, every channel (name, datatype,
  count) and every pixel value the program reads in the message's byte order equal Python's
  views of the same scan.

With the PyPI wheels (no librmw_implementation, a Fast DDS CMake target naming a missing
tinyxml2), the program links librmw_fastrtps_cpp directly and runs with the wheels' library
folders on LD_LIBRARY_PATH (docs in tests/cpp/CMakeLists.txt).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import lidarscan as ls
from lidarscan.scan import data_view

pytestmark = pytest.mark.ros

SOURCE = Path(__file__).parent / "cpp"

# What roundtrip.cpp's make_scan() sets.
CPP_STAMP = (1700000000, 123456789)
CPP_FRAME = "os_lidar"
CPP_INFO_TIME = (1699999999, 5)
CPP_RANGE = np.array([[1.5, 2.25, 3.0], [0.5, 100.0, 7.125]], np.float32)
CPP_INTENSITY = np.array([[0, 1, 255], [256, 4096, 65535]], np.uint16)


def ros_env(prefix: Path) -> dict[str, str]:
    """Environment for cmake and for the program: the prefix on AMENT_PREFIX_PATH and
    CMAKE_PREFIX_PATH; its lib/ and the wheels' bundled libraries on LD_LIBRARY_PATH."""
    env = {k: v for k, v in os.environ.items() if k != "_ROS_WHEELS_BOOTSTRAP_COMPLETE"}
    for var in ("AMENT_PREFIX_PATH", "CMAKE_PREFIX_PATH"):
        env[var] = os.pathsep.join(p for p in (str(prefix), env.get(var, "")) if p)
    site = Path(sys.prefix) / "lib" / f"python{sys.version_info[0]}.{sys.version_info[1]}" \
        / "site-packages"
    libs = [str(prefix / "lib")] + sorted(str(p) for p in site.glob("ros_*.libs"))
    env["LD_LIBRARY_PATH"] = os.pathsep.join(libs + [env.get("LD_LIBRARY_PATH", "")]).rstrip(
        os.pathsep)
    return env


def missing_tools() -> list[str]:
    return [t for t in ("cmake", "ninja", "c++") if shutil.which(t) is None]


@pytest.fixture(scope="module")
def program(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, str]]:
    """The built tests/cpp program and the environment to run it in."""
    missing = missing_tools()
    if missing:
        pytest.skip(f"needs {', '.join(missing)} on PATH to build the C++ test program")
    prefix = Path(sys.prefix)
    if not (prefix / "share" / "lidarscan_msgs" / "cmake").is_dir():
        pytest.skip(f"lidarscan_msgs is not built into {prefix} (run make install)")
    build = tmp_path_factory.mktemp("cpp_build")
    env = ros_env(prefix)
    cmake_env = {k: v for k, v in env.items() if k != "LD_LIBRARY_PATH"}
    for step in (["cmake", "-S", str(SOURCE), "-B", str(build), "-G", "Ninja",
                  "-DCMAKE_BUILD_TYPE=Release", f"-DCMAKE_PREFIX_PATH={prefix}"],
                 ["cmake", "--build", str(build)]):
        done = subprocess.run(step, env=cmake_env, capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, f"{' '.join(step)} failed:\n{done.stdout}\n{done.stderr}"
    return build / "lidarscan_roundtrip", env


def run(program: tuple[Path, dict[str, str]], mode: str, path: Path) -> str:
    exe, env = program
    done = subprocess.run([str(exe), mode, str(path)], env=env, capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 0, f"{mode} failed: {done.stderr}"
    return done.stdout


def parse_fields(text: str) -> dict[str, Any]:
    """The program's ``key=value`` lines (``channel`` repeated)."""
    fields: dict[str, Any] = {"channel": []}
    for line in text.splitlines():
        key, _, value = line.partition("=")
        if key == "channel":
            fields["channel"].append(value)
        else:
            fields[key] = value
    return fields


def test_cpp_serialized_scan_decodes_in_python(program: Any, tmp_path: Path) -> None:
    path = tmp_path / "cpp.cdr"
    run(program, "encode", path)
    payload = path.read_bytes()
    scan = ls.decode_scan(payload)
    assert (scan.header.stamp.sec, scan.header.stamp.nanosec) == CPP_STAMP
    assert scan.header.frame_id == CPP_FRAME
    assert (scan.lidar_info_time.sec, scan.lidar_info_time.nanosec) == CPP_INFO_TIME
    assert (scan.height, scan.width, scan.is_bigendian, scan.is_destaggered) == (2, 3, False, True)
    assert list(scan.column_time_offsets) == [0, 33333, 66666]
    assert list(scan.column_azimuth_angles) == [3.0, 1.0, -1.0]
    assert [(c.name, c.offset, c.datatype, c.count) for c in scan.channels] == [
        ("range", 0, 7, 1), ("intensity", 24, 4, 1)]
    ls.validate(scan)
    np.testing.assert_array_equal(ls.channel(scan, "range"), CPP_RANGE)
    np.testing.assert_array_equal(ls.channel(scan, "intensity"), CPP_INTENSITY)
    # same bytes from Python, except C++'s trailing zeros (the C++ padding is not compared)
    again = ls.encode(scan)
    assert len(again) <= len(payload) <= len(again) + 8
    assert payload[len(again):] == bytes(len(payload) - len(again))


def test_python_encoded_scan_deserializes_in_cpp(program: Any, tmp_path: Path) -> None:
    info = ls.make_info(stamp_ns=1_600_000_000_000_000_042, frame_id="front_lidar",
                        vertical_angles=np.radians([10.0, -10.0]),
                        horizontal_angles=[2.5, 0.5, -1.5], as_dataclass=True)
    ranges = np.array([[0.25, np.inf, 12.5], [np.nan, 3.75, 80.0]], np.float32)
    reflect = np.array([[1, 2, 3], [250, 251, 252]], np.uint8)
    scan = ls.make_scan(info, {"range": ranges, "reflectivity": reflect},
                        stamp_ns=1_600_000_000_999_000_001, is_destaggered=True,
                        column_time_offsets=[0, 1_000_000, 2_000_000], as_dataclass=True)
    path = tmp_path / "py.cdr"
    path.write_bytes(ls.encode(scan))
    fields = parse_fields(run(program, "decode", path))
    assert fields["stamp"] == "1600000000 999000001"
    assert fields["frame_id"] == "front_lidar"
    assert fields["lidar_info_time"] == "1600000000 42"
    assert (fields["height"], fields["width"]) == ("2", "3")
    assert (fields["is_bigendian"], fields["is_destaggered"]) == ("0", "1")
    assert fields["column_time_offsets"] == "0 1000000 2000000"
    assert [float(v) for v in fields["column_azimuth_angles"].split()] == \
        list(scan.column_azimuth_angles)
    assert fields["channel"] == [f"{c.name} {c.offset} {c.datatype} {c.count}"
                                 for c in scan.channels]
    assert bytes.fromhex(fields["data"]) == bytes(data_view(scan))


def parse_pixels(text: str) -> tuple[dict[str, str], dict[str, tuple[int, int, list[str]]]]:
    """The ``pixels`` mode's header lines and, per channel, (datatype, count, values)."""
    header: dict[str, str] = {}
    channels: dict[str, tuple[int, int, list[str]]] = {}
    for line in text.splitlines():
        key, _, value = line.partition("=")
        if key == "pixels":
            name, datatype, count, *values = value.split(" ")
            channels[name] = (int(datatype), int(count), values)
        else:
            header[key] = value
    return header, channels


def real_scans() -> list[tuple[str, Any, Any]]:
    """(label, LidarInfo, LidarScan) dataclasses of the real Ouster frames in tests/data, with
    float32 metres and with UINT32 millimetres."""
    from converters.ouster import info_from_metadata, scan_from_frame
    data = Path(__file__).parent / "data" / "ouster"
    out = []
    for frame_path in sorted(data.glob("*_frame*.npz")):
        meta = data / (frame_path.name.split("_frame")[0] + ".json")
        info = info_from_metadata(meta, stamp_ns=1_000_000_000, as_dataclass=True)
        with np.load(frame_path, allow_pickle=False) as npz:
            frame = {k: npz[k] for k in npz.files}
        for encoding in ("float32", "uint32_mm"):
            scan = scan_from_frame(frame, info, range_encoding=encoding, as_dataclass=True)
            out.append((f"{frame_path.stem} {encoding}", info, scan))
    return out


def check_pixels(text: str, scan: Any) -> None:
    """The C++ program's view of a scan equals Python's, pixel for pixel."""
    header, channels = parse_pixels(text)
    stamp = f"{scan.header.stamp.sec} {scan.header.stamp.nanosec}"
    assert header["stamp"] == stamp and header["frame_id"] == scan.header.frame_id
    assert header["lidar_info_time"] == (f"{scan.lidar_info_time.sec} "
                                         f"{scan.lidar_info_time.nanosec}")
    assert (header["height"], header["width"]) == (str(scan.height), str(scan.width))
    assert header["is_bigendian"] == str(int(bool(scan.is_bigendian)))
    assert header["is_destaggered"] == str(int(bool(scan.is_destaggered)))
    assert list(channels) == ls.channel_names(scan)
    for desc in scan.channels:
        datatype, count, values = channels[desc.name]
        assert (datatype, count) == (desc.datatype, desc.count)
        want = ls.channel(scan, desc.name).reshape(-1)
        got = np.array([float(v) if want.dtype.kind == "f" else int(v) for v in values],
                       dtype=want.dtype.newbyteorder("="))
        assert got.size == want.size
        np.testing.assert_array_equal(got, want.astype(want.dtype.newbyteorder("=")))


def test_real_python_encoded_scans_read_in_cpp(program: Any, tmp_path: Path) -> None:
    scans = real_scans()
    assert len(scans) >= 4 and any(s.channels[0].datatype == 6 for _, _, s in scans)
    path = tmp_path / "scan.cdr"
    for _, _, scan in scans:
        path.write_bytes(ls.encode(scan))
        check_pixels(run(program, "pixels", path), scan)
    # the other byte order: the program reads what the message says
    _, info, scan = scans[-1]
    big = ls.make_scan(info, {c.name: ls.channel(scan, c.name) for c in scan.channels},
                       ls.to_ns(scan.header.stamp), frame_id=scan.header.frame_id,
                       column_time_offsets=scan.column_time_offsets, is_bigendian=True,
                       as_dataclass=True)
    assert big.is_bigendian and bytes(data_view(big)) != bytes(data_view(scan))
    path.write_bytes(ls.encode(big))
    check_pixels(run(program, "pixels", path), big)


def test_scan_from_a_project_mcap_reads_in_cpp(program: Any, tmp_path: Path) -> None:
    from lidarscan.mcap import McapMessage, McapWriter, read_messages
    scan = next(s for label, _, s in real_scans() if "OS-0-32" in label and "uint32" in label)
    path = tmp_path / "scan.mcap"
    with McapWriter(path) as writer:
        writer.write("/lidar/scan", scan)
    payloads = [m.payload for m in read_messages(path)
                if isinstance(m, McapMessage) and m.topic == "/lidar/scan"]
    assert len(payloads) == 1
    cdr = tmp_path / "from_mcap.cdr"
    cdr.write_bytes(bytes(payloads[0]))
    check_pixels(run(program, "pixels", cdr), scan)
