"""The stop signals, caught from the process's first moment so that none is ever lost.

SIGTERM (systemd, ``kill``), SIGHUP (the ssh session or terminal closed), SIGQUIT and SIGINT
(Ctrl-C) all mean the same to the bridge: send safe values for ``shutdown_flush_ms`` and exit
0. Python's default for SIGTERM, SIGHUP and SIGQUIT is to die on the spot, so the command line
installs :class:`StopSignals` before it does anything else (parsing, imports, the
configuration); a signal that arrives before the daemon is up is kept and acted on once it is,
and a command other than ``run`` gets the signal's default behaviour back, the signal included.

The callbacks run in a thread of their own, woken through :func:`signal.set_wakeup_fd` (Python's
C-level handler writes each signal's number to a pipe); the Python handler only notes the first
signal. A Python handler runs in the main thread between two of its bytecodes, possibly while
that thread holds a lock a callback takes (a :class:`threading.Event`'s, to wake the
supervisor's threads), and a signal that arrives while a handler runs nests a second handler in
the first: a demo's bridge that got SIGINT and SIGTERM together was found hung so, the second
handler waiting for the lock the first held.
"""

from __future__ import annotations

import os
import signal
import threading
from collections.abc import Callable
from types import FrameType
from typing import Any

STOP_SIGNALS: tuple[signal.Signals, ...] = (
    signal.SIGTERM,
    signal.SIGHUP,
    signal.SIGQUIT,
    signal.SIGINT,
)
_BY_NUMBER: dict[int, signal.Signals] = {int(sig): sig for sig in STOP_SIGNALS}


class StopSignals:
    """Records the first stop signal and calls the registered callbacks for each (in a thread
    of its own: the module's docstring says why)."""

    def __init__(self) -> None:
        self.received: signal.Signals | None = None
        self._callbacks: list[Callable[[signal.Signals], None]] = []
        self._previous: dict[signal.Signals, Any] = {}
        self._pending, self._notify = os.pipe()
        os.set_blocking(self._notify, False)  # as set_wakeup_fd requires
        self._thread = threading.Thread(target=self._run, name="stop-signals", daemon=True)

    @classmethod
    def install(cls) -> StopSignals:
        """Catch the stop signals from now on (main thread only, as Python requires)."""
        stop = cls()
        stop._thread.start()
        # A storm of signals fills the pipe: the numbers it cannot take say nothing new.
        signal.set_wakeup_fd(stop._notify, warn_on_full_buffer=False)
        stop._previous = {sig: signal.signal(sig, stop._on_signal) for sig in STOP_SIGNALS}
        return stop

    def _on_signal(self, signum: int, _frame: FrameType | None) -> None:
        # A store and a lookup, nothing that takes a lock or calls into Python code (in which a
        # storm of signals would nest handlers): the wakeup pipe has the number already.
        if self.received is None:
            self.received = _BY_NUMBER[signum]

    def _run(self) -> None:
        while signums := os.read(self._pending, 256):
            for signum in signums:
                sig = _BY_NUMBER.get(signum)
                if sig is None:  # a signal with another Python handler: not ours
                    continue
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
        signal.set_wakeup_fd(-1)
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous = {}
        if self.received is not None:
            os.kill(os.getpid(), self.received)
