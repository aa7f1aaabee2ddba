"""argparse types shared by the command line's parsers (below ``_parser`` and ``fleet``)."""

from __future__ import annotations

import argparse
from collections.abc import Callable

__all__ = ["_int_at_least", "_non_negative_int", "_positive_int"]


def _int_at_least(minimum: int) -> Callable[[str], int]:
    """An argparse type: an integer >= ``minimum`` (the error names the text and the bound,
    also for a text that is no integer)."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = None
        if value is None or value < minimum:
            raise argparse.ArgumentTypeError(f"{text!r}: expected an integer >= {minimum}")
        return value
    return parse


_positive_int = _int_at_least(1)
_non_negative_int = _int_at_least(0)
