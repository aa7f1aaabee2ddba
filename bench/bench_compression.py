"""Benchmark: lidarscan.codec against zstd of the raw LidarScan buffer, measured in one run.

Scan: 128 x 2048 from the real OS-2-128 frame (tests/data/ouster, 128 x 1024: tiled twice
horizontally, the second copy mirrored left-right so that no byte sequence repeats for zstd to
find), five canonical channels (range float32 m, intensity, reflectivity, ambient,
flags), staggered as published; the codec gets the info (destaggered prediction).

Baselines, same run, one thread: zstd-3 and zstd-1 of the whole ``data`` buffer (what MCAP's
chunk compression does) and lz4. The codec runs its default format version
(``lidarscan.codec.VERSION``) called as a user calls it, ``compress_scan(scan, info)`` /
``decompress_scan(buf)`` with no coder argument (``coder="auto"``: the compiled coder,
:mod:`lidarscan.codec._compiled`, numba with the compiled fit and prediction of version 3, when
numba is installed; the coder it chose is printed), and with the numpy reference
(``coder="numpy"``; both must write the same bytes), and the other version it writes with
the compiled coder (version 2 when 3 is the default); the ratios of version 3's encode /
decode time to version 2's in the same run are printed. Printed:
bytes and ratio to zstd-3's bytes; median encode / decode CPU milliseconds
(``time.process_time`` of interleaved rounds, so the load of a shared machine costs less),
ratio to zstd-3's time, frames per second; and the load average. Targets (issue): encode and
decode >= 50 Hz on one core at 128 x 2048 (the default version, called without a coder
argument); bytes below zstd-3's. Exits 1 when one is missed.

``--baseline FILE``: also time another revision, FILE being a copy of its compiled coder
``lidarscan/codec/_compiled.py`` (``converters/_kernels/codec.py`` before the codec moved into
the core: its imports are redirected), e.g. ``git show main:lidarscan/codec/_compiled.py >
/tmp/main_codec.py``, interleaved with the others, writing its default version; the ratios of
the encode / decode time of this revision's run of that version to it are printed, and
whether the bytes are the same (the before/after of a change, measured in one run).
``--baseline-core FILE``: with ``--baseline``, the baseline also runs that revision's
container (encoder's choices and decoder), FILE being a copy of its
``lidarscan/codec/__init__.py`` (the primitives and versions are this revision's);
``--baseline-v3 FILE``: with ``--baseline-core``, its ``lidarscan/codec/_v3.py`` too (the
container's imports of ``lidarscan.codec._v3`` then load it). ``--baseline-version N [N
...]``: the format versions the baseline writes, each a candidate of its own (default: its
own default).

Usage: ``.venv/bin/python bench/bench_compression.py [--rounds N] [--baseline FILE
[--baseline-core FILE [--baseline-v3 FILE]] [--baseline-version N [N ...]]]``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
import sys
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _timing import interleaved_times  # noqa: E402

import lidarscan as ls  # noqa: E402
from lidarscan import codec  # noqa: E402


def make_scan() -> tuple[Any, Any]:
    """(128 x 2048 LidarScan dataclass, an info-like object with its row shifts)."""
    from converters.edge.evidence._common import load_frame, ouster_files, ouster_info
    from converters.sources.ouster.metadata import scan_from_frame
    meta, path = next((m, p) for m, p in ouster_files() if p is not None and "128" in m.name)
    info = ouster_info(meta)
    scan = scan_from_frame(load_frame(path), info, as_dataclass=True)
    chans = {c.name: np.hstack([ls.channel(scan, c.name), ls.channel(scan, c.name)[:, ::-1]])
             for c in scan.channels}
    height, width = next(iter(chans.values())).shape
    wide = ls.make_info(stamp_ns=1_000_000_000, frame_id="os_sensor",
                        vertical_angles=info.vertical_angles,
                        horizontal_angles=2 * np.pi * (1 - np.arange(width) / width),
                        pixel_shift_by_row=np.asarray(info.pixel_shift_by_row) * 2,
                        as_dataclass=True)
    out = ls.make_scan(wide, chans, 1_000_000_000,
                       column_time_offsets=np.arange(width, dtype=np.int64) * 48_828,
                       as_dataclass=True)
    return out, SimpleNamespace(pixel_shift_by_row=np.asarray(info.pixel_shift_by_row) * 2)


#: imports of a compiled coder copied from a revision before the codec moved into the core
_OLD_LAYOUT = {"from converters._kernels._loader import": "from lidarscan._backends import",
               "from lidarscan._codec_bits import": "from lidarscan.codec._bits import",
               "from converters._kernels import codec3":
                   "from lidarscan.codec import _compiled_v3 as codec3"}


def _load_module(name: str, path: Path, renames: dict[str, str] | None = None) -> Any:
    """The Python file ``path`` imported as module ``name`` (another revision's copy), with
    the import statements of ``renames`` (old text -> new text) rewritten."""
    import importlib.util
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # numba's on-disk cache finds the module by name
    source = path.read_text(encoding="utf-8")
    for old, new in (renames or {}).items():
        source = source.replace(old, new)
    exec(compile(source, str(path), "exec"), module.__dict__)  # noqa: S102 - a revision's file
    return module


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=15, help="timed rounds")
    parser.add_argument("--baseline", type=Path, default=None,
                        help="a copy of another revision's lidarscan/codec/_compiled.py")
    parser.add_argument("--baseline-core", type=Path, default=None,
                        help="with --baseline: a copy of its lidarscan/codec/__init__.py")
    parser.add_argument("--baseline-v3", type=Path, default=None,
                        help="with --baseline-core: a copy of its lidarscan/codec/_v3.py")
    parser.add_argument("--baseline-version", type=int, nargs="+", default=[None],
                        help="the format version(s) the baseline writes (default: its default)")
    args = parser.parse_args(argv)

    import lz4.frame
    import zstandard

    compiled = codec.residual_coder("auto")
    compiled = None if compiled is codec.NUMPY else compiled
    scan, info = make_scan()
    raw = scan.data.tobytes()
    z3, z1 = zstandard.ZstdCompressor(level=3), zstandard.ZstdCompressor(level=1)
    dz = zstandard.ZstdDecompressor()
    default = codec.VERSION
    other = 2 if default == 3 else 3
    # name -> (codec module, coder (None: no coder argument, the default of compress_scan /
    # decompress_scan), version written (None: the module's default))
    runs: dict[str, tuple[Any, Any | None, int | None]] = {}
    runs["lidarscan.codec"] = (codec, None, None)
    runs["codec (numpy)"] = (codec, "numpy", default)
    if compiled is not None:
        runs[f"codec v{other}"] = (codec, compiled, other)
    if args.baseline is not None and compiled is not None:
        core = codec
        if args.baseline_core is not None:
            renames = {}
            if args.baseline_v3 is not None:
                _load_module("baseline_v3", args.baseline_v3)
                renames = {"from lidarscan.codec import _v3": "import baseline_v3 as _v3"}
            core = _load_module("baseline_core", args.baseline_core, renames)
        base_coder = _load_module("baseline_codec", args.baseline, _OLD_LAYOUT).coder()
        for version in args.baseline_version:
            name = "codec (baseline)" if version is None else f"codec (baseline v{version})"
            runs[name] = (core, base_coder, version)
    packed = {"zstd-3 (buffer)": z3.compress(raw), "zstd-1 (buffer)": z1.compress(raw),
              "lz4 (buffer)": lz4.frame.compress(raw)}
    enc = {"zstd-3 (buffer)": lambda: z3.compress(raw), "zstd-1 (buffer)": lambda: z1.compress(raw),
           "lz4 (buffer)": lambda: lz4.frame.compress(raw)}
    dec = {"zstd-3 (buffer)": lambda: dz.decompress(packed["zstd-3 (buffer)"]),
           "zstd-1 (buffer)": lambda: dz.decompress(packed["zstd-1 (buffer)"]),
           "lz4 (buffer)": lambda: lz4.frame.decompress(packed["lz4 (buffer)"])}
    for name, (core, coder, version) in runs.items():
        options = {} if version is None else {"version": version}
        given = {} if coder is None else {"coder": coder}
        packed[name] = core.compress_scan(scan, info, **given, **options)
        back = core.decompress_scan(packed[name], **given)
        assert ls.encode(back) == ls.encode(scan), name
        enc[name] = lambda g=given, m=core, o=options: m.compress_scan(scan, info, **g, **o)
        dec[name] = lambda n=name, g=given, m=core: m.decompress_scan(packed[n], **g)
    by_version: dict[int, bytes] = {}
    for name in runs:  # every coder of this revision writes the same bytes of a version
        if not name.startswith("codec (baseline"):
            assert by_version.setdefault(packed[name][4], packed[name]) == packed[name], name
    load = os.getloadavg()[0]
    cpu = time.process_time
    te = {k: statistics.median(v) for k, v in interleaved_times(enc, args.rounds, 0, cpu).items()}
    td = {k: statistics.median(v) for k, v in interleaved_times(dec, args.rounds, 1, cpu).items()}
    base_b, base_e, base_d = (len(packed["zstd-3 (buffer)"]), te["zstd-3 (buffer)"],
                              td["zstd-3 (buffer)"])
    print(f"LidarScan {scan.height}x{scan.width}, {len(scan.channels)} channels, "
          f"{len(raw) / 1e6:.2f} MB raw; CPU-time medians of {args.rounds} interleaved rounds; "
          f"load average {load:.1f} -> {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores; "
          f"lidarscan.codec without a coder argument runs the {codec.residual_coder().name} "
          f"coder")
    print(f"  {'coding':<21s} {'bytes':>10s} {'÷zstd-3':>8s} {'enc ms':>8s} {'÷zstd-3':>8s} "
          f"{'dec ms':>8s} {'÷zstd-3':>8s} {'enc Hz':>7s} {'dec Hz':>7s}")
    for name in packed:
        size = len(packed[name])
        print(f"  {name:<21s} {size:>10d} {size / base_b:>8.3f} {te[name] * 1e3:>8.2f} "
              f"{te[name] / base_e:>8.2f} {td[name] * 1e3:>8.2f} {td[name] / base_d:>8.2f} "
              f"{1 / te[name]:>7.0f} {1 / td[name]:>7.0f}")
    ours = next(iter(runs))
    if f"codec v{other}" in runs:
        v3, v2 = (ours, f"codec v{other}") if default == 3 else (f"codec v{other}", ours)
        print(f"  format version 3 / version 2 (compiled, same run): encode "
              f"{te[v3] / te[v2]:.3f}x, decode {td[v3] / td[v2]:.3f}x")
    for base in [n for n in runs if n.startswith("codec (baseline")]:
        same = next(n for n in runs if not n.startswith("codec (baseline")
                    and packed[n][4] == packed[base][4])
        print(f"  {same} / {base} (version {packed[base][4]}): encode "
              f"{te[same] / te[base]:.3f}x, decode {td[same] / td[base]:.3f}x; "
              f"{'the same bytes' if packed[same] == packed[base] else 'other bytes'}")
    checks = [("bytes below zstd-3 of the buffer", len(packed[ours]) < base_b),
              ("encode >= 50 Hz", 1 / te[ours] >= 50), ("decode >= 50 Hz", 1 / td[ours] >= 50)]
    for label, ok in checks:
        print(f"{label:<34s} {'OK' if ok else 'MISSED'}")
    return 0 if all(ok for _, ok in checks) else 1


if __name__ == "__main__":
    sys.exit(main())
