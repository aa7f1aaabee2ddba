"""Ctrl-C (SIGINT) as a request to stop between messages, for ``lidarscan convert``.

Python's default SIGINT handler raises ``KeyboardInterrupt`` at whatever bytecode runs when the
signal arrives: inside a numba-compiled kernel's dispatcher that surfaced as ``SystemError:
CPUDispatcher(...) returned a result with an exception set`` (exit 1, the output deleted). With
:class:`StopRequest` installed, the first Ctrl-C only sets a flag; the reading loop of the
conversion checks it between messages, stops reading, and the command finishes the output
(a valid MCAP of everything written so far) and exits 130. A second Ctrl-C raises
``KeyboardInterrupt`` as before (for a user who does not want to wait for the output to be
closed; the writer still closes it, see :func:`lidarscan._mcap_writer._interrupts_deferred`).
"""

from __future__ import annotations

import signal
import threading
from types import FrameType, TracebackType
from typing import Any


class StopRequest:
    """A context manager: while active (main thread only; elsewhere a no-op that never
    requests a stop), SIGINT sets :attr:`requested` instead of raising.

    Calling the object returns :attr:`requested` (a ``stop()`` predicate for the loops)."""

    def __init__(self) -> None:
        self.requested = False
        self._previous: Any = None
        self._installed = False

    def __call__(self) -> bool:
        return self.requested

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        if self.requested:   # the second Ctrl-C: the old behaviour (KeyboardInterrupt)
            raise KeyboardInterrupt
        self.requested = True

    def __enter__(self) -> StopRequest:
        if threading.current_thread() is threading.main_thread():
            previous = signal.getsignal(signal.SIGINT)
            if previous is not None and previous is not signal.SIG_IGN:
                self._previous = previous
                signal.signal(signal.SIGINT, self._handle)
                self._installed = True
        return self

    def __exit__(self, kind: type[BaseException] | None, value: BaseException | None,
                 traceback: TracebackType | None) -> None:
        if self._installed:
            signal.signal(signal.SIGINT, self._previous)
            self._installed = False


def is_interrupt(err: BaseException) -> bool:
    """Whether ``err`` is a KeyboardInterrupt, or an error a KeyboardInterrupt raised inside a
    compiled function turned into (numba's dispatcher: ``SystemError ... with an exception
    set``, whose context is the KeyboardInterrupt)."""
    seen: set[int] = set()
    current: BaseException | None = err
    while current is not None and id(current) not in seen:
        if isinstance(current, KeyboardInterrupt):
            return True
        seen.add(id(current))
        current = current.__cause__ or current.__context__
    return False
