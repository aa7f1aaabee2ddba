"""Pieces every node uses: bounded logging, counters, and the ``main`` runner with clean
shutdown. Nothing here imports rclpy at module import time."""

from __future__ import annotations

import contextlib
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

__all__ = ["LogLimiter", "entry_points", "run_node"]


class LogLimiter:
    """At most ``per_second`` lines per key and second; the rest are counted and summarised.

    A node that receives a broken stream at 40 Hz logs the first lines of each kind at once and
    then one summary line per second ("... (37 more like this in the last 1.0 s)"), so the log
    stays readable and bounded.

    Args:
        emit: where a line goes (e.g. ``node.get_logger().warning``).
        per_second: lines per key and second before suppressing.
        clock: monotonic seconds.
    """

    def __init__(self, emit: Callable[[str], None], *, per_second: int = 5,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._emit = emit
        self._per_second = per_second
        self._clock = clock
        self._windows: dict[str, list[Any]] = {}  # key -> [window start, lines, suppressed]

    def __call__(self, line: str, key: str = "") -> None:
        now = self._clock()
        window = self._windows.get(key)
        if window is None or now - window[0] >= 1.0:
            if window is not None and window[2]:
                self._emit(f"({window[2]} more like '{key or 'this'}' in the last "
                           f"{now - window[0]:.1f} s)")
            window = [now, 0, 0]
            self._windows[key] = window
            if len(self._windows) > 256:  # bounded: forget the oldest keys
                for old in list(self._windows)[:64]:
                    del self._windows[old]
                self._windows[key] = window
        if window[1] < self._per_second:
            window[1] += 1
            self._emit(line)
        else:
            window[2] += 1


def run_node(make_node: Callable[[], Any], args: Sequence[str] | None = None) -> int:
    """Init rclpy, build the node, spin until Ctrl-C / shutdown, always clean up.

    Returns the process exit status: 0 after a normal or Ctrl-C shutdown, 2 when the node could
    not start (invalid parameters, printed as one line).
    """
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.utilities import try_shutdown

    from lidarscan.errors import LidarScanError

    rclpy.init(args=list(args) if args is not None else sys.argv)  # returns None on Jazzy
    node = None
    status = 0
    try:
        node = make_node()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except LidarScanError as err:
        print(f"error: {err}", file=sys.stderr)
        status = 2
    finally:
        if node is not None:
            with contextlib.suppress(Exception):  # never mask the original exit path
                node.destroy_node()
        try_shutdown()
    return status


def entry_points(class_name: str, node_class: Callable[[], Any], script: str
                 ) -> tuple[Callable[[str], Any], Callable[..., int]]:
    """A node module's ``__getattr__`` and ``main``, assigned at its top level.

    ``__getattr__`` builds the rclpy node class (``node_class()``) on the first access of
    ``module.<class_name>``, so importing the module does not import rclpy; ``main`` is the
    console script ``script`` (ROS arguments after ``--ros-args``), run by :func:`run_node`.
    """

    def module_getattr(name: str) -> Any:
        if name == class_name:
            return node_class()
        raise AttributeError(name)

    def main(args: Sequence[str] | None = None) -> int:
        return run_node(lambda: node_class()(), args)

    main.__doc__ = f"Console script ``{script}`` (ROS arguments after ``--ros-args``)."
    return module_getattr, main
