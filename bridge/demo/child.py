"""A child process of ``esc-bridge demo`` (the bridge, the simulator): started in a session of
its own, its last lines of output kept, stopped with SIGTERM and, if need be, SIGKILL, and sent
SIGTERM by the kernel if the demo dies first (killed, or crashed): never left running alone."""

from __future__ import annotations

import collections
import ctypes
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Callable, Sequence
from typing import Final

LAST_LINES: Final = 25
"""Lines of a child's output kept to show when it dies."""


PR_SET_PDEATHSIG: Final = 1
"""prctl(2): the signal this process gets when the thread that started it ends."""


def _terminated_with(parent_pid: int) -> Callable[[], None] | None:
    """What the child runs before exec (Linux): SIGTERM to it when the demo dies, and at once
    if the demo died before that was set. The C function is looked up here, in the parent:
    between fork and exec the child calls it and nothing else."""
    if not sys.platform.startswith("linux"):
        return None
    prctl = ctypes.CDLL(None, use_errno=True).prctl

    def set_parent_death_signal() -> None:
        prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
        if os.getppid() != parent_pid:
            os.kill(os.getpid(), signal.SIGTERM)

    return set_parent_death_signal


class Child:
    """A subprocess whose output (stdout and stderr merged) is kept, last lines only."""

    def __init__(self, name: str, argv: Sequence[str]) -> None:
        """Start it, in a session of its own (the terminal's Ctrl-C does not reach it). Call
        from the thread that stops it: the kernel signals the child when this thread ends.

        Raises:
            OSError: it cannot be started.
        """
        self.name = name
        self.argv = list(argv)
        self.returncode: int | None = None
        self._lines: collections.deque[str] = collections.deque(maxlen=LAST_LINES)
        self._lock = threading.Lock()
        self.proc = subprocess.Popen(
            self.argv,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            errors="replace",
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
            start_new_session=True,
            preexec_fn=_terminated_with(os.getpid()),
        )
        self._reader = threading.Thread(target=self._read, name=f"demo-{name}-output", daemon=True)
        self._reader.start()

    @property
    def pid(self) -> int:
        return self.proc.pid

    def _read(self) -> None:
        stream = self.proc.stdout
        if stream is None:
            return
        for line in stream:
            with self._lock:
                self._lines.append(line.rstrip("\n"))

    def last_lines(self) -> list[str]:
        with self._lock:
            return list(self._lines)

    def poll(self) -> int | None:
        self.returncode = self.proc.poll()
        return self.returncode

    def stop(self, timeout_s: float) -> tuple[int, bool]:
        """SIGTERM and wait; SIGKILL when it does not exit in time. (exit status, killed).
        Stopping a child that already exited only collects its status."""
        killed = False
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
                killed = True
        self._reader.join(2.0)
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        self.returncode = self.proc.returncode
        return self.proc.returncode, killed
