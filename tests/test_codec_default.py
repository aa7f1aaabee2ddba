"""lidarscan.codec's coder choice (issue 28): without a coder argument the compiled coder runs
when numba is installed and not switched off, the numpy reference otherwise; the reference stays
selectable; every choice writes the same bytes; importing the core never imports numba."""

from __future__ import annotations

import subprocess
import sys
from typing import Any

import numpy as np
import pytest

import lidarscan as ls
from lidarscan import codec
from lidarscan.errors import ConfigError
from lidarscan.mcap import CODEC_ENCODING, McapWriter, read_messages


def _numba_installed() -> bool:
    try:
        import numba  # noqa: F401
    except ImportError:
        return False
    return True


def _scan() -> tuple[Any, Any]:
    """A small scan with float metres, integer and staggered channels (every v2/v3 method)."""
    rng = np.random.default_rng(7)
    h, w = 16, 64
    info = ls.make_info(stamp_ns=1, frame_id="s", vertical_angles=np.linspace(0.2, -0.2, h),
                        horizontal_angles=2 * np.pi * (1 - np.arange(w) / w),
                        pixel_shift_by_row=np.tile([0, 3, 6, 9], h // 4), as_dataclass=True)
    rng_m = np.round(rng.uniform(0.5, 40.0, (h, w)), 3).astype(np.float32)
    rng_m[::5, ::7] = np.inf
    signal = rng.integers(0, 3000, (h, w)).astype(np.uint16)
    refl = np.minimum(signal // 12, 255).astype(np.uint8)
    scan = ls.make_scan(info, {"range": rng_m, "signal": signal, "reflectivity": refl}, 2,
                        as_dataclass=True)
    return scan, info


def test_without_numba_or_switched_off_the_default_is_the_reference(monkeypatch: Any) -> None:
    monkeypatch.setenv("LIDARSCAN_NUMBA", "0")
    assert codec.residual_coder() is codec.NUMPY
    assert codec.residual_coder("auto") is codec.NUMPY
    with pytest.raises(ConfigError, match="numba"):
        codec.residual_coder("numba")
    scan, info = _scan()
    assert codec.compress_scan(scan, info) == codec.compress_scan(scan, info, coder="numpy")


def test_the_reference_stays_selectable_and_bad_choices_are_errors() -> None:
    assert codec.residual_coder(None) is codec.NUMPY
    assert codec.residual_coder("numpy") is codec.NUMPY
    assert codec.residual_coder(codec.NUMPY) is codec.NUMPY
    for bad in ("fast", "NUMBA", 3):
        with pytest.raises(ConfigError, match="coder"):
            codec.residual_coder(bad)  # type: ignore[arg-type]
    scan, _ = _scan()
    with pytest.raises(ConfigError, match="coder"):
        codec.compress_scan(scan, coder="fast")
    with pytest.raises(ConfigError, match="coder"):
        codec.decompress_scan(codec.compress_scan(scan), coder="fast")


@pytest.mark.skipif(not _numba_installed(), reason="numba is not installed")
def test_with_numba_the_default_is_the_compiled_coder_and_writes_the_reference_bytes(
        monkeypatch: Any) -> None:
    monkeypatch.delenv("LIDARSCAN_NUMBA", raising=False)
    default = codec.residual_coder()
    assert default is not codec.NUMPY and default.name == "numba"
    assert codec.residual_coder("numba") is default
    assert default.xfit is not None and default.xpredict is not None  # version 3's kernels
    from converters._kernels import select
    assert select("codec").numba is default  # the converters' seam hands out the same coder
    scan, info = _scan()
    for version in (2, 3):
        ref = codec.compress_scan(scan, info, coder=None, version=version)
        assert codec.compress_scan(scan, info, version=version) == ref
        for coder in ("auto", "numpy", None, "numba"):
            back = codec.decompress_scan(ref, coder=coder)
            assert back.data.tobytes() == scan.data.tobytes()


def test_mcap_writer_and_reader_default_to_the_default_coder(tmp_path: Any) -> None:
    scan, info = _scan()
    paths = {}
    for name, given in (("auto", {}), ("numpy", {"codec_coder": "numpy"})):
        paths[name] = tmp_path / f"{name}.mcap"
        with McapWriter(paths[name], scan_encoding=CODEC_ENCODING, **given) as writer:
            writer.write("/info", info)
            writer.write("/scan", scan)
    payloads = {name: [m.payload for m in read_messages(path) if m.topic == "/scan"]
                for name, path in paths.items()}
    assert payloads["auto"] == payloads["numpy"]
    (record,) = [m for m in read_messages(paths["auto"]) if m.topic == "/scan"]
    assert ls.encode(record.decode()) == ls.encode(scan)


def test_importing_the_core_and_the_codec_does_not_import_numba() -> None:
    code = ("import sys, lidarscan, lidarscan.codec, lidarscan.mcap, lidarscan.rosbag2; "
            "assert 'numba' not in sys.modules, 'numba imported'; print('ok')")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120, check=False)
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr
