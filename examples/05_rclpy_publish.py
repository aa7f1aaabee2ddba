"""Publish a LidarInfo (latched) and a LidarScan with rclpy, receive the scan as raw CDR and
decode it without copying. Exits by itself.

Run: python examples/05_rclpy_publish.py   (uses $ROS_DOMAIN_ID if set)
"""

import time

import numpy as np
import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data

import lidarscan

try:
    from lidarscan_msgs.msg import LidarInfo, LidarScan
except ModuleNotFoundError:   # a plain `pip install` builds no message package
    raise SystemExit("this example publishes lidarscan_msgs, not built into this environment: "
                     "run `make install` in the checkout (README, 'Other ways to install')"
                     ) from None

LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


def main() -> int:
    rclpy.init()                       # returns None with the Jazzy wheels: use try/finally
    try:
        node = Node("example_publisher")
        info = lidarscan.make_info(stamp_ns=1_000_000_000, frame_id="lidar",
                                   vertical_angles=np.radians(np.linspace(15, -15, 16)),
                                   horizontal_angles=2 * np.pi * (1 - np.arange(512) / 512))
        ranges = np.full((16, 512), 4.2, np.float32)
        scan = lidarscan.make_scan(info, {"range": ranges}, 2_000_000_000)  # an rclpy message

        received = []
        node.create_subscription(LidarScan, "lidar_scan",
                                 lambda raw: received.append(lidarscan.decode_scan(raw)),
                                 qos_profile_sensor_data, raw=True)   # raw CDR bytes
        info_pub = node.create_publisher(LidarInfo, "lidar_info", LATCHED)
        scan_pub = node.create_publisher(LidarScan, "lidar_scan", qos_profile_sensor_data)
        info_pub.publish(info)

        executor = SingleThreadedExecutor()
        executor.add_node(node)
        deadline = time.monotonic() + 10.0
        while not received and time.monotonic() < deadline:
            scan_pub.publish(scan)    # best effort: repeat until discovery has completed
            executor.spin_once(timeout_sec=0.1)
        if not received:
            print("no scan received within 10 s")
            return 1
        got = received[0]
        print(f"received LidarScan {got.height}x{got.width}, range[0, 0] = "
              f"{lidarscan.range_m(got, info)[0, 0]:.1f} m, {len(got.data)} data bytes")
        return 0
    except (KeyboardInterrupt, ExternalShutdownException):
        return 0
    finally:
        rclpy.try_shutdown()


if __name__ == "__main__":
    raise SystemExit(main())
