"""How a deterministic block of ``docs/proposal.md`` is compared with what the script writes.

Exact, character for character, for every figure the project controls. Two kinds of figures
are not the project's and are compared within a stated relative tolerance instead:

* figures of a third-party encoder whose output depends on the CPU for the same library
  version (a block's :attr:`Block.tolerance`: lines holding one of its keys, e.g. the JPEG-XL
  rows of the codec study: libjxl picks its SIMD path at run time);
* every figure of a block whose third-party library versions (:attr:`Block.versions`, named
  in its text) differ from the versions the document names: zstd, lz4, Pillow, Draco or
  imagecodecs of another release code the same data in other sizes. Such a block is compared
  within :data:`VERSION_TOLERANCE` and reported as "skipped:" (exact comparison skipped, with
  both version lists), which the tests turn into a visible ``pytest.skip``.

Within a tolerance, the text around the numbers must still be equal (a claim such as "met" /
"**not met**" that flips is a difference), and two numbers agree when
``|a - b| <= rtol * max(|a|, |b|) + one unit of their last printed digit``.
"""

from __future__ import annotations

import re

from converters.edge.evidence._common import Block

__all__ = ["VERSION_TOLERANCE", "compare", "documented_versions"]

#: Relative tolerance of every figure of a block whose library versions differ from the
#: document's (a new zstd / lz4 / Draco / libjxl release moves compressed sizes by a few %).
VERSION_TOLERANCE = 0.05

#: A printed number: digits, optional thin-space thousands groups (fmt_int), optional decimals.
_NUMBER = re.compile(r"\d+(?: \d{3})*(?:\.\d+)?")
_VERSIONS = "\x00versions\x00"


def _versions_pattern(versions: str) -> re.Pattern[str]:
    """Matches a version list of the same libraries, in the same order, any releases."""
    parts = [re.escape(part.rsplit(" ", 1)[0]) + r" [^,;)\n]+" for part in versions.split(", ")]
    return re.compile(", ".join(parts))


def documented_versions(documented: str, block: Block) -> str | None:
    """The library versions ``documented`` (a block's text in the document) names for the
    libraries of ``block.versions``; None when it names none."""
    if not block.versions:
        return None
    found = _versions_pattern(block.versions).search(documented)
    return None if found is None else found.group(0)


def _within(a: str, b: str, rtol: float) -> bool:
    x, y = float(a.replace(" ", "")), float(b.replace(" ", ""))
    decimals = max(len(t.split(".")[1]) if "." in t else 0 for t in (a, b))
    return abs(x - y) <= rtol * max(abs(x), abs(y)) + 10.0 ** -decimals


def _line_difference(old: str, new: str, rtol: float) -> str | None:
    """None when the lines agree (exactly, or within ``rtol`` on the numbers), else why not."""
    if old == new:
        return None
    if rtol <= 0:
        return f"{old!r} is now {new!r}"
    if _NUMBER.sub("#", old) != _NUMBER.sub("#", new):
        return f"{old!r} is now {new!r} (the words differ)"
    for a, b in zip(_NUMBER.findall(old), _NUMBER.findall(new)):
        if not _within(a, b, rtol):
            return f"{a} is now {b}, beyond {rtol * 100:g} % in {new!r}"
    return None


def compare(documented: str, block: Block) -> tuple[str, str]:
    """Compare a block's documented text with the script's text.

    Returns:
        ("", "") when they agree; ("differs", why) when the document is stale; ("skipped",
        why) when they agree within :data:`VERSION_TOLERANCE` only because the block's library
        versions differ from the document's (the exact comparison could not be made).
    """
    old, new = documented.strip(), block.text.strip()
    if old == new:
        return "", ""
    doc_versions = documented_versions(old, block)
    versions_differ = bool(block.versions) and doc_versions != block.versions
    if block.versions and doc_versions is not None:
        old = old.replace(doc_versions, _VERSIONS)
        new = new.replace(block.versions, _VERSIONS)
    old_lines, new_lines = old.split("\n"), new.split("\n")
    if len(old_lines) != len(new_lines):
        return "differs", f"{len(old_lines)} lines in the document, {len(new_lines)} now"
    for a, b in zip(old_lines, new_lines):
        rtol = VERSION_TOLERANCE if versions_differ else max(
            [tol for key, tol in block.tolerance.items() if key in b], default=0.0)
        why = _line_difference(a, b, rtol)
        if why is not None:
            return "differs", why
    if versions_differ:
        return "skipped", (f"the document's figures come from {doc_versions}, this run's from "
                           f"{block.versions}: compared within {VERSION_TOLERANCE * 100:.0f} %, not "
                           "exactly")
    return "", ""
