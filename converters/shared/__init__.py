"""Shared vocabulary of the converters (the bottom of ``converters``): parameter validation
(:mod:`.options`), extrinsics and frames (:mod:`.frames`), rigid transforms and tracks
(:mod:`.transforms`), motion models (:mod:`.deskew`), PointCloud2 field layouts
(:mod:`.cloud_layout`), bare ROS message construction (:mod:`.rosmsg`) and the geometry service
the outputs ask once per scan (:mod:`.scan_rays`).

Nothing here imports an importer, an output, the merger, the kernels or the edge.
"""
