"""Benchmark: Ouster lidar packets -> LidarScan as a multiple of real time, one core, and
ouster-sdk's own pcap -> LidarScan path in the same run.

Run: ``.venv/bin/python bench/bench_ouster.py [--frames N] [--rounds N]``. Prints medians and
ratios measured in one run (no assertions). Target: the decoder >= 100x real time for an
OS-2-128 at 1024x10 (RNG19_RFL8_SIG16_NIR16, 64 packets of 24 832 bytes per 0.1 s frame), and
not slower than ouster-sdk.

Input: the real OS-2-128 frame of ``tests/data/ouster`` (one frame, 64 lidar packets and 10 IMU
packets), repeated ``--frames`` times (default 10 = 1 s of sensor time) with frame ids counting
up: in memory for the decoder, and written as one classic pcap (the same Ethernet/IP/UDP
frames, UDP checksum cleared) for the pcap paths. Candidates, interleaved round after round:

* ``push_many``: ``PacketDecoder.push_many`` on the (N, 24832) uint8 array of all packets, then
  ``flush``: (LidarScan, LidarInfo) dataclasses, range float32 metres (the default);
* ``push_many uint32_mm``: the same with ``range_encoding="uint32_mm"`` (ranges kept in mm);
* ``push``: ``PacketDecoder.push`` packet by packet (bytes);
* ``push+msg``: ``push`` building rclpy messages (what a node publishes; skipped without them);
* ``pcap``: ``converters.ouster.scans_from_pcap`` on the file (read, decode, scans);
* ``sdk pcap``: ouster-sdk's ``open_source(pcap, meta=[json])``, iterated to the end: its
  ``LidarFrame`` per frame (its own pcap -> LidarScan path; needs ``pip install ouster-sdk``);
* ``sdk pcap+scan``: the same, each frame then turned into a LidarScan by
  ``converters.ouster.scan_from_frame`` (what this project did before its own decoder).

Medians of wall-clock time and of CPU time (``time.process_time``, a second set of rounds): on
a shared, overloaded machine the process is often descheduled, and the CPU time is what one
core spends. The load average is printed with the figures.
"""

from __future__ import annotations

import argparse
import os
import statistics
import struct
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).parent))
from _timing import interleaved_times  # noqa: E402

import numpy as np  # noqa: E402

from converters import ouster  # noqa: E402

DATA = Path(__file__).resolve().parent.parent / "tests" / "data" / "ouster"
NAME = "OS-2-128-U1_v2.3.0_1024x10"


def _records(path: Path) -> tuple[bytes, list[tuple[bytes, bytes]]]:
    """(global header, [(record header, frame bytes)]) of a classic little-endian pcap."""
    data = path.read_bytes()
    out, at = [], 24
    while at + 16 <= len(data):
        caplen = struct.unpack_from("<I", data, at + 8)[0]
        out.append((data[at:at + 16], data[at + 16:at + 16 + caplen]))
        at += 16 + caplen
    return data[:24], out


def build_inputs(frames: int, directory: Path) -> tuple[np.ndarray, Path]:
    """All lidar packets of ``frames`` copies of the real frame, as an (N, size) array and as
    a pcap file (frame ids counting up, UDP checksum cleared)."""
    meta = DATA / f"{NAME}.json"
    size = ouster.layout_from_metadata(meta).packet_bytes
    head, records = _records(DATA / f"{NAME}.pcap")
    rows, out = [], [head]
    for k in range(frames):
        for rec, frame in records:
            frame = bytearray(frame)
            udp = 14 + (frame[14] & 0x0F) * 4
            if len(frame) - udp - 8 == size:
                fid = (int.from_bytes(frame[udp + 10:udp + 12], "little") + k) % 65536
                frame[udp + 10:udp + 12] = fid.to_bytes(2, "little")
                frame[udp + 6:udp + 8] = b"\x00\x00"
                rows.append(np.frombuffer(bytes(frame[udp + 8:]), np.uint8))
            out += [rec, bytes(frame)]
    path = directory / f"{NAME}_x{frames}.pcap"
    path.write_bytes(b"".join(out))
    return np.stack(rows), path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=10, help="frames of 0.1 s (10)")
    parser.add_argument("--rounds", type=int, default=15, help="interleaved rounds (15)")
    args = parser.parse_args()
    meta = DATA / f"{NAME}.json"
    sensor_s = args.frames * 0.1

    with tempfile.TemporaryDirectory() as tmp:
        rows, pcap = build_inputs(args.frames, Path(tmp))
        packets = [r.tobytes() for r in rows]
        stamps = np.zeros(len(rows), np.int64)

        def push_many(**kw: Any) -> int:
            decoder = ouster.PacketDecoder(meta, as_dataclass=True, **kw)
            return len(decoder.push_many(stamps, rows) + decoder.flush())

        def push(as_dataclass: bool = True) -> int:
            decoder = ouster.PacketDecoder(meta, as_dataclass=as_dataclass)
            n = sum(len(decoder.push(0, p)) for p in packets)
            return n + len(decoder.flush())

        candidates: dict[str, Any] = {
            "push_many": push_many,
            "push_many uint32_mm": lambda: push_many(range_encoding="uint32_mm"),
            "push": push,
            "pcap": lambda: sum(1 for _ in ouster.scans_from_pcap(pcap, meta,
                                                                  as_dataclass=True)),
        }
        try:
            import lidarscan_msgs.msg  # noqa: F401
            candidates["push+msg"] = lambda: push(as_dataclass=False)
        except ImportError:
            print("push+msg: skipped (no lidarscan_msgs)")
        try:
            from ouster.sdk import open_source
        except ImportError:
            print("sdk: skipped (ouster-sdk not installed: pip install ouster-sdk)")
        else:
            info = ouster.info_from_metadata(meta, as_dataclass=True)
            names = {"RANGE": "range_mm", "SIGNAL": "signal", "REFLECTIVITY": "reflectivity",
                     "NEAR_IR": "near_ir", "FLAGS": "flags"}

            def sdk(scan: bool) -> int:
                source = open_source(str(pcap), meta=[str(meta)])
                n = 0
                for item in source:
                    frame = item if hasattr(item, "status") else item[0]
                    if frame is None:
                        continue
                    if scan:
                        arrays = {names[f]: np.asarray(frame.field(f)) for f in frame.fields
                                  if f in names}
                        arrays["timestamps_ns"] = np.asarray(frame.timestamp)
                        arrays["status"] = np.asarray(frame.status)
                        ouster.scan_from_frame(arrays, info, as_dataclass=True)
                    n += 1
                source.close()
                return n

            candidates["sdk pcap"] = lambda: sdk(False)
            candidates["sdk pcap+scan"] = lambda: sdk(True)
        counts = {name: fn() for name, fn in candidates.items()}
        print(f"{len(rows)} packets, {args.frames} frames ({sensor_s:.1f} s of sensor time); "
              f"frames out: {counts}")
        load = os.getloadavg()[0]
        wall = interleaved_times(candidates, args.rounds)
        cpu = interleaved_times(candidates, args.rounds, seed=1, clock=time.process_time)
    print(f"load average {load:.1f} -> {os.getloadavg()[0]:.1f}; medians of {args.rounds} "
          "rounds")
    base = statistics.median(cpu["sdk pcap"]) if "sdk pcap" in cpu else None
    print(f"{'candidate':22s} {'wall ms':>9s} {'x real':>8s} {'cpu ms':>9s} {'x real':>8s}"
          + ("  cpu / sdk pcap" if base else ""))
    for name in candidates:
        w, c = statistics.median(wall[name]), statistics.median(cpu[name])
        line = (f"{name:22s} {w * 1e3:9.2f} {sensor_s / w:8.1f} {c * 1e3:9.2f} "
                f"{sensor_s / c:8.1f}")
        if base:
            line += f"  {c / base:6.3f}"
        print(line)


if __name__ == "__main__":
    main()
