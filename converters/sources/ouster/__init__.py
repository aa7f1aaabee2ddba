"""Ouster sensors: metadata JSON -> LidarInfo, frames and lidar packets -> LidarScan."""
