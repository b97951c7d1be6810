"""The stop signals, caught from the process's first moment so that none is ever lost.

SIGTERM (systemd, ``kill``), SIGHUP (the ssh session or terminal closed), SIGQUIT and SIGINT
(Ctrl-C) all mean the same to the bridge: send safe values for ``shutdown_flush_ms`` and exit
0. Python's default for SIGTERM, SIGHUP and SIGQUIT is to die on the spot, so the command line
installs :class:`StopSignals` before it does anything else (parsing, imports, the
configuration); a signal that arrives before the daemon is up is kept and acted on once it is,
and a command other than ``run`` gets the signal's default behaviour back, the signal included.
"""

from __future__ import annotations

import os
import signal
from collections.abc import Callable
from types import FrameType
from typing import Any

STOP_SIGNALS: tuple[signal.Signals, ...] = (
    signal.SIGTERM,
    signal.SIGHUP,
    signal.SIGQUIT,
    signal.SIGINT,
)


class StopSignals:
    """Records the first stop signal and calls the registered callbacks (in the main thread,
    as Python runs signal handlers)."""

    def __init__(self) -> None:
        self.received: signal.Signals | None = None
        self._callbacks: list[Callable[[signal.Signals], None]] = []
        self._previous: dict[signal.Signals, Any] = {}

    @classmethod
    def install(cls) -> StopSignals:
        """Catch the stop signals from now on (main thread only, as Python requires)."""
        stop = cls()
        stop._previous = {sig: signal.signal(sig, stop._on_signal) for sig in STOP_SIGNALS}
        return stop

    def _on_signal(self, signum: int, _frame: FrameType | None) -> None:
        sig = signal.Signals(signum)
        if self.received is None:
            self.received = sig
        for callback in tuple(self._callbacks):
            callback(sig)

    def on_stop(self, callback: Callable[[signal.Signals], None]) -> None:
        """Call ``callback`` on every stop signal from now on, and at once if one came."""
        self._callbacks.append(callback)
        if self.received is not None:
            callback(self.received)

    def release(self) -> None:
        """Give the signals their previous handlers back; a signal caught meanwhile is raised
        again, so it does what it would have done (end the process, or KeyboardInterrupt)."""
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous = {}
        if self.received is not None:
            os.kill(os.getpid(), self.received)
