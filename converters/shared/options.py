"""Validation of converter parameters: one function per configurable object.

Every parameter is checked for type, finiteness and range when the object is built, so a bad
configuration fails at once with a :class:`lidarscan.errors.ConfigError` whose ``field`` names
the parameter (``"range_min"``, ``"slices['floor'].max_height"``,
``"inputs['front'].timeout_ns"``), never later with a bare ``TypeError`` inside the algorithm.

* :func:`slice_options`: the keyword options of :class:`converters.slices.converter.SliceConverter` and
  :func:`converters.slices.converter.to_laserscan` (also used by the nodes' helpers), including the
  hole-detection options (:data:`HOLE_DEFAULTS`; a caller that has none gets their defaults);
* :func:`merger_options` and :func:`merger_input`: :class:`converters.merger.LaserScanMerger` and
  one :class:`converters.merger.MergerInput`;
* small checkers (:func:`number`, :func:`integer`, :func:`flag`, :func:`name`, :func:`choice`)
  for other objects.

Optional channels: a channel name given as :class:`IfPresent` (the defaults, e.g.
``intensity_channel=IfPresent("intensity")``) is used when the scan has that channel and
skipped otherwise; a plain ``str`` names a channel the scan must have.

Conventions: numbers may be any real (int, float, numpy scalar; not bool, not text); ``inf`` is
accepted only where the parameter says so; NaN never, except as a ``fill`` value.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from converters.shared.frames import check_extrinsics
from lidarscan.errors import ConfigError

__all__ = ["HOLE_DEFAULTS", "HOLE_KEYS", "IfPresent", "choice", "flag", "integer",
           "merger_input", "merger_options", "name", "number", "slice_options"]

BACKENDS = ("auto", "numba", "numpy", "c")
#: The hole-detection options of a slice and their defaults
#: (:class:`converters.slices.converter.SliceConverter`: holes off).
HOLE_DEFAULTS: dict[str, Any] = {"holes": False, "floor_height": 0.0, "hole_depth": 0.05,
                                 "hole_range_max": None, "hole_no_return": True}
HOLE_KEYS = tuple(HOLE_DEFAULTS)


class IfPresent(str):
    """A channel name used when the scan has that channel and skipped otherwise (defaults).

    A plain ``str`` names a required channel: a scan without it is an error.
    """

    __slots__ = ()

    def __repr__(self) -> str:
        return f"IfPresent({str.__repr__(self)})"


def number(field: str, value: Any, *, minimum: float | None = None, positive: bool = False,
           allow_inf: bool = False, allow_none: bool = False, allow_nan: bool = False
           ) -> float | None:
    """``value`` as a float after checking it is a real number (not bool, not text).

    Args:
        minimum: smallest allowed value (inclusive); ``positive``: strictly above 0.
        allow_inf: accept +-inf (still subject to ``minimum``); ``allow_nan``: accept NaN.
        allow_none: accept None (returned as None).
    """
    if value is None:
        if allow_none:
            return None
        raise ConfigError(field, value, "a number")
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer,
                                                                      np.floating)):
        raise ConfigError(field, value, "a number" + (" or None" if allow_none else ""))
    out = float(value)
    if math.isnan(out):
        if allow_nan:
            return out
        raise ConfigError(field, value, "a number, not NaN")
    if math.isinf(out) and not allow_inf:
        raise ConfigError(field, value, "a finite number")
    if positive and not out > 0:
        raise ConfigError(field, value, "> 0")
    if minimum is not None and out < minimum:
        raise ConfigError(field, value, f">= {minimum}")
    return out


def integer(field: str, value: Any, *, minimum: int | None = None, allow_none: bool = False
            ) -> int | None:
    """``value`` as an int after checking it is an integer (not bool, not a float)."""
    if value is None and allow_none:
        return None
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise ConfigError(field, value, "an int" + (" or None" if allow_none else ""))
    if minimum is not None and value < minimum:
        raise ConfigError(field, value, f"an int >= {minimum}")
    return int(value)


def flag(field: str, value: Any) -> bool:
    """``value`` as a bool after checking it is one (``"false"`` is not)."""
    if not isinstance(value, (bool, np.bool_)):
        raise ConfigError(field, value, "True or False")
    return bool(value)


def name(field: str, value: Any, *, allow_none: bool = False) -> str | None:
    """A non-empty str (a channel or frame name), or None where allowed."""
    if value is None and allow_none:
        return None
    if not isinstance(value, str) or not value:
        raise ConfigError(field, value, "a non-empty str" + (" or None" if allow_none else ""))
    return value


def choice(field: str, value: Any, choices: Sequence[str]) -> str:
    """One of ``choices``."""
    if not isinstance(value, str) or value not in choices:
        raise ConfigError(field, value, "one of " + ", ".join(repr(c) for c in choices))
    return value


def _grid_and_output(prefix: str, values: Mapping[str, Any], optional: bool) -> None:
    """Checks shared by slices and the merger: the angle grid and the output values."""
    none = optional
    number(prefix + "angle_min", values["angle_min"], allow_none=none)
    number(prefix + "angle_max", values["angle_max"], allow_none=none)
    number(prefix + "angle_increment", values["angle_increment"], positive=True,
           allow_none=none)
    rmin = number(prefix + "range_min", values["range_min"], minimum=0.0, allow_none=none)
    rmax = number(prefix + "range_max", values["range_max"], positive=True, allow_inf=True,
                  allow_none=none)
    if rmin is not None and rmax is not None and rmax < rmin:
        raise ConfigError(prefix + "range_max", values["range_max"],
                          f">= range_min ({rmin}), may be inf")
    if values["use_inf"] is not None or not optional:
        flag(prefix + "use_inf", values["use_inf"])
    number(prefix + "inf_epsilon", values["inf_epsilon"], minimum=0.0, allow_none=none)
    number(prefix + "fill", values["fill"], allow_inf=True, allow_nan=True, allow_none=True)


def _holes(prefix: str, values: Mapping[str, Any], optional: bool) -> None:
    """Checks of the hole options (:data:`HOLE_KEYS`); ``optional``: None = not overridden."""
    for key in ("holes", "hole_no_return"):
        if values[key] is not None or not optional:
            flag(prefix + key, values[key])
    number(prefix + "floor_height", values["floor_height"], allow_none=optional)
    number(prefix + "hole_depth", values["hole_depth"], positive=True, allow_none=optional)
    number(prefix + "hole_range_max", values["hole_range_max"], positive=True, allow_inf=True,
           allow_none=True)


def slice_options(slices: Any, options: Mapping[str, Any]) -> None:
    """Check the configuration of a :class:`converters.slices.converter.SliceConverter`.

    Args:
        slices: name -> SliceSpec (or a dict of its fields; converted by the caller).
        options: the converter's keyword options by name (all of them).

    Raises:
        ConfigError: the first bad parameter, by name.
    """
    unknown = set(options) - _SLICE_KEYS
    if unknown:
        raise ConfigError(sorted(unknown)[0], options[sorted(unknown)[0]],
                          f"an option among {sorted(_SLICE_KEYS)}")
    choice("backend", options["backend"], BACKENDS)
    if not isinstance(slices, Mapping) or not slices:
        raise ConfigError("slices", slices, "a non-empty dict of name -> SliceSpec")
    for key, spec in slices.items():
        if not isinstance(key, str) or not key:
            raise ConfigError("slices", key, "non-empty str slice names")
        prefix = f"slices[{key!r}]."
        lo = number(prefix + "min_height", spec.min_height, allow_inf=True)
        hi = number(prefix + "max_height", spec.max_height, allow_inf=True)
        if lo is not None and hi is not None and lo > hi:
            raise ConfigError(prefix + "max_height", spec.max_height,
                              f">= min_height ({spec.min_height}): the band is inclusive "
                              "[min_height, max_height]")
        _grid_and_output(prefix, {k: getattr(spec, k) for k in _OUTPUT_KEYS}, optional=True)
        _holes(prefix, {k: getattr(spec, k) for k in HOLE_KEYS}, optional=True)
    _grid_and_output("", {k: options[k] for k in _OUTPUT_KEYS}, optional=True)
    _holes("", {k: options.get(k, v) for k, v in HOLE_DEFAULTS.items()}, optional=False)
    flag("use_inf", options["use_inf"])
    number("inf_epsilon", options["inf_epsilon"], minimum=0.0)
    check_extrinsics(options["extrinsics"])
    name("frame_id", options["frame_id"], allow_none=True)
    if options["extrinsics"] is not None and not options["frame_id"]:
        raise ConfigError("frame_id", options["frame_id"],
                          "the target frame's name when extrinsics are given")
    name("intensity_channel", options["intensity_channel"], allow_none=True)
    name("range_channel", options["range_channel"])


_OUTPUT_KEYS = ("angle_min", "angle_max", "angle_increment", "range_min", "range_max",
                "use_inf", "inf_epsilon", "fill")
_SLICE_KEYS = {*_OUTPUT_KEYS, *HOLE_KEYS, "extrinsics", "frame_id", "intensity_channel",
               "range_channel", "backend"}


def merger_input(key: str, cfg: Any) -> None:
    """Check one :class:`converters.merger.MergerInput` named ``key``."""
    prefix = f"inputs[{key!r}]."
    rmin = number(prefix + "range_min", cfg.range_min, minimum=0.0)
    rmax = number(prefix + "range_max", cfg.range_max, minimum=0.0, allow_inf=True)
    if rmax is not None and rmin is not None and rmax < rmin:
        raise ConfigError(prefix + "range_max", cfg.range_max,
                          f">= range_min ({cfg.range_min}) >= 0")
    lo = number(prefix + "min_height", cfg.min_height, allow_inf=True)
    hi = number(prefix + "max_height", cfg.max_height, allow_inf=True)
    if lo is not None and hi is not None and lo > hi:
        raise ConfigError(prefix + "max_height", cfg.max_height, f">= min_height ({lo})")
    number(prefix + "angle_min", cfg.angle_min, allow_none=True)
    number(prefix + "angle_max", cfg.angle_max, allow_none=True)
    if (cfg.angle_min is None) != (cfg.angle_max is None):
        raise ConfigError(prefix + "angle_max", cfg.angle_max,
                          "set together with angle_min (or both None)")
    integer(prefix + "timeout_ns", cfg.timeout_ns, minimum=1, allow_none=True)
    name(prefix + "frame_id", cfg.frame_id, allow_none=True)


def merger_options(options: Mapping[str, Any]) -> None:
    """Check the keyword options of a :class:`converters.merger.LaserScanMerger` (all of them,
    by name; the inputs are checked by :func:`merger_input`)."""
    choice("backend", options["backend"], BACKENDS)
    name("frame_id", options["frame_id"])
    _grid_and_output("", {k: options[k] for k in _OUTPUT_KEYS}, optional=False)
    flag("intensities", options["intensities"])
    flag("motion_compensation", options["motion_compensation"])
    for key in ("slop_ns", "timeout_ns", "odom_max_gap_ns"):
        integer(key, options[key], minimum=0)
    for key in ("queue_size", "odom_queue_size"):
        integer(key, options[key], minimum=1)
    integer("jump_back_ns", options["jump_back_ns"], minimum=1, allow_none=True)
    choice("policy", options["policy"], ("wait", "timeout"))
    choice("reference", options["reference"], ("newest", "oldest"))
