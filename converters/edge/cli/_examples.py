"""The examples at the end of each ``lidarscan COMMAND --help`` (an argparse epilog kept as
written; ``tests/test_cli_help.py`` parses every example line with the real parser)."""

from __future__ import annotations

import argparse

EXAMPLES = {
    "demo": """\
examples:
  lidarscan demo --out /tmp/demo                 # 10 frames, demo.mcap and PNG views
  lidarscan demo --out /tmp/demo --frames 50 --no-images --noise 0.01
""",
    "info": """\
examples:
  lidarscan info my_bag/                         # a rosbag2 folder (metadata.yaml + .db3/.mcap)
  lidarscan info my_bag/my_bag_0.db3             # one storage file of a bag
  lidarscan info run.mcap                        # size, dates, topics, sensors, problems
  lidarscan info capture.pcap --metadata sensor.json   # an Ouster capture, as convert reads it
""",
    "convert": """\
examples:
  lidarscan convert velodyne_bag/ out.mcap --calibration VLP32.yaml   # packets -> LidarScan
  lidarscan convert hesai_bag/ out/ --calibration PandarXT32.csv      # OUT/: a rosbag2 folder
  lidarscan convert scans.mcap out.mcap --pointcloud2 --preset ouster --replace
  lidarscan convert scans.mcap out.mcap --frame base_link --slice floor:0.05:0.5:holes --merge
  lidarscan convert big.mcap part.mcap --start +10 --end +20   # seconds after the first message
  lidarscan convert big.mcap part.mcap --start 2024-04-19T02:11:17Z --end 1713492700.5
  lidarscan convert big.mcap lidar.mcap --topics /lidar/info,/lidar/scan,/tf_static
  lidarscan convert scans.mcap out.mcap --rename-topic /lidar/scan=/front/lidar_scan
  lidarscan convert capture.pcap out.mcap --metadata sensor.json    # Ouster (ouster-sdk)
  lidarscan convert clouds.mcap scans.mcap --compress               # LidarScan, codec-compressed
""",
    "view": """\
examples:
  lidarscan view out.mcap --out views/           # the first complete rotation of each scan topic
  lidarscan view out.mcap --out views/ --index 10 --frame base_link
""",
}


class HelpFormatter(argparse.HelpFormatter):
    """argparse's formatter, but an ``examples:`` block (the epilog) is printed as written."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        if text.startswith("examples:"):
            return "".join(indent + line for line in text.splitlines(keepends=True))
        return super()._fill_text(text, width, indent)
