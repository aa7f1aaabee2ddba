"""What is installed, and what to run when a module is missing (one line, no traceback).

Install paths (README, "Other ways to install"): ``make install`` (or ``make demo`` / ``make test``) gives
everything: the ROS 2 Jazzy wheels, ``lidarscan_msgs`` and ``tf2_msgs`` built into ``.venv``,
and the extras. A plain ``pip install .`` installs the Python packages and the ROS 2 wheels but
builds no message package: the core then makes :mod:`lidarscan.types` dataclasses where it
would make ``lidarscan_msgs`` messages (:func:`have_messages`), and the entry points that need
the messages (the rclpy nodes) print :func:`missing_module_hint` and exit with status 2.

Nothing here imports rclpy or a message package at import time.
"""

from __future__ import annotations

import functools
import sys

__all__ = ["have_messages", "missing_module_hint"]

_MAKE = ("in the lidarscan checkout, run `make install` (a .venv with everything) or build them "
         "into this environment: `{python} -m pip install '.[msgs-build]' && make msgs "
         "VENV={prefix}`; in a ROS 2 workspace: colcon (README, 'In a ROS 2 workspace')")
_ROS = ("install the ROS 2 Jazzy wheels (`pip install .` in the lidarscan checkout does, on "
        "CPython 3.11) or source a ROS 2 Jazzy installation")

#: top-level module -> what provides it
_PROVIDERS: dict[str, str] = {
    "lidarscan_msgs": "lidarscan's own ROS 2 messages are not built into this environment: "
                      + _MAKE,
    "tf2_msgs": "tf2_msgs is not in the ROS 2 wheels: in the lidarscan checkout, run `make "
                "install` (a .venv with everything) or `make tf2msgs VENV={prefix}` (after "
                "`pip install '.[msgs-build]'`), or source a ROS 2 installation",
    "matplotlib": "it is an extra: `pip install '.[viz]'` in the lidarscan checkout",
    "numba": "it is an extra: `pip install '.[fast]'` in the lidarscan checkout",
    "ouster": "it is an extra: `pip install '.[ouster]'` in the lidarscan checkout",
    "DracoPy": "it is an extra: `pip install '.[evidence]'` in the lidarscan checkout",
    "imagecodecs": "it is an extra: `pip install '.[evidence]'` in the lidarscan checkout",
    "dask": "it is an extra: `pip install '.[dask]'` in the lidarscan checkout",
    "distributed": "it is an extra: `pip install '.[dask]'` in the lidarscan checkout",
}
for _name in ("rclpy", "rosidl_runtime_py", "rpyutils", "builtin_interfaces", "std_msgs",
              "sensor_msgs", "geometry_msgs", "nav_msgs", "diagnostic_msgs", "rcl_interfaces"):
    _PROVIDERS[_name] = f"{_name} is part of ROS 2: " + _ROS


@functools.cache
def have_messages() -> bool:
    """Whether ``lidarscan_msgs`` (the generated rclpy message classes) can be imported here."""
    try:
        import lidarscan_msgs.msg  # noqa: F401
    except ImportError:
        return False
    return True


def missing_module_hint(err: ImportError | str, what: str = "this") -> str:
    """One line naming the missing module and what to run to get it.

    Args:
        err: the ImportError (its ``name``) or a module name (``pkg`` or ``pkg.sub``).
        what: the program or feature that needs it, e.g. ``"lidarscan-converter"``.
    """
    name = err if isinstance(err, str) else (err.name or str(err))
    top = name.split(".")[0]
    fix = _PROVIDERS.get(top, f"install the Python package that provides {top!r}")
    fix = fix.replace("{python}", sys.executable).replace("{prefix}", sys.prefix)
    return f"{what} needs the module {top!r}: {fix}"
