"""LidarScan (or any PointCloud2) -> height-filtered LaserScan slices.

Layers, bottom up: :mod:`.spec` (the slicing spec: angle grid, binning, value classes, fusion
codes, decoding, LaserScan assembly; shared with the merger and the kernels), :mod:`.holes`
(negative obstacles), :mod:`.tables` (per-pixel ray tables of a LidarInfo version), then the
converters :mod:`.converter` (:class:`SliceConverter`, :func:`to_laserscan`) and :mod:`.cloud`
(:class:`CloudSliceConverter`, :func:`cloud_to_laserscan`). The public names are
``converters.to_laserscan``, ``converters.SliceConverter`` and the short path
``converters.laserscan``.
"""
