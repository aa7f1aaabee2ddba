"""Hesai packets -> LidarScan + LidarInfo, one scan per rotation.

:mod:`.formats` (the packet formats and calibration/firetime tables of each model),
:mod:`.rotation` (assembling the decoded blocks into a rotation), :mod:`.decoder` (the streaming
:class:`PacketDecoder` and :func:`decode_packets`).
"""

from converters.sources.hesai.decoder import *  # noqa: F401,F403  (the public names)
from converters.sources.hesai.decoder import __all__  # noqa: F401
