"""The golden-digest and oracle tests of the compiled paths, again on the portable paths.

Which code runs is chosen at run time: numba or numpy (``LIDARSCAN_NUMBA``), the C kernels or
numpy (``LIDARSCAN_NO_KERNEL``), the C kernels' AVX-512 / AVX2 paths or their scalar code (the
CPU), numpy's own SIMD loops (the CPU). The rest of the suite runs what this machine takes
(and, in-process, the kernels' scalar paths: ``SIMD = 0``), so a figure that holds only on
one kind of machine would pass here and fail on another. Each case below re-runs the tests
that pin bytes (golden digests of real recordings, the codec's golden bytes, bit-exact kernel
oracles) in a subprocess with the switches of :mod:`converters._kernels` set, as another
machine would run them:

* ``no-numba``: ``LIDARSCAN_NUMBA=0``, what a plain ``pip install`` without the ``fast`` extra
  runs (the C kernels where built, numpy elsewhere), with the PointCloud2 kernel's portable
  code (``LIDARSCAN_CLOUD_SIMD=0``: what a CPU without AVX-512 runs);
* ``baseline-cpu``: no numba, no C kernel (``LIDARSCAN_NO_KERNEL=1``), the Velodyne kernel's
  portable path (``LIDARSCAN_VELODYNE_SIMD=0``) and numpy without its run-time SIMD targets
  (``NPY_DISABLE_CPU_FEATURES``: the code numpy runs on a CPU without AVX2 / AVX-512).

The document's deterministic evidence (``python -m converters.edge.evidence --check``) is checked
on the baseline paths too: its figures must not depend on the machine either.

A failure prints the subprocess's failures; run the same command to reproduce it.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

#: the tests that pin bytes across backends (about 2 minutes per case without numba)
FILES = [
    "tests/test_velodyne_golden.py",      # golden digests of real Velodyne recordings
    "tests/test_velokernel.py",           # the Velodyne kernel against numpy
    "tests/test_hesai_golden.py",         # golden digests of real Hesai recordings
    "tests/test_codec.py",                # the codec's golden bytes (residual coder)
    "tests/test_codec_v3.py",
    "tests/test_pointcloud2_kernel.py",   # the PointCloud2 kernel against its float32 oracle
    "tests/test_slicekernel.py",          # the slicing kernel against numpy and the loop oracle
    "tests/test_merger.py",               # the merger against its loop oracle
    "tests/test_laserscan.py",            # slices against the loop oracle, bit for bit
    "tests/test_holes.py",
]
#: and, where nothing is compiled, the numpy paths that have a C kernel elsewhere
BASELINE_FILES = ["tests/test_cloud_slices.py", "tests/test_pointcloud2.py"]


def _numpy_dispatch_targets() -> str:
    """numpy's run-time SIMD targets on this build (disabled together: its baseline code)."""
    try:
        from numpy._core._multiarray_umath import __cpu_dispatch__
    except ImportError:                                     # numpy < 2
        from numpy.core._multiarray_umath import __cpu_dispatch__
    return " ".join(__cpu_dispatch__)


CASES = {
    "no-numba": {"LIDARSCAN_NUMBA": "0", "LIDARSCAN_CLOUD_SIMD": "0"},
    "baseline-cpu": {"LIDARSCAN_NUMBA": "0", "LIDARSCAN_NO_KERNEL": "1",
                     "LIDARSCAN_VELODYNE_SIMD": "0",
                     "NPY_DISABLE_CPU_FEATURES": _numpy_dispatch_targets()},
}


def _env(case: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items()
           if not k.startswith("LIDARSCAN_") and k != "NPY_DISABLE_CPU_FEATURES"}
    env.update(CASES[case])
    return env


@pytest.mark.slow
@pytest.mark.parametrize("case", sorted(CASES))
def test_byte_pinning_tests_pass_on_the_portable_paths(case: str) -> None:
    env = _env(case)
    command = [sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider",
               "-p", "no:randomly", *FILES, *(BASELINE_FILES if case == "baseline-cpu" else [])]
    done = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=1800, check=False)
    switches = " ".join(f"{k}={v!r}" for k, v in CASES[case].items())
    assert done.returncode == 0, (f"{switches} {' '.join(command[2:])} failed:\n"
                                  + done.stdout[-6000:] + done.stderr[-2000:])
    assert " passed" in done.stdout.splitlines()[-1], done.stdout[-2000:]


@pytest.mark.slow
def test_the_evidence_document_holds_on_the_baseline_paths() -> None:
    command = [sys.executable, "-m", "converters.edge.evidence", "--check"]
    done = subprocess.run(command, cwd=ROOT, env=_env("baseline-cpu"), capture_output=True,
                          text=True, timeout=1800, check=False)
    assert done.returncode == 0, done.stdout[-4000:] + done.stderr[-2000:]
    assert "document up to date" in done.stdout
