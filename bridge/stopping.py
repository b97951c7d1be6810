"""The stop signals, caught from the process's first moment so that none is ever lost.

SIGTERM (systemd, ``kill``), SIGHUP (the ssh session or terminal closed), SIGQUIT and SIGINT
(Ctrl-C) all mean the same to the bridge: send safe values for ``shutdown_flush_ms`` and exit
0. Python's default for SIGTERM, SIGHUP and SIGQUIT is to die on the spot, so the command line
installs :class:`StopSignals` before it does anything else (parsing, imports, the
configuration); a signal that arrives before the daemon is up is kept and acted on once it is,
and a command other than ``run`` gets the signal's default behaviour back, the signal included.

The handler itself only notes the signal and writes its number to a pipe; the callbacks run in
a thread of their own that reads it. A Python signal handler runs in the main thread between two
of its bytecodes, possibly while that thread holds a lock a callback takes (a
:class:`threading.Event`'s, to wake the supervisor's threads), and a signal that arrives while
a handler runs nests a second handler in the first: a demo's bridge that got SIGINT and SIGTERM
together was found hung so, the second handler waiting for the lock the first held.
"""

from __future__ import annotations

import contextlib
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


class StopSignals:
    """Records the first stop signal and calls the registered callbacks for each (in a thread
    of its own: the module's docstring says why)."""

    def __init__(self) -> None:
        self.received: signal.Signals | None = None
        self._callbacks: list[Callable[[signal.Signals], None]] = []
        self._previous: dict[signal.Signals, Any] = {}
        self._handling = False
        self._pending, self._notify = os.pipe()
        # A storm of signals fills the pipe: the ones it cannot take say nothing new.
        os.set_blocking(self._notify, False)
        self._thread = threading.Thread(target=self._run, name="stop-signals", daemon=True)

    @classmethod
    def install(cls) -> StopSignals:
        """Catch the stop signals from now on (main thread only, as Python requires)."""
        stop = cls()
        stop._thread.start()
        stop._previous = {sig: signal.signal(sig, stop._on_signal) for sig in STOP_SIGNALS}
        return stop

    def _on_signal(self, signum: int, _frame: FrameType | None) -> None:
        # Nothing here may take a lock: plain stores and a write to the pipe. A signal whose
        # handler runs nested in this one says no more than this one does: it returns, so that a
        # storm of signals cannot nest handlers until Python's recursion limit.
        if self._handling:
            return
        self._handling = True
        try:
            if self.received is None:
                self.received = signal.Signals(signum)
            with contextlib.suppress(BlockingIOError):
                os.write(self._notify, bytes((signum,)))
        finally:
            self._handling = False

    def _run(self) -> None:
        while signums := os.read(self._pending, 256):
            for signum in signums:
                for callback in tuple(self._callbacks):
                    callback(signal.Signals(signum))

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
