"""Shared, generic test fixtures (keep this file small: no heavy work at import or per test).

* a Hypothesis profile with modest example counts and no deadline (shared 2-core machine);
* ``rng``: a seeded numpy Generator;
* ``small_info``: a tiny valid LidarInfo dataclass (4 beams x 8 columns), no ROS libraries needed;
* Ctrl-C restored: a suite started in the background of a non-interactive shell inherits SIGINT
  ignored, and so would every process it starts (the Ctrl-C tests send real SIGINTs).
"""

from __future__ import annotations

import signal
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, settings

settings.register_profile(
    "lidarscan", max_examples=60, deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
settings.load_profile("lidarscan")

if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.fixture
def rng() -> np.random.Generator:
    """Seeded random generator (same numbers on every run)."""
    return np.random.default_rng(20240601)


@pytest.fixture
def small_info() -> Any:
    """A valid 4x8 ``lidarscan.types.LidarInfo`` (stamp 1.5 s, frame "lidar")."""
    import lidarscan

    return lidarscan.make_info(
        stamp_ns=1_500_000_000, frame_id="lidar",
        vertical_angles=np.radians([15.0, 5.0, -5.0, -15.0]),
        horizontal_angles=2 * np.pi * (1 - np.arange(8) / 8),
        as_dataclass=True)
