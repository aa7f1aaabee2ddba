"""Ouster lidar packets -> LidarScan (converters.ouster.PacketDecoder, pcap, ouster-ros bags).

* Real data, ground truth made by someone else: the two shipped pcaps (a dual-return OS-0-32
  frame and an OS-2-128 frame, tests/data/ouster/NOTICE.md) decode to exactly ouster-sdk's
  frames (the ``.npz``: every channel, dtype and column timestamp), and the scan is the one
  ``converters.ouster.scan_from_frame`` makes of those frames, byte for byte.
* Synthetic packets of every profile, beam count, column count and column window, against a
  per-pixel loop over the documented bit layout (tests/ouster_packet_helpers.py) and, when it
  is installed, ouster-sdk's own FrameBatcher on the same packets.
* Frames: missing packets and invalid columns give no-return pixels and are counted; a new
  frame id ends a frame, a late packet never opens a second one; another sensor's packet is
  an error naming both.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np
import pytest

from converters import ouster
from converters.sources.ouster.decoder import frame_arrays
from lidarscan import geometry
from lidarscan.errors import ConfigError, DecodeError, InfoMismatchError

from ouster_packet_helpers import (
    DATA, DOCUMENTED, OS0, OS2, WINDOWED, Writer, load, loop_frame, metadata, sdk_frames)

PROFILES = list(DOCUMENTED)


def _npz(name: str) -> dict[str, np.ndarray]:
    path = next(DATA.glob(f"{name}_frame*.npz"))
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def _same_scan(scan: Any, ref: Any) -> None:
    """Byte-identical scans: header, channels (names, types, offsets), data, times."""
    assert scan.header == ref.header
    assert scan.channels == ref.channels
    assert (scan.height, scan.width, scan.is_destaggered) == (ref.height, ref.width,
                                                              ref.is_destaggered)
    np.testing.assert_array_equal(np.asarray(scan.data), np.asarray(ref.data))
    np.testing.assert_array_equal(scan.column_time_offsets, ref.column_time_offsets)


def _decode(meta: Any, packets: list[bytes], **kw: Any) -> tuple[list[Any], Any]:
    decoder = ouster.PacketDecoder(meta, as_dataclass=True, **kw)
    out = []
    for k, packet in enumerate(packets):
        out += decoder.push(k, packet)
    return out + decoder.flush(), decoder


# ------------------------------------------------------------------------------ real data

@pytest.mark.parametrize("name", [OS2, OS0])
def test_real_pcap_frame_is_ouster_sdks(name: str) -> None:
    """Every array of ouster-sdk's frame, bit for bit and with its dtype."""
    meta = DATA / f"{name}.json"
    packets = [p for _, p in ouster.lidar_packets(DATA / f"{name}.pcap", meta)]
    assert len(packets) == 64
    expected = _npz(name)
    rows = np.stack([np.frombuffer(p, np.uint8) for p in packets])
    frame = frame_arrays(ouster.layout_from_metadata(meta), rows)
    assert sorted(frame) == sorted(expected)
    for key, value in expected.items():
        assert np.asarray(frame[key]).dtype == value.dtype or key == "frame_id", key
        np.testing.assert_array_equal(frame[key], value, err_msg=key)


@pytest.mark.parametrize("name", [OS2, OS0])
@pytest.mark.parametrize("encoding", ["float32", "uint32_mm"])
def test_real_pcap_scan_is_scan_from_frame(name: str, encoding: str) -> None:
    meta = DATA / f"{name}.json"
    results = list(ouster.scans_from_pcap(DATA / f"{name}.pcap", meta, as_dataclass=True,
                                          range_encoding=encoding))
    assert len(results) == 1
    scan, info = results[0]
    direct = ouster.info_from_metadata(meta, as_dataclass=True)
    assert geometry.info_key(info) == geometry.info_key(direct)
    assert (info.vendor_metadata, info.serial_number) == (direct.vendor_metadata,
                                                         direct.serial_number)
    expected = _npz(name)
    _same_scan(scan, ouster.scan_from_frame(expected, info, range_encoding=encoding,
                                            as_dataclass=True))
    times = expected["timestamps_ns"].astype(np.int64)
    assert scan.header.stamp.sec * 10**9 + scan.header.stamp.nanosec == times[0]
    np.testing.assert_array_equal(scan.column_time_offsets, times - times[0])


def test_real_pcap_destaggered_and_rclpy_paths() -> None:
    meta = DATA / f"{OS0}.json"
    packets = [p for _, p in ouster.lidar_packets(DATA / f"{OS0}.pcap", meta)]
    info = ouster.info_from_metadata(meta, as_dataclass=True)
    (scan, _), = _decode(meta, packets, destagger=True)[0]
    _same_scan(scan, ouster.scan_from_frame(_npz(OS0), info, destagger=True,
                                            as_dataclass=True))
    pytest.importorskip("lidarscan_msgs.msg")
    decoder = ouster.PacketDecoder(meta)
    out = [r for p in packets for r in decoder.push(0, p)]
    msg = out[0][0]
    assert type(msg).__module__.startswith("lidarscan_msgs")
    ref = ouster.scan_from_frame(_npz(OS0), decoder.info)
    assert bytes(msg.data) == bytes(ref.data)


def test_real_pcaps_through_ouster_sdk_frame_batcher() -> None:
    """The SDK's own batcher on the same packets gives the shipped frames (and ours)."""
    pytest.importorskip("ouster.sdk", reason="ouster-sdk (optional extra [ouster]) absent")
    for name in (OS2, OS0):
        meta_path = DATA / f"{name}.json"
        packets = [p for _, p in ouster.lidar_packets(DATA / f"{name}.pcap", meta_path)]
        later = [bytearray(p) for p in packets]
        for p in later:
            p[2:4] = ((int.from_bytes(p[2:4], "little") + 1) % 65536).to_bytes(2, "little")
        frames = sdk_frames(meta_path.read_text(), packets, 1, [bytes(p) for p in later])
        expected = _npz(name)
        for key, value in expected.items():
            np.testing.assert_array_equal(frames[0][key], value, err_msg=key)


# ----------------------------------------------------------------------------- synthetic

CASES = [(p, h, w) for p in PROFILES for h, w in ((16, 512), (32, 1024))] + [
    ("RNG19_RFL8_SIG16_NIR16", 64, 2048), ("RNG15_RFL8_NIR8", 128, 512),
    ("LEGACY", 128, 1024), ("RNG19_RFL8_SIG16_NIR16_DUAL", 16, 4096),
    ("FUSA_RNG15_RFL8_NIR8_DUAL", 16, 2048)]


@pytest.mark.parametrize("profile,height,width", CASES)
def test_synthetic_profiles_match_the_documented_layout(profile: str, height: int,
                                                        width: int) -> None:
    meta = metadata(profile, height, width)
    packets = Writer(meta, seed=height + width).frame(7)
    results, decoder = _decode(meta, packets)
    assert len(results) == 1 and decoder.stats["frames"] == 1
    expected = loop_frame(meta, packets)
    frame = frame_arrays(decoder.layout, np.stack([np.frombuffer(p, np.uint8)
                                                   for p in packets]))
    for key, value in expected.items():
        assert frame[key].dtype == value.dtype, key
        np.testing.assert_array_equal(frame[key], value, err_msg=key)
    for encoding in ("float32", "uint32_mm"):
        results, _ = _decode(meta, packets, range_encoding=encoding)
        _same_scan(results[0][0], ouster.scan_from_frame(expected, decoder.info,
                                                         range_encoding=encoding,
                                                         as_dataclass=True))


@pytest.mark.parametrize("profile", PROFILES)
@pytest.mark.parametrize("per_packet", [16, 8])
def test_synthetic_packets_match_ouster_sdk(profile: str, per_packet: int) -> None:
    """ouster-sdk's FrameBatcher on the same synthetic packets (an independent decoder),
    including a frame with a missing packet and invalid columns."""
    pytest.importorskip("ouster.sdk", reason="ouster-sdk (optional extra [ouster]) absent")
    meta = metadata(profile, 32, 512, per_packet)
    writer = Writer(meta, seed=3)
    first = writer.frame(11)
    second = writer.frame(12, invalid={5, 6, 300})
    del second[9]
    later = writer.frame(13) + writer.frame(14)
    frames = sdk_frames(meta, first + second, 2, later)
    assert len(frames) == 2
    results, decoder = _decode(meta, first + second)
    assert len(results) == 2
    for (scan, info), frame in zip(results, frames):
        assert (frame["status"] & 1).sum() in (512, 512 - 3 - per_packet)
        _same_scan(scan, ouster.scan_from_frame(frame, info, as_dataclass=True))
    assert decoder.stats["missing_columns"] == per_packet
    assert decoder.stats["invalid_columns"] == 3


def test_column_window_legacy_metadata() -> None:
    """The real windowed metadata (measurement ids 2014..2036 of 2048, LEGACY): the sensor
    sends the packets holding those columns; the frame is complete with the last of them."""
    meta = load(WINDOWED)
    meta["initialization_id"] = 0
    layout = ouster.layout_from_metadata(meta)
    assert (layout.profile, layout.packet_bytes, layout.column_window) == ("LEGACY", 24896,
                                                                             (2014, 2036))
    writer = Writer(meta, seed=5)
    packets = writer.frame(3)
    assert len(packets) == 3                          # columns 2000..2047
    decoder = ouster.PacketDecoder(meta, as_dataclass=True)
    assert decoder.push(0, packets[0]) == [] and decoder.push(0, packets[1]) == []
    (scan, info), = decoder.push(0, packets[2])       # complete: emitted without a flush
    expected = loop_frame(meta, packets)
    assert (expected["status"] != 0).sum() == 23
    _same_scan(scan, ouster.scan_from_frame(expected, info, as_dataclass=True))
    assert decoder.stats["invalid_columns"] == 48 - 23 and decoder.stats["missing_columns"] == 0
    ranges = np.asarray(ouster_range(scan))
    assert np.isinf(ranges[:, :2014]).all() and np.isinf(ranges[:, 2037:]).all()


def ouster_range(scan: Any) -> np.ndarray:
    import lidarscan
    return lidarscan.channel(scan, "range")


def test_window_across_column_zero() -> None:
    meta = metadata("RNG19_RFL8_SIG16_NIR16", 16, 512, window=(480, 40))
    packets = Writer(meta, seed=9).frame(4)
    assert len(packets) == 5
    results, decoder = _decode(meta, packets)
    assert len(results) == 1 and decoder.stats["missing_columns"] == 0
    _same_scan(results[0][0], ouster.scan_from_frame(loop_frame(meta, packets),
                                                     decoder.info, as_dataclass=True))


@pytest.mark.parametrize("name", [OS2, OS0])
def test_nested_metadata_layout_decodes_the_same(name: str) -> None:
    flat = load(name)
    nested = {
        "sensor_info": {"prod_line": flat["prod_line"], "prod_sn": flat["prod_sn"],
                        "initialization_id": flat["initialization_id"],
                        "build_rev": flat["build_rev"]},
        "beam_intrinsics": {"beam_altitude_angles": flat["beam_altitude_angles"],
                            "beam_azimuth_angles": flat["beam_azimuth_angles"],
                            "lidar_origin_to_beam_origin_mm":
                                flat["lidar_origin_to_beam_origin_mm"]},
        "lidar_intrinsics": {"lidar_to_sensor_transform": flat["lidar_to_sensor_transform"]},
        "lidar_data_format": flat["data_format"],
        "config_params": {"lidar_mode": flat["lidar_mode"],
                          "udp_port_lidar": flat["udp_port_lidar"]},
    }
    a = ouster.layout_from_metadata(flat)
    b = ouster.layout_from_metadata(nested)
    assert a == b and a.udp_port == 7502 and a.init_id == flat["initialization_id"]
    packets = [p for _, p in ouster.lidar_packets(DATA / f"{name}.pcap", nested)]
    (scan, _), = _decode(nested, packets)[0]
    (ref, _), = _decode(flat, packets)[0]
    np.testing.assert_array_equal(np.asarray(scan.data), np.asarray(ref.data))


def test_sdk_written_nested_metadata() -> None:
    layout = ouster.layout_from_metadata(DATA / f"{OS2}_nested.json")
    assert layout == ouster.layout_from_metadata(DATA / f"{OS2}.json")
    # a sensor's own metadata may give the profile and packet size in config_params only
    nested = json.loads((DATA / f"{OS2}_nested.json").read_text())
    fmt = nested["lidar_data_format"]
    nested["config_params"].update(udp_profile_lidar=fmt.pop("udp_profile_lidar"),
                                   columns_per_packet=fmt.pop("columns_per_packet"))
    assert ouster.layout_from_metadata(nested) == layout


def test_firmware_1_metadata_is_legacy() -> None:
    """No data_format at all (firmware 1.x): LEGACY, 16 columns per packet, every column."""
    meta = load(OS2)
    for key in ("data_format", "initialization_id", "udp_port_lidar"):
        meta.pop(key)
    layout = ouster.layout_from_metadata(meta)
    assert (layout.profile, layout.height, layout.width, layout.columns_per_packet,
            layout.column_window, layout.init_id) == ("LEGACY", 128, 1024, 16, (0, 1023), 0)
    packets = Writer({**meta, "data_format": {"pixels_per_column": 128,
                                              "columns_per_frame": 1024,
                                              "columns_per_packet": 16}}).frame(2)
    results, decoder = _decode(meta, packets)
    assert len(results) == 1
    _same_scan(results[0][0], ouster.scan_from_frame(
        loop_frame({**meta, "data_format": {"pixels_per_column": 128, "columns_per_frame": 1024,
                                            "columns_per_packet": 16}}, packets),
        decoder.info, as_dataclass=True))


# ------------------------------------------------------------------------------- frames

def test_missing_packets_and_invalid_columns_are_no_return_and_counted() -> None:
    meta = metadata("RNG19_RFL8_SIG16_NIR16", 16, 512)
    writer = Writer(meta, seed=1)
    packets = writer.frame(20, invalid={0, 100, 101})
    del packets[10]                                   # columns 160..175 never arrive
    results, decoder = _decode(meta, packets)
    assert len(results) == 1
    scan, info = results[0]
    assert decoder.stats == {"packets": 31, "frames": 1, "late_packets": 0,
                             "missing_columns": 16, "invalid_columns": 3}
    rng = ouster_range(scan)
    gone = [0, 100, 101, *range(160, 176)]
    assert np.isinf(rng[:, gone]).all()
    expected = loop_frame(meta, packets)
    _same_scan(scan, ouster.scan_from_frame(expected, info, as_dataclass=True))
    # column 0 invalid: the stamp is extrapolated from column 1 by the nominal increment
    times = expected["timestamps_ns"].astype(np.int64)
    stamp = scan.header.stamp.sec * 10**9 + scan.header.stamp.nanosec
    assert stamp == times[1] - info.column_time_increment
    assert scan.column_time_offsets[1] == times[1] - stamp


def test_frame_boundaries_never_shift_or_merge() -> None:
    meta = metadata("RNG15_RFL8_NIR8", 16, 512)
    writer = Writer(meta, seed=2)
    a, b, c = writer.frame(1, 10**12), writer.frame(2, 10**12 + 10**8), writer.frame(3)
    stream = a[:20] + b + [a[25]] + c[:4]             # a ends early, then a late packet of a
    decoder = ouster.PacketDecoder(meta, as_dataclass=True)
    counts = [len(decoder.push(k, p)) for k, p in enumerate(stream)]
    assert counts[20] == 1                             # b's first packet ends a
    assert counts[19 + len(b)] == 1                    # b's last packet completes b
    assert sum(counts) == 2                            # c is still open
    decoder = ouster.PacketDecoder(meta, as_dataclass=True)
    results = [r for k, p in enumerate(stream) for r in decoder.push(k, p)] + decoder.flush()
    assert len(results) == 3
    assert decoder.stats["late_packets"] == 1 and decoder.stats["frames"] == 3
    for (scan, info), packets in zip(results, (a[:20], b, c[:4])):
        _same_scan(scan, ouster.scan_from_frame(loop_frame(meta, packets), info,
                                                as_dataclass=True))
    assert decoder.flush() == []


def test_push_many_equals_push() -> None:
    meta = metadata("RNG19_RFL8_SIG16_NIR16_DUAL", 16, 512)
    writer = Writer(meta, seed=4)
    stream = writer.frame(1) + writer.frame(2)[:7] + writer.frame(3)
    one, _ = _decode(meta, stream)
    decoder = ouster.PacketDecoder(meta, as_dataclass=True)
    rows = np.stack([np.frombuffer(p, np.uint8) for p in stream])
    many = decoder.push_many(np.zeros(len(stream), np.int64), rows) + decoder.flush()
    assert len(one) == len(many) == 3
    for (s1, _), (s2, _) in zip(one, many):
        _same_scan(s1, s2)
    assert rows.flags.writeable and rows.sum() == sum(np.frombuffer(p, np.uint8).sum()
                                                      for p in stream)


def test_push_reads_an_ndarray_packet_without_changing_it() -> None:
    """A packet given as a 1-D uint8 array (contiguous, read-only, or a strided view) decodes
    as its bytes do, and the caller's array is left as it was."""
    meta = metadata("RNG19_RFL8_SIG16_NIR16", 16, 512)
    packets = Writer(meta, seed=9).frame(1)
    expected, _ = _decode(meta, packets)
    arrays = [np.frombuffer(p, np.uint8) for p in packets]          # read-only views
    wide = np.zeros((len(packets), 2 * len(packets[0])), np.uint8)
    wide[:, ::2] = np.stack(arrays)
    for given in (arrays, [a.copy() for a in arrays], list(wide[:, ::2])):
        before = [a.copy() for a in given]
        got, _ = _decode(meta, given)
        assert len(got) == len(expected) == 1
        _same_scan(got[0][0], expected[0][0])
        for a, b in zip(given, before):
            np.testing.assert_array_equal(a, b)
    decoder = ouster.PacketDecoder(meta)
    with pytest.raises(DecodeError, match="1-D uint8"):
        decoder.push(0, np.stack(arrays[:2]))
    with pytest.raises(DecodeError, match="1-D uint8"):
        decoder.push(0, arrays[0].astype(np.uint16))


def test_decode_packets_gives_the_frames_before_another_sensors_packet() -> None:
    """decode_packets (runs through push_many) stops at another sensor's packet as push()
    one by one does: the frames completed before it are given, then InfoMismatchError."""
    meta = metadata("RNG19_RFL8_SIG16_NIR16", 16, 512, init_id=4242)
    writer = Writer(meta, seed=3)
    stream = (writer.frame(1) + writer.frame(2)[:3] + [writer.packet(2, 48, init_id=777)]
              + writer.frame(3))
    decoder = ouster.PacketDecoder(meta, as_dataclass=True)
    one: list[Any] = []
    with pytest.raises(InfoMismatchError):
        for packet in stream:
            one += decoder.push(0, packet)
    got: list[Any] = []
    with pytest.raises(InfoMismatchError, match="777"):
        for result in ouster.decode_packets([(0, p) for p in stream], meta, as_dataclass=True):
            got.append(result)
    assert len(got) == len(one) == 1
    _same_scan(got[0][0], one[0][0])


def test_another_sensors_packet_is_an_error_naming_both() -> None:
    meta = metadata("RNG19_RFL8_SIG16_NIR16", 16, 512, init_id=4242)
    writer = Writer(meta)
    decoder = ouster.PacketDecoder(meta, as_dataclass=True)
    decoder.push(0, writer.packet(1, 0))
    with pytest.raises(InfoMismatchError) as err:
        decoder.push(0, writer.packet(1, 16, init_id=777))
    assert "777" in str(err.value) and "4242" in str(err.value)
    with pytest.raises(InfoMismatchError, match="123456"):
        decoder.push(0, writer.packet(1, 16, serial=123456))
    rows = np.frombuffer(writer.packet(1, 32, init_id=5), np.uint8)[None]
    errors: list[Any] = []
    assert decoder.push_many([0], rows, errors=errors) == []
    assert errors and errors[0][0] == 0 and isinstance(errors[0][1], InfoMismatchError)
    assert len(decoder.push(0, writer.packet(1, 48))) == 0      # still usable


def test_bad_inputs() -> None:
    meta = metadata("RNG19_RFL8_SIG16_NIR16", 16, 512)
    decoder = ouster.PacketDecoder(meta)
    with pytest.raises(DecodeError, match="packet size"):
        decoder.push(0, b"\x00" * 48)
    with pytest.raises(ConfigError, match="metadata"):
        ouster.PacketDecoder()
    bad = metadata("RNG99", 16, 512)
    with pytest.raises(DecodeError, match="udp_profile_lidar"):
        ouster.PacketDecoder(bad)
    bad = metadata("LEGACY", 16, 512, window=(0, 600))
    with pytest.raises(Exception, match="column_window"):
        ouster.layout_from_metadata(bad)


def test_frame_with_no_valid_column_gives_no_scan() -> None:
    meta = metadata("RNG19_RFL8_SIG16_NIR16", 16, 512)
    packets = Writer(meta).frame(1, invalid=set(range(512)))
    results, decoder = _decode(meta, packets)
    assert results == [] and decoder.stats["invalid_columns"] == 512


def test_packet_sizes_from_metadata() -> None:
    sizes = {p: ouster.layout_from_metadata(metadata(p, 128, 1024)).packet_bytes
             for p in PROFILES}
    assert sizes == {"LEGACY": 24896, "RNG19_RFL8_SIG16_NIR16": 24832,
                     "RNG19_RFL8_SIG16_NIR16_DUAL": 33024, "RNG15_RFL8_NIR8": 8448,
                     "FUSA_RNG15_RFL8_NIR8_DUAL": 16640}
    assert json.loads(json.dumps(sizes)) == sizes


def test_valid_columns_without_timestamps_give_no_scan() -> None:
    meta = metadata("RNG19_RFL8_SIG16_NIR16", 16, 512)
    writer = Writer(meta)
    packets = []
    for p in writer.frame(1):
        raw = bytearray(p)
        for k in range(writer.cpp):
            raw[writer.head + k * writer.col:writer.head + k * writer.col + 8] = bytes(8)
        packets.append(bytes(raw))
    results, decoder = _decode(meta, packets)
    assert results == [] and decoder.stats["frames"] == 1


@pytest.mark.parametrize("profile", PROFILES)
def test_header_and_headers_read_the_documented_fields(profile: str) -> None:
    """One packet's header() and the rows' headers() give the frame id, init_id and serial
    number the Writer put at the documented offsets (LEGACY: the first column's frame id)."""
    meta = metadata(profile, 16, 512, init_id=0xABCDEF, serial="1099511627775")
    writer = Writer(meta)
    layout = ouster.layout_from_metadata(meta)
    packets = [writer.packet(frame, 0) for frame in (3, 0xBEEF)]
    rows = np.stack([np.frombuffer(p, np.uint8) for p in packets])
    ident = (0, 0) if profile == "LEGACY" else (0xABCDEF, 2**40 - 1)
    expected = [(3, *ident), (0xBEEF, *ident)]
    assert [layout.header(p) for p in packets] == expected
    assert [tuple(int(v) for v in column) for column in zip(*layout.headers(rows))] == expected
