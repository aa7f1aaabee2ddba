"""Ouster sensors: metadata JSON -> LidarInfo and ouster-sdk frames -> LidarScan
(:mod:`.metadata`)."""

from converters.sources.ouster.metadata import *  # noqa: F401,F403  (the public names)
from converters.sources.ouster.metadata import __all__  # noqa: F401
