"""YAML reading for the project: PyYAML's C loader when libyaml is present (about 10x faster
on calibration files and rosbag2 QoS profiles), else the pure-Python one; same results."""

from __future__ import annotations

from typing import Any

import yaml

_LOADER: Any = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def safe_load(text: str) -> Any:
    """``yaml.safe_load(text)`` through the fastest safe loader available."""
    return yaml.load(text, Loader=_LOADER)  # noqa: S506 - a SafeLoader
