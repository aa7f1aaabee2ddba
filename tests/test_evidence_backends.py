"""The deterministic blocks of docs/proposal.md do not depend on the compiled kernels.

``make evidence --check`` must give the same answer on a machine with the C kernels built and on
one without (``LIDARSCAN_NO_KERNEL=1``): the deterministic sections run on the reference paths
(:func:`converters.edge.evidence.reference_backends`). Checked on the ``slicing`` section (a couple
of seconds), whose bin-by-bin comparison of slices from the scan and from a PointCloud2 changes
when the cloud is written by the C kernel instead of numpy (a few float32 ulps per point); each
backend runs in its own interpreter, so nothing is shared between them.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from typing import Any

import pytest

from converters.pointcloud2.converter import kernel_available

CHILD = """
import json
from converters.edge import evidence
from converters.edge.evidence import slicing
from converters.pointcloud2.converter import kernel_available

outside = slicing.slice_agreement()          # the enabled backend, outside the reference paths
blocks = evidence.generate(fast=True, sections=["slicing"])
print(json.dumps({"kernel": kernel_available(), "outside": outside,
                  "blocks": {b.name: b.text for b in blocks if b.deterministic},
                  "failed": evidence.FAILED}))
"""


def _child(no_kernel: str) -> dict[str, Any]:
    env = {**os.environ, "LIDARSCAN_NO_KERNEL": no_kernel}
    done = subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True,
                          env=env, timeout=600, check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    out: dict[str, Any] = json.loads(done.stdout.strip().splitlines()[-1])
    return out


@pytest.fixture(scope="module")
def both() -> tuple[dict[str, Any], dict[str, Any]]:
    return _child("0"), _child("1")


def test_deterministic_blocks_are_the_same_with_and_without_the_kernels(
        both: tuple[dict[str, Any], dict[str, Any]]) -> None:
    with_kernels, without = both
    assert without["kernel"] is False
    assert with_kernels["failed"] == {} and without["failed"] == {}
    assert set(with_kernels["blocks"]) == {"slicing", "merger"}
    assert with_kernels["blocks"] == without["blocks"]


def test_the_subset_is_sensitive_to_the_backend(
        both: tuple[dict[str, Any], dict[str, Any]]) -> None:
    """Outside the reference paths the same measurement differs between the backends: the
    test above would see a backend leaking into a block."""
    with_kernels, without = both
    if not (kernel_available() and with_kernels["kernel"]):
        pytest.skip("the C PointCloud2 kernel is not built here: one backend only")
    assert with_kernels["outside"] != without["outside"]


def test_numpy_reference_builds_numpy_converters_inside_only() -> None:
    import numpy as np

    import lidarscan
    from converters.pointcloud2.converter import PointCloud2Converter, numpy_reference, to_pointcloud2

    info = lidarscan.make_info(stamp_ns=1_000, frame_id="lidar",
                               vertical_angles=np.radians([10.0, 0.0, -10.0]),
                               horizontal_angles=2 * np.pi * (1 - np.arange(16) / 16),
                               beam_origins=np.tile([0.015, 0.0, 0.01], 3),
                               range_multiplier=0.001, as_dataclass=True)
    ranges = (np.arange(48, dtype=np.uint32).reshape(3, 16) * 997) % 30_000
    scan = lidarscan.make_scan(info, {"range": ranges,
                                      "intensity": np.ones((3, 16), np.uint16)}, 2_000,
                               as_dataclass=True)
    reference = PointCloud2Converter(info, kernel=False).convert(scan)
    with numpy_reference():
        inside = PointCloud2Converter(info)
        cloud = to_pointcloud2(scan, info)
    assert inside._kfn is None
    assert bytes(cloud.data) == bytes(reference.data)
    outside = PointCloud2Converter(info)
    assert (outside._kfn is not None) == kernel_available()
    if kernel_available():
        with numpy_reference():                       # an explicit choice wins inside too
            assert PointCloud2Converter(info, kernel=True)._kfn is not None
