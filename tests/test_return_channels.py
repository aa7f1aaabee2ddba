"""The N-th return channel rule (msgs/README.md: the N-th return appends N, ``range2``,
``intensity2``; ``range3`` for a third) is stated once, :func:`lidarscan.scan.return_of` /
:func:`lidarscan.scan.return_channel`, and every place that finds returns by name follows it.

Each use site is tested on an input where its own old rule disagreed with the README's.
"""

from __future__ import annotations

import numpy as np
import pytest

import lidarscan as ls
from lidarscan.errors import LidarScanError
from lidarscan.scan import return_channel, return_channels, return_of


@pytest.mark.parametrize(("name", "names", "expected"), [
    ("range", ("range", "range2"), ("range", 1)),
    ("range2", ("range", "range2"), ("range", 2)),
    ("intensity3", ("intensity", "intensity3"), ("intensity", 3)),
    ("signal12", ("signal", "signal12"), ("signal", 12)),
    ("range2", ("range2",), ("range2", 1)),          # no first return of that name
    ("range1", ("range", "range1"), ("range1", 1)),  # N >= 2: "range" is the first return
    ("range02", ("range", "range02"), ("range02", 1)),   # no leading zero
    ("beam7", ("range", "beam7"), ("beam7", 1)),     # a name ending in a digit, not a return
    ("2", ("", "2"), ("2", 1)),                      # no base name
    ("near_ir", ("near_ir",), ("near_ir", 1)),
])
def test_return_of(name: str, names: tuple[str, ...], expected: tuple[str, int]) -> None:
    assert return_of(name, names) == expected


def test_return_channel_is_the_inverse_of_return_of() -> None:
    for base in ("range", "intensity", "near_ir", "signal"):
        for number in range(1, 13):
            name = return_channel(base, number)
            assert name == (base if number == 1 else f"{base}{number}")
            assert return_of(name, (base, name)) == (base, number)
    with pytest.raises(LidarScanError, match="return number"):
        return_channel("range", 0)


def test_return_channels_lists_a_channels_returns_in_order() -> None:
    names = ("range3", "intensity", "range", "beam7", "range2", "intensity3", "range1")
    assert return_channels("range", names) == ["range", "range2", "range3"]
    assert return_channels("intensity", names) == ["intensity", "intensity3"]
    assert return_channels("beam", names) == [] and return_channels("ambient", names) == []


def _scan(names: tuple[str, ...]) -> tuple[object, object]:
    rng = np.random.default_rng(3)
    info = ls.make_info(stamp_ns=1, frame_id="lidar",
                        vertical_angles=np.radians(np.linspace(10, -10, 4)),
                        horizontal_angles=2 * np.pi * (1 - np.arange(16) / 16),
                        as_dataclass=True)
    channels = {n: (rng.uniform(1, 50, (4, 16)).astype(np.float32) if n.startswith("range")
                    else rng.integers(0, 255, (4, 16), dtype=np.uint8)) for n in names}
    return ls.make_scan(info, channels, 5, as_dataclass=True), info


def test_the_mcap_writer_counts_only_return_channels() -> None:
    """A channel whose name merely ends in a digit is no second return: its scan's repeats
    stay local (the writer used to take any trailing digit for a return)."""
    from lidarscan._mcap_writer import _local
    from lidarscan.mcap import SCAN_TYPE

    assert _local(_scan(("range", "intensity", "beam7"))[0], SCAN_TYPE)
    assert _local(_scan(("range", "intensity", "range1"))[0], SCAN_TYPE)
    assert not _local(_scan(("range", "intensity", "range2", "intensity2"))[0], SCAN_TYPE)
    assert not _local(_scan(("range", "intensity", "range3"))[0], SCAN_TYPE)


TRIPLE = ("range", "intensity", "range2", "intensity2", "range3", "intensity3")


def test_the_codec_study_drops_every_later_return_from_the_first_return_scan() -> None:
    """A triple-return scan's (Hesai PandarXT32M mode 0x3D) first-return channels exclude the
    third return too (they used to keep ``range3`` and ``intensity3``)."""
    from converters.edge.evidence import codec_study

    scan, info = _scan(TRIPLE)
    first = codec_study.first_return_scan(scan, info)
    assert ls.scan.channel_names(first) == ["range", "intensity"]
    assert codec_study.second_return_pairs(scan) == [("range", "range2"),
                                                     ("intensity", "intensity2")]
    assert codec_study.second_return_pairs(_scan(("range", "beam2"))[0]) == []


def test_the_nebula_cloud_carries_every_return() -> None:
    """Nebula publishes every return of every firing: the third return's points too, with
    return_type 3 and the third return's intensity (it used to stop at ``range2``)."""
    from converters.edge.evidence import codec_study
    from converters.edge.evidence.sensors import NEBULA_STEP

    scan, info = _scan(TRIPLE)
    cloud = np.frombuffer(codec_study.nebula_cloud(scan, info), np.uint8).reshape(-1, NEBULA_STEP)
    return_type = cloud[:, 13]
    assert np.bincount(return_type).tolist() == [0, 64, 64, 64]
    intensity = cloud[:, 12]
    for number in (1, 2, 3):
        expected = ls.channel(scan, return_channel("intensity", number))
        assert sorted(intensity[return_type == number]) == sorted(expected.ravel())
