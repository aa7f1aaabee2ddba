"""Pieces every node uses: bounded logging, rates and latency for ``/diagnostics``, and the
``main`` runner (``--help`` without ROS, clean shutdown). Nothing here imports rclpy at module
import time.

Diagnostics: each node publishes ``diagnostic_msgs/DiagnosticArray`` on ``/diagnostics`` once a
second (:class:`Diagnostics`); levels are OK (0), WARN (1), ERROR (2) with the reason in the
message; values are per-second rates over the last period, totals, latency (receive time minus
the message stamp, milliseconds) and the node's linkage state.
"""

from __future__ import annotations

import contextlib
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

__all__ = ["OK", "WARN", "ERROR", "Diagnostics", "LatencyWindow", "LogLimiter", "RateMeter",
           "Status", "entry_points", "run_node"]

OK, WARN, ERROR = 0, 1, 2


class Status:
    """One DiagnosticStatus before it becomes a message.

    Attributes:
        name: status name (the node name is prefixed when published).
        level: OK, WARN or ERROR.
        message: the reasons (one line, "; "-separated).
        values: key -> value (published as text).
    """

    def __init__(self, name: str, values: dict[str, Any] | None = None) -> None:
        self.name, self.level, self.message = name, OK, "ok"
        self.values = dict(values or {})

    def worse(self, level: int, reason: str) -> None:
        """Raise the level to ``level`` (never lower it) and add the reason."""
        if level <= OK:
            return
        self.level = max(self.level, level)
        self.message = reason if self.message == "ok" else f"{self.message}; {reason}"


class RateMeter:
    """Increases of monotonically growing counters between two calls.

    Args:
        clock: monotonic seconds.
    """

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._clock = clock
        self._last: dict[str, int] = {}
        self._t = clock()

    def update(self, counters: dict[str, int]) -> tuple[dict[str, int], float]:
        """(counter -> increase since the last call, seconds elapsed)."""
        now = self._clock()
        dt = max(now - self._t, 1e-9)
        delta = {k: int(v) - self._last.get(k, 0) for k, v in counters.items()}
        self._last = {k: int(v) for k, v in counters.items()}
        self._t = now
        return delta, dt


class LatencyWindow:
    """Latencies (ns) of the current period, bounded (the last ``size`` kept)."""

    def __init__(self, size: int = 512) -> None:
        from collections import deque

        self._samples: Any = deque(maxlen=size)

    def add(self, latency_ns: int) -> None:
        self._samples.append(int(latency_ns))

    def take(self) -> dict[str, float]:
        """``latency_p50_ms`` and ``latency_max_ms`` of the period, then forget it (empty: no
        sample)."""
        if not self._samples:
            return {}
        data = sorted(self._samples)
        self._samples.clear()
        return {"latency_p50_ms": round(data[len(data) // 2] / 1e6, 3),
                "latency_max_ms": round(data[-1] / 1e6, 3)}


class Diagnostics:
    """Publishes ``collect()`` on ``/diagnostics`` every ``period`` seconds.

    Args:
        node: rclpy node.
        collect: ``() -> list[Status]``.
        period: seconds (1 Hz by default).
    """

    def __init__(self, node: Any, collect: Callable[[], list[Status]],
                 period: float = 1.0) -> None:
        from diagnostic_msgs.msg import DiagnosticArray

        self._node = node
        self._collect = collect
        self.publisher = node.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.last: list[Status] = []
        self.timer = node.create_timer(period, self.publish)

    def publish(self) -> None:
        from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

        try:
            statuses = self._collect()
        except Exception as err:  # noqa: BLE001 - diagnostics must never stop the node
            statuses = [Status("diagnostics")]
            statuses[0].worse(ERROR, f"collecting failed: {type(err).__name__}: {err}")
        self.last = statuses
        msg = DiagnosticArray()
        msg.header.stamp = self._node.get_clock().now().to_msg()
        name = self._node.get_fully_qualified_name().lstrip("/")
        for st in statuses:
            msg.status.append(DiagnosticStatus(
                level=bytes([st.level]), name=f"{name}: {st.name}", message=st.message,
                hardware_id=name,
                values=[KeyValue(key=str(k), value=str(v)) for k, v in st.values.items()]))
        self.publisher.publish(msg)



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


def entry_points(class_name: str, node_class: Callable[[], Any], script: str,
                 usage: Callable[[], str] | None = None
                 ) -> tuple[Callable[[str], Any], Callable[..., int]]:
    """A node module's ``__getattr__`` and ``main``, assigned at its top level.

    ``__getattr__`` builds the rclpy node class (``node_class()``) on the first access of
    ``module.<class_name>``, so importing the module does not import rclpy; ``main`` is the
    console script ``script`` (ROS arguments after ``--ros-args``), run by :func:`run_node`.
    ``-h`` / ``--help`` before ``--ros-args`` prints ``usage()`` and returns 0 without starting
    ROS; any other argument there is refused (status 2) with the usage line.
    """

    def module_getattr(name: str) -> Any:
        if name == class_name:
            return node_class()
        raise AttributeError(name)

    def main(args: Sequence[str] | None = None) -> int:
        argv = list(sys.argv if args is None else args)
        ours = argv[1:argv.index("--ros-args")] if "--ros-args" in argv else argv[1:]
        if usage is not None and any(a in ("-h", "--help") for a in ours):
            print(usage())
            return 0
        if ours:
            print(f"usage: {script} [-h] [--ros-args ...]\nerror: unknown argument(s) "
                  f"{' '.join(ours)} (ROS arguments go after --ros-args; -h for help)",
                  file=sys.stderr)
            return 2
        try:
            return run_node(lambda: node_class()(), argv)
        except ModuleNotFoundError as err:   # e.g. a plain `pip install`: no lidarscan_msgs
            from lidarscan._install import missing_module_hint
            print(f"error: {missing_module_hint(err, script)}", file=sys.stderr)
            return 2

    main.__doc__ = f"Console script ``{script}`` (ROS arguments after ``--ros-args``)."
    return module_getattr, main
