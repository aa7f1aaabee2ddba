"""Shared vocabulary of the converters (the bottom of ``converters``): parameter validation
(:mod:`.options`), extrinsics and frames (:mod:`.frames`), rigid transforms and tracks
(:mod:`.transforms`), motion models (:mod:`.deskew`), PointCloud2 field layouts
(:mod:`.cloud_layout`) and bare ROS message construction (:mod:`.rosmsg`).

Nothing here imports an importer, an output, the merger, the kernels or the edge.
"""
