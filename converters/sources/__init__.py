"""What makes a LidarScan: one package or module per input family.

Each importer turns what a sensor or a recording gives (vendor packets, driver clouds, depth
images, tilting 2D scans, recordings) into ``LidarScan`` + ``LidarInfo`` messages.
Nothing here imports the outputs (PointCloud2, slices), the merger or the edge.
"""
