"""No compiler on a node's start (converters.warmup): the warm-up loads numba's kernels from its
cache only, and with a kernel missing it selects ``backend="c"`` (the C kernels built at
install, numpy elsewhere), which gives the same slices; ``describe`` says what runs.

The cache checks run in a fresh interpreter with an empty ``NUMBA_CACHE_DIR`` (a kernel loaded
by an earlier test in this process would hide the missing cache).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from converters import _kernels
from lidarscan.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]


def test_backend_c_never_selects_numba() -> None:
    assert _kernels.select("slices", backend="c").numba is None
    assert _kernels.select("merger", backend="c") == _kernels.Backends()
    assert _kernels.select("cloud_slices", backend="c").c == \
        _kernels.select("cloud_slices").c
    with pytest.raises(ConfigError, match="'c'"):
        _kernels.select("slices", backend="C")


def test_backend_c_slices_equal_the_numpy_reference() -> None:
    from converters import warmup
    from converters.slices.converter import SliceConverter

    info = warmup.probe_info(32, 1024)
    scan = warmup.probe_scan(info)
    slices = {"low": {"min_height": -0.5, "max_height": 0.2},
              "wide": {"min_height": -0.2, "max_height": 1.0, "angle_increment": 0.01}}
    c, s = np.cos(0.3), np.sin(0.3)
    tilted = np.array([[c, 0.0, s, 0.0], [0.0, 1.0, 0.0, 0.0], [-s, 0.0, c, 0.4],
                       [0.0, 0.0, 0.0, 1.0]])
    for extrinsics in (None, tilted):
        frame = "base" if extrinsics is not None else None
        got = SliceConverter(info, slices, extrinsics=extrinsics, frame_id=frame,
                             backend="c").convert(scan)
        ref = SliceConverter(info, slices, extrinsics=extrinsics, frame_id=frame,
                             backend="numpy").convert(scan)
        for name in slices:
            np.testing.assert_array_equal(np.asarray(got[name].ranges),
                                          np.asarray(ref[name].ranges))


def test_describe_names_what_runs() -> None:
    from converters.warmup import describe

    runs = describe(("cloud", "slices", "merger", "cloud_slices"), "c")
    assert runs["merger"] == "numpy" and "numba" not in runs["slices"]
    assert runs["cloud"] in ("C", "numpy") and runs["cloud_slices"] in ("C", "numpy")
    if _kernels.select("slices", backend="c").c:
        assert runs["slices"].startswith("C ") and runs["slices"].endswith(
            "numpy (other cases)")
    else:
        assert runs["slices"] == "numpy"


def _run(code: str, cache: Path) -> dict[str, Any]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("_ROS_WHEELS")}
    env["NUMBA_CACHE_DIR"] = str(cache)
    proc = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=600, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])  # type: ignore[no-any-return]


def test_an_empty_cache_compiles_nothing_and_selects_backend_c(tmp_path: Path) -> None:
    pytest.importorskip("numba")
    if not _kernels.numba_enabled():
        pytest.skip("numba switched off (LIDARSCAN_NUMBA=0)")
    got = _run("""
        import json
        from converters import warmup
        slices = {"a": {"min_height": -0.5, "max_height": 0.5}}
        try:
            warmup.warm(("slices",), slices=slices, moving=False, compile=False)
            refused = ""
        except warmup.NotCached as err:
            refused = str(err)
        prepared = warmup.prepare(("cloud", "slices"), slices=slices, moving=False,
                                  background=False)
        print(json.dumps({"refused": refused, "backend": prepared.backend,
                          "missing": prepared.missing, "runs": prepared.runs,
                          "compiled": warmup.specialisations(),
                          "summary": prepared.summary()}))
    """, tmp_path)
    assert "numba's cache has no" in got["refused"]
    assert got["backend"] == "c" and got["missing"] and "numba" not in got["runs"]["slices"]
    assert sum(got["compiled"].values()) == 0            # nothing was compiled
    assert "numba not used" in got["summary"]
    # once the cache holds this configuration (what the background fill does), the same
    # start loads numba from it
    subprocess.run([sys.executable, "-m", "converters.warmup", "--config", json.dumps(
        {"tasks": ["cloud", "slices"], "moving": False,
         "slices": {"a": {"min_height": -0.5, "max_height": 0.5}}})], cwd=ROOT,
        env={**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}, check=True,
        capture_output=True, timeout=600)
    again = _run("""
        import json
        from converters import warmup
        prepared = warmup.prepare(("cloud", "slices"), moving=False, background=False,
                                  slices={"a": {"min_height": -0.5, "max_height": 0.5}})
        print(json.dumps({"backend": prepared.backend, "missing": prepared.missing,
                          "runs": prepared.runs}))
    """, tmp_path)
    assert again["backend"] == "auto" and not again["missing"], again
    assert "numba" in again["runs"]["slices"]
