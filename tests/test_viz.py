"""The colour scales and axis labels of the PNG views (converters.edge.demo.viz): robust, and true for
the sensor shown."""

from __future__ import annotations

import numpy as np
import pytest

import lidarscan as ls
from converters.edge.demo import viz

pytest.importorskip("matplotlib")


def test_one_bright_window_does_not_set_the_scale() -> None:
    """The demo's ambient channel: most pixels 150..300, 3 % saturated at 2500 (a doorway):
    the room keeps its contrast, the window saturates."""
    rng = np.random.default_rng(0)
    values = np.concatenate([rng.uniform(150, 300, 9700), np.full(300, 2500.0)])
    lo, hi = viz.robust_limits(values)
    assert 150 <= lo < 160 and 290 < hi < 750          # 2500 would leave the room black
    # a channel of a few levels (MAD 0): the percentiles, not a degenerate range
    steps = np.repeat([25.0, 60.0, 70.0], [300, 600, 100])
    assert viz.robust_limits(steps) == (25.0, 70.0)
    assert viz.robust_limits(np.array([])) == (0.0, 1.0)


def test_ranges_span_their_bulk_not_the_farthest_return() -> None:
    """An outdoor frame: most returns within 50 m, a few at 240 m."""
    rng = np.random.default_rng(1)
    ranges = np.concatenate([rng.uniform(3, 50, 9800), rng.uniform(150, 240, 200)])
    lo, hi = viz.robust_limits(ranges, range_like=True)
    assert lo < 4 and 45 < hi < 60


def _info(angles: np.ndarray, shifts: list[int] | None = None) -> object:
    return ls.make_info(stamp_ns=1, frame_id="l", vertical_angles=[0.1, -0.1],
                        horizontal_angles=angles, pixel_shift_by_row=shifts or [],
                        as_dataclass=True)


def _scan(info: object, azimuths: np.ndarray | None = None) -> object:
    return ls.make_scan(info, {"range": np.ones((2, 8), np.float32)}, 2,
                        column_azimuth_angles=azimuths, as_dataclass=True)


def test_the_column_label_says_how_azimuth_runs_for_this_sensor() -> None:
    ouster = _info(2 * np.pi * (1 - np.arange(8) / 8), [2, 0])
    label = viz.column_label(_scan(ouster), ouster)
    assert label.startswith("column (destaggered): azimuth decreases to the right")
    assert "Ouster" not in label
    rising = _info(np.radians(np.arange(8) * 45.0 + 90))          # no stagger
    label = viz.column_label(_scan(rising), rising)
    assert label.startswith("column: azimuth increases to the right (90 deg at column 0")
    # a scan's measured azimuths win over the info's (Velodyne, Hesai)
    measured = np.radians(350.0 - np.arange(8) * 10.0)
    label = viz.column_label(_scan(rising, measured), rising)
    assert "decreases" in label and "(350 deg at column 0" in label


def test_the_azimuth_panel_is_in_degrees(tmp_path: object) -> None:
    info = _info(2 * np.pi * (1 - np.arange(8) / 8))
    scan = ls.make_scan(info, {"range": np.ones((2, 8), np.float32),
                               "azimuth": np.tile(np.arange(8, dtype=np.uint16) * 4500, (2, 1))},
                        2, as_dataclass=True)
    image, label = viz._channel_image(scan, info, "azimuth")
    assert label == "azimuth [deg]" and image[0].tolist() == [i * 45.0 for i in range(8)]
    assert viz.range_image(scan, info, tmp_path / "r.png").read_bytes()[:4] == b"\x89PNG"
