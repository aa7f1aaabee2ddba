"""Small helpers shared by several test modules (imported as ``from helpers import ...``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from lidarscan.mcap import BadMessage, read_messages


def numba_usable() -> bool:
    """Whether the numba kernels can run here: numba installed and not switched off
    (``LIDARSCAN_NUMBA=0``, :func:`converters._kernels.numba_enabled`); tests that need
    ``backend="numba"`` skip otherwise."""
    import importlib.util

    from converters._kernels import numba_enabled
    return importlib.util.find_spec("numba") is not None and numba_enabled()


def cpu_has(*features: str) -> bool:
    """Whether this CPU (and its OS) has every one of ``features`` ("AVX2", "AVX512F", ...):
    the kernel's flags in ``/proc/cpuinfo``, else numpy's run-time detection. An independent
    check of which path a compiled kernel reports it takes (it asks the CPU itself)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        text = ""
    line = next((x for x in text.splitlines() if x.startswith("flags")), None)
    if line is not None:
        flags = set(line.split(":", 1)[1].split())
        return all(f.lower() in flags for f in features)
    try:
        from numpy._core._multiarray_umath import __cpu_features__
    except ImportError:                                     # numpy < 2
        from numpy.core._multiarray_umath import __cpu_features__
    return all(bool(__cpu_features__.get(f)) for f in features)


#: the AVX-512 subsets the slicing kernel's vector path needs (_slicekernel.c)
AVX512_SLICES = ("AVX512F", "AVX512VL", "AVX512DQ", "AVX512BW")


def assert_document_current(problems: list[str]) -> None:
    """Fail on every difference :func:`converters.edge.evidence.check` reports; then, when some
    block could be compared within a tolerance only (its third-party library versions differ
    from the document's: lines "skipped: ..."), skip visibly with those lines as the reason."""
    real = [p for p in problems if not p.startswith("skipped:")]
    assert real == [], "docs/proposal.md is stale; run `make evidence`:\n" + "\n".join(real)
    skipped = [p for p in problems if p.startswith("skipped:")]
    if skipped:
        pytest.skip("exact comparison not possible with these library versions:\n"
                    + "\n".join(skipped))


def messages_by_topic(path: Path) -> dict[str, list[Any]]:
    """Every message of an MCAP file grouped by topic, in file order; fails on a bad record."""
    out: dict[str, list[Any]] = {}
    for item in read_messages(path):
        assert not isinstance(item, BadMessage), item
        out.setdefault(item.topic, []).append(item)
    return out


class Clock:
    """A settable clock for code that takes a ``clock()`` callable: returns ``now`` (int ns)."""

    def __init__(self) -> None:
        self.now = 0

    def __call__(self) -> int:
        return self.now
