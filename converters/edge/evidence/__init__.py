"""The standardisation evidence: every number and plot of ``docs/proposal.md``, regenerated.

``python -m converters.edge.evidence`` (``make evidence``) measures everything, writes the plots to
``docs/img/`` and rewrites ``docs/proposal.md`` between its markers
``<!-- evidence:NAME:begin -->`` / ``<!-- evidence:NAME:end -->``; it prints the machine it ran
on. ``--check`` computes only the deterministic blocks (sizes, errors, counts: seconds, no rclpy)
and reports where the document differs; :func:`check` is what ``tests/test_evidence.py`` calls.

The deterministic blocks write their PointCloud2s with the numpy reference path
(:func:`reference_backends`), so they are the same whether or not the C kernels were built: the
C PointCloud2 kernel evaluates the beam model a few float32 ulps away from numpy, which changes
compressed cloud sizes and bin-by-bin comparisons (the slice, merger and decoder backends give
identical bytes). Timings measure the fastest enabled backend.

One module per question:

=====================  =====================================================================
module                 answers
=====================  =====================================================================
``sizes``              1: bytes per frame and MB/s, LidarScan vs PointCloud2 layouts
``compression``        1, 3: lossless compression of real channel blocks; range encodings
``codec_study``        1: compressed vs compressed: driver's cloud (zstd, Draco) vs LidarScan
                       (zstd, lidarscan.codec, PNG, JPEG-XL), the goals per real sensor
``images``             2: one sensor_msgs/Image per channel vs one LidarScan; synchronisers
``range_error``        3: float32 metres vs integer units, worst round-trip error
``units``              3: uint32 mm vs float32 m on the real frames: bytes, precision, cost
``geometry``           4: cost of omitting a geometry field, on real metadata
``sensors``            4b: real Ouster, Velodyne, Hesai data vs the vendor's / Nebula's points
``transport``          2: CPU per frame through real rclpy; receiver-side conversions
``linkage``            5: the info link, scenario counts, resolver vs "latest info wins"
``slicing``            6: slices from the scan vs from a point cloud; merger vs per-point
``summary``            the headline numbers, from the modules above
``decision``           the decision record: each open question's answer and its number
=====================  =====================================================================
"""

from __future__ import annotations

import contextlib
import re
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

from converters.edge.evidence._common import DOC, IMG, Block, machine_lines, pending

__all__ = ["DOC", "Block", "check", "generate", "main", "read_blocks", "reference_backends",
           "render"]

_MARKER = re.compile(r"<!-- evidence:([a-z0-9-]+):begin -->\n(.*?)\n?<!-- evidence:\1:end -->",
                     re.DOTALL)


def _deterministic_sections() -> list[tuple[str, Callable[[], list[Block]]]]:
    from converters.edge.evidence import (
        codec_study,
        compression,
        decision,
        geometry,
        images,
        linkage,
        range_error,
        sensors,
        sizes,
        slicing,
        summary,
        units,
    )
    return [
        ("sizes", sizes.blocks),
        ("compression", lambda: compression.blocks(timing=False)),
        ("codec study", lambda: codec_study.blocks(timing=False)),
        ("images", lambda: images.blocks(timing=False)),
        ("range_error", range_error.blocks),
        ("units", lambda: units.blocks(timing=False)),
        ("geometry", geometry.blocks),
        ("sensors", sensors.blocks),
        ("linkage", linkage.blocks),
        ("slicing", lambda: slicing.blocks(timing=False)),
        ("summary", summary.blocks),
        ("decision", decision.blocks),
    ]


#: blocks each section writes (used for the placeholders when a section fails)
_SECTION_BLOCKS = {
    "sizes": ("sizes", "rates"), "compression": ("compression", "range-encoding"),
    "range_error": ("range-error",), "geometry": ("geometry",),
    "sensors": ("sensors-error", "sensors-claims", "sensors-fields", "sensors-size"), "linkage": ("linkage",),
    "slicing": ("slicing", "merger"), "summary": ("headline", "headline-compression"),
    "decision": ("decision-msgs", "decision-answers", "decision-compression", "decision-rejected"),
    "compression timing": ("timing-compression",),
    "codec study": ("codec-study", "codec-goals"), "codec timing": ("timing-codec",),
    "images": ("images-sizes", "images-sync"), "images timing": ("timing-images",),
    "units": ("int-vs-float",), "units timing": ("timing-int-vs-float",),
    "transport": ("timing-transport", "timing-receiver"), "slicing timing": ("timing-slicing",),
}

#: cached evidence function -> its cache misses when :func:`reference_backends` last exited
_REFERENCE_MISSES: dict[str, int] = {}


def _evidence_caches() -> dict[str, Any]:
    """Every ``lru_cache`` function of the loaded ``converters.edge.evidence`` modules."""
    out = {}
    for name, module in list(sys.modules.items()):
        if module is None or not name.startswith(__name__ + "."):
            continue
        for attr, value in vars(module).items():
            if callable(getattr(value, "cache_info", None)) and \
                    getattr(value, "__module__", None) == name:
                out[f"{name}.{attr}"] = value
    return out


@contextlib.contextmanager
def reference_backends() -> Iterator[None]:
    """Inside: PointCloud2s are written by the numpy reference path, whatever is compiled
    (:func:`converters.pointcloud2.converter.numpy_reference`).

    Evidence caches that computed anything outside this context since it last ran (e.g. a test
    calling a measurement directly, with the kernel) are cleared first, so no value computed
    with another backend leaks into a deterministic block.
    """
    from converters.pointcloud2.converter import numpy_reference

    for key, fn in _evidence_caches().items():
        if fn.cache_info().misses != _REFERENCE_MISSES.get(key, 0):
            fn.cache_clear()
    try:
        with numpy_reference():
            yield
    finally:
        _REFERENCE_MISSES.clear()
        _REFERENCE_MISSES.update({key: fn.cache_info().misses
                                  for key, fn in _evidence_caches().items()})


#: sections that raised in the last :func:`generate` (name -> one-line error)
FAILED: dict[str, str] = {}


def _run(name: str, fn: Callable[[], list[Block]], deterministic: bool,
         say: Callable[[str], None]) -> list[Block]:
    """One section; an exception (e.g. a converter being rewritten) becomes placeholders."""
    start = time.perf_counter()
    try:
        blocks = fn()
    except Exception as err:  # noqa: BLE001 - reported loudly, the run goes on
        import traceback
        traceback.print_exc(file=sys.stderr)
        reason = f"the measurement raised {type(err).__name__}: {err}"
        FAILED[name] = reason
        say(f"{name}: FAILED ({reason})")
        return [pending(block, f"block `{block}`", reason, deterministic)
                for block in _SECTION_BLOCKS[name]]
    say(f"{name}: {time.perf_counter() - start:.1f} s")
    return blocks


def generate(fast: bool = False, log: Callable[[str], None] | None = None,
             sections: Sequence[str] | None = None) -> list[Block]:
    """Every block of the document.

    A section that raises is reported on stderr, listed in :data:`FAILED` and replaced by
    "not yet measured" placeholders (so the check fails until it works again).

    Args:
        fast: deterministic blocks only (no timings, no rclpy, no plots).
        log: called with one progress line per section.
        sections: with ``fast``, only these deterministic sections (names as in the progress
            lines, e.g. ``["slicing"]``); None = all.

    Returns:
        The blocks in document order of generation (names are unique).
    """
    say = log or (lambda line: None)
    FAILED.clear()
    out: list[Block] = []
    chosen = _deterministic_sections()
    if sections is not None:
        unknown = set(sections) - {name for name, _ in chosen}
        if unknown or not fast:
            raise ValueError(f"sections={list(sections)}: only with fast=True, names from "
                             f"{[name for name, _ in chosen]}")
        chosen = [(name, fn) for name, fn in chosen if name in sections]
    with reference_backends():
        for name, fn in chosen:
            out += _run(name, fn, True, say)
    if fast:
        return out
    from converters.edge.evidence import codec_study, compression, images, slicing, transport, units
    for name, fn in (("compression timing", lambda: [b for b in compression.blocks(timing=True)
                                                     if not b.deterministic]),
                     ("codec timing", lambda: [b for b in codec_study.blocks(timing=True)
                                               if not b.deterministic]),
                     ("images timing", lambda: [b for b in images.blocks(timing=True)
                                                if not b.deterministic]),
                     ("units timing", lambda: [b for b in units.blocks(timing=True)
                                               if not b.deterministic]),
                     ("transport", transport.blocks),
                     ("slicing timing", lambda: [b for b in slicing.blocks(timing=True)
                                                 if not b.deterministic])):
        out += _run(name, fn, False, say)
    out.append(Block("machine", "Measured on: " + "; ".join(machine_lines()) + ".",
                     deterministic=False))
    return out


def plots(log: Callable[[str], None] | None = None) -> list[Path]:
    """Write every PNG of the document into ``docs/img/``."""
    from converters.edge.evidence import geometry, range_error, sizes
    say = log or (lambda line: None)
    IMG.mkdir(parents=True, exist_ok=True)
    paths = [sizes.plot(sizes.measure()), range_error.plot(), geometry.plot()]
    for path in paths:
        say(f"wrote {Path(path).relative_to(DOC.parent.parent)}")
    return paths


def read_blocks(text: str) -> dict[str, str]:
    """NAME -> text between the NAME markers of a document."""
    return {m.group(1): m.group(2).strip("\n") for m in _MARKER.finditer(text)}


def render(text: str, blocks: list[Block]) -> str:
    """The document with every generated block written between its markers.

    Raises:
        KeyError: a block has no markers in the document (add them where it belongs).
    """
    present = set(read_blocks(text))
    missing = [b.name for b in blocks if b.name not in present]
    if missing:
        raise KeyError(f"docs/proposal.md has no markers for {missing}: add "
                       "'<!-- evidence:NAME:begin -->' / '<!-- evidence:NAME:end -->' lines")
    by_name = {b.name: b for b in blocks}

    def replace(match: re.Match[str]) -> str:
        block = by_name.get(match.group(1))
        if block is None:
            return match.group(0)
        return (f"<!-- evidence:{block.name}:begin -->\n{block.text.strip()}\n"
                f"<!-- evidence:{block.name}:end -->")

    return _MARKER.sub(replace, text)


def check(doc: Path = DOC, blocks: list[Block] | None = None) -> list[str]:
    """Differences between the document's deterministic blocks and what the script writes.

    Blocks whose numbers depend on library versions (compression) carry those versions in their
    text; when the installed versions differ from the document's, the block is reported as
    skipped (prefix "skipped:") rather than as a difference.

    Returns:
        One line per difference (empty: the document is up to date).
    """
    blocks = generate(fast=True) if blocks is None else blocks
    have = read_blocks(doc.read_text(encoding="utf-8"))
    problems = []
    for block in blocks:
        if not block.deterministic:
            continue
        if block.name not in have:
            problems.append(f"{block.name}: no markers in {doc.name}")
            continue
        if have[block.name].strip() != block.text.strip():
            first_doc = have[block.name].strip().split("\n", 1)[0]
            first_new = block.text.strip().split("\n", 1)[0]
            if "zstandard" in first_new and first_doc != first_new:
                problems.append(f"skipped: {block.name} (library versions differ: "
                                f"{first_new!r})")
                continue
            problems.append(f"{block.name}: the document differs from the script's output "
                            "(run `make evidence`)")
    return problems


def main(argv: list[str] | None = None) -> int:
    """Command line: regenerate everything (default) or ``--check`` the document."""
    import argparse
    parser = argparse.ArgumentParser(prog="python -m converters.edge.evidence",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true",
                        help="compute the deterministic tables only and compare with the document")
    parser.add_argument("--no-plots", action="store_true", help="do not rewrite docs/img/*.png")
    parser.add_argument("--doc", type=Path, default=DOC, help="document to update")
    args = parser.parse_args(argv)

    def log(line: str) -> None:
        print(f"  {line}", flush=True)

    print("machine:")
    for line in machine_lines():
        print(f"  {line}")
    start = time.perf_counter()
    if args.check:
        problems = check(args.doc, generate(fast=True, log=log))
        for line in problems:
            print(line)
        real = [p for p in problems if not p.startswith("skipped:")]
        print("document up to date" if not real else f"{len(real)} block(s) out of date")
        return 1 if real else 0
    blocks = generate(fast=False, log=log)
    if not args.no_plots:
        plots(log)
    text = args.doc.read_text(encoding="utf-8")
    args.doc.write_text(render(text, blocks), encoding="utf-8")
    placeholders = [b.name for b in blocks if b.placeholder]
    print(f"wrote {len(blocks)} blocks into {args.doc} in {time.perf_counter() - start:.0f} s")
    if placeholders:
        print("NOT YET MEASURED (placeholders): " + ", ".join(placeholders))
    return 1 if FAILED else 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
