"""Pieces every node uses: bounded logging, rates and latency for ``/diagnostics``, the warm-up
before a node reports ready, an exact-stamp synchroniser, and the ``main`` runner (``--help``
without ROS, clean shutdown). Nothing here imports rclpy at module import time.

Ready before listening: a node loads every kernel it will use (:func:`warm_up`, which runs the
node's steps, e.g. :func:`converters.warmup.prepare` with its configuration: numba's cache only,
the C kernels or numpy while the cache lacks a kernel) after its publishers and BEFORE its
subscriptions, then logs one ``ready`` line naming the backends that run; its ``/diagnostics``
carry a ``startup`` status with the time each step took and the backends. A publisher that
waits for the subscription to match therefore never sends to a node that is not ready, and no
scan compiles anything.

Diagnostics: each node publishes ``diagnostic_msgs/DiagnosticArray`` on ``/diagnostics`` once a
second (:class:`Diagnostics`); levels are OK (0), WARN (1), ERROR (2) with the reason in the
message; values are per-second rates over the last period, totals, latency (receive time minus
the message stamp, milliseconds) and the node's linkage state.
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from typing import Any

__all__ = ["OK", "WARN", "ERROR", "Diagnostics", "ExactSync", "Guard", "LatencyWindow",
           "LogLimiter", "RateMeter", "Startup", "Status", "entry_points", "kernels_status",
           "run_node", "warm_up"]

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
        #: the node's warm-up (:func:`warm_up`), published as a ``startup`` status once set
        self.startup: Startup | None = None
        self.timer = node.create_timer(period, self.publish)

    def publish(self) -> None:
        from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

        try:
            statuses = self._collect()
        except Exception as err:  # noqa: BLE001 - diagnostics must never stop the node
            statuses = [Status("diagnostics")]
            statuses[0].worse(ERROR, f"collecting failed: {type(err).__name__}: {err}")
        if self.startup is not None:
            statuses = [*statuses, self.startup.status()]
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



class Startup:
    """What a node did before it reported ready: each warm-up step's time and failure.

    Attributes:
        seconds: step -> seconds it took.
        failed: step -> the error of a step that failed (the node runs anyway: a warm-up only
            moves work off the message path).
        ready: set once every step ran.
    """

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self.failed: dict[str, str] = {}
        self.ready = False
        #: more values of the ``startup`` status (e.g. the backends that run)
        self.values: dict[str, Any] = {}

    def run(self, name: str, step: Callable[[], Any]) -> None:
        """Run and time one step; an exception is recorded, not raised."""
        start = time.perf_counter()
        try:
            step()
        except Exception as err:  # noqa: BLE001 - a failed warm-up must not stop the node
            self.failed[name] = f"{type(err).__name__}: {err}"
        self.seconds[name] = time.perf_counter() - start

    def summary(self) -> str:
        """One line: total and per-step milliseconds, failures."""
        total = sum(self.seconds.values())
        steps = ", ".join(f"{k} {1e3 * v:.0f} ms" for k, v in self.seconds.items())
        line = f"warm-up {1e3 * total:.0f} ms ({steps or 'nothing to do'})"
        if self.failed:
            line += "; failed: " + "; ".join(f"{k}: {v}" for k, v in self.failed.items())
        return line

    def status(self) -> Status:
        """The ``startup`` DiagnosticStatus: ready, total and per-step milliseconds (WARN when
        a step failed: the first messages then pay that work)."""
        values: dict[str, Any] = {"ready": self.ready,
                                  "warmup_ms": round(1e3 * sum(self.seconds.values()), 1)}
        values.update({f"{k}_ms": round(1e3 * v, 1) for k, v in self.seconds.items()})
        values.update(self.values)
        st = Status("startup", values)
        if not self.ready:
            st.worse(WARN, "warming up")
        for name, err in self.failed.items():
            st.worse(WARN, f"warm-up step {name} failed ({err}): first messages may be slow")
        return st


@contextlib.contextmanager
def _interrupts_in_callbacks_quiet() -> Iterator[None]:
    """A Ctrl-C that lands inside a compiled library's callback during the warm-up (numba's
    object-cache hook in llvmlite) cannot propagate from there: Python reports it as an
    "Exception ignored" traceback. rclpy's SIGINT handler has already shut the context down by
    then, so the node stops once the warm-up returns (:func:`run_node`); only the report is
    dropped. Every other unraisable exception is reported as before."""
    previous = sys.unraisablehook

    def hook(unraisable: Any) -> None:
        if not isinstance(unraisable.exc_value, KeyboardInterrupt):
            previous(unraisable)

    sys.unraisablehook = hook
    try:
        yield
    finally:
        sys.unraisablehook = previous


def warm_up(node: Any, steps: dict[str, Callable[[], Any]],
            diagnostics: Diagnostics | None = None,
            describe: Callable[[], tuple[str, dict[str, Any]]] | None = None) -> Startup:
    """Run a node's warm-up ``steps`` (name -> callable), then log ``ready`` with their times.

    Call it after the node's publishers exist and BEFORE it creates its subscriptions: a
    publisher that starts when it matches a subscription then finds the node ready.
    ``diagnostics`` gets the ``startup`` status; ``describe`` (after the steps) gives one more
    log clause and status values (the backends that run).
    """
    startup = Startup()
    with _interrupts_in_callbacks_quiet():
        for name, step in steps.items():
            startup.run(name, step)
    startup.ready = True
    line, values = describe() if describe is not None else ("", {})
    startup.values.update(values)
    log = node.get_logger()
    (log.warning if startup.failed else log.info)(
        f"ready: {startup.summary()}" + (f"; {line}" if line else ""))
    if diagnostics is not None:
        diagnostics.startup = startup
    return startup


def kernels_status(kernels: Any) -> tuple[str, dict[str, Any]]:
    """A node's ``describe`` for :func:`warm_up`: (log clause, ``startup`` status values) of
    the kernels that run, from its :class:`converters.warmup.Prepared` (None: not warmed,
    nothing to say): the backend, ``kernels_<task>`` per task, and ``numba_cache`` while
    numba's cache is being filled in the background."""
    if kernels is None:
        return "", {}
    return kernels.summary(), {
        "backend": kernels.backend,
        **{f"kernels_{k}": v for k, v in kernels.runs.items()},
        **({"numba_cache": "filling in the background"} if kernels.missing else {})}


class ExactSync:
    """Pairs messages of several inputs that carry the same stamp (the ExactTime policy of
    ``message_filters``), with bounded queues and every unpaired message counted.

    Each input keeps at most ``queue_size`` messages waiting for their partners. A message
    whose stamp all inputs have is released at once, in input order. Counted drops (per
    input, in :attr:`dropped`): ``overflow`` (the oldest waiting message of a full queue),
    ``stale`` (a waiting message older than a released set: its partners will not come when
    stamps increase), ``duplicate`` (a second message with a waiting stamp replaces the first).

    Args:
        names: the inputs, in the order the released tuples have.
        queue_size: messages kept per input (>= 1).
    """

    def __init__(self, names: Sequence[str], queue_size: int = 10) -> None:
        from lidarscan.errors import ConfigError

        if isinstance(queue_size, bool) or not isinstance(queue_size, int) or queue_size < 1:
            raise ConfigError("queue_size", queue_size, "an int >= 1")
        if len(set(names)) != len(names) or len(names) < 2:
            raise ConfigError("names", list(names), "at least two distinct input names")
        self.names = tuple(names)
        self.queue_size = queue_size
        self._queues: dict[str, dict[int, Any]] = {n: {} for n in self.names}
        self.dropped: dict[str, dict[str, int]] = {
            n: {"overflow": 0, "stale": 0, "duplicate": 0} for n in self.names}
        self.released = 0

    def add(self, name: str, stamp_ns: int, message: Any) -> tuple[Any, ...] | None:
        """Add one message; returns the messages of every input at ``stamp_ns`` when this
        completes the set (in :attr:`names` order), else None.

        Raises:
            ConfigError: an unknown input name.
        """
        from lidarscan.errors import ConfigError

        queue = self._queues.get(name)
        if queue is None:
            raise ConfigError("input", name, f"one of {list(self.names)}")
        stamp = int(stamp_ns)
        if stamp in queue:
            self.dropped[name]["duplicate"] += 1
        queue[stamp] = message
        while len(queue) > self.queue_size:
            del queue[min(queue)]
            self.dropped[name]["overflow"] += 1
        if not all(stamp in q for q in self._queues.values()):
            return None
        out = tuple(self._queues[n].pop(stamp) for n in self.names)
        for n, q in self._queues.items():
            for old in [t for t in q if t < stamp]:
                del q[old]
                self.dropped[n]["stale"] += 1
        self.released += 1
        return out

    def waiting(self) -> dict[str, int]:
        """Messages waiting per input."""
        return {n: len(q) for n, q in self._queues.items()}

    def drops(self) -> int:
        """Total messages dropped unpaired."""
        return sum(sum(d.values()) for d in self.dropped.values())


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


class Guard:
    """The one error guard of the nodes' callbacks: nothing a message contains stops a node.

    ``with Guard(log, "scan not converted", bad=..., internal=...) as guard: ...`` then ``if
    guard.failed: return``. A :class:`lidarscan.errors.LidarScanError` (bad input, no
    transform, ...) calls ``bad(err)`` (the caller's counters) and logs ``"{what}: {err}"``
    under ``key``; any other ``Exception`` (a bug) calls ``internal(err)`` (default: ``bad``)
    and logs ``"{what} (internal error {type}: {err})"`` with its traceback under
    ``internal_key``; both are swallowed. ``KeyboardInterrupt`` and ``SystemExit`` pass.

    Args:
        log: ``(line, key) -> None``, e.g. a :class:`LogLimiter` (rate-limited per key).
        what: what failed, the start of the log line.
        bad, internal: counters to update (None: count nothing).
        key, internal_key: the log keys of the two kinds.
    """

    def __init__(self, log: Callable[[str, str], None], what: str, *,
                 bad: Callable[[Exception], Any] | None = None,
                 internal: Callable[[Exception], Any] | None = None, key: str = "bad",
                 internal_key: str = "internal") -> None:
        self._log, self.what, self.key, self.internal_key = log, what, key, internal_key
        self._bad = bad
        self._internal = internal if internal is not None else bad
        #: the body raised (and the error was counted and logged)
        self.failed = False
        #: the error the body raised, if any
        self.error: Exception | None = None

    def __enter__(self) -> Guard:
        return self

    def __exit__(self, kind: Any, err: Any, tb: Any) -> bool:
        if err is None or not isinstance(err, Exception):
            return False
        from lidarscan.errors import LidarScanError

        self.failed, self.error = True, err
        if isinstance(err, LidarScanError):
            if self._bad is not None:
                self._bad(err)
            self._log(f"{self.what}: {err}", self.key)
        else:
            if self._internal is not None:
                self._internal(err)
            trace = "".join(traceback.format_exception(kind, err, tb)).rstrip()
            self._log(f"{self.what} (internal error {type(err).__name__}: {err})\n{trace}",
                      self.internal_key)
        return True


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
        # Ctrl-C while the node was being built (its kernel warm-up can take seconds) is
        # handled by rclpy's own SIGINT handler: it shuts the context down instead of raising,
        # so spinning now would fail with "context is not valid". That is a normal stop.
        if rclpy.ok():
            rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except LidarScanError as err:
        print(f"error: {err}", file=sys.stderr)
        status = 2
    except Exception:
        if rclpy.ok():     # a real failure, not the shutdown above racing the check
            raise
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
            try:
                print(usage(), flush=True)
            except BrokenPipeError:          # `--help | head`: the reader has what it wanted
                os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
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
