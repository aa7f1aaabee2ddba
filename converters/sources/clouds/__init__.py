"""Driver PointCloud2 -> LidarScan + an estimated LidarInfo (:mod:`.importer`), with the grid
and beam-model estimation behind it (:mod:`.grid`)."""
