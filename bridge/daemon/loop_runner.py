"""Where the control loop runs (a process of its own, or a thread of the daemon's), and the safe
values the daemon sends itself when the loop died."""

from __future__ import annotations

import logging
import multiprocessing
import multiprocessing.connection
import signal
import socket
import threading
from typing import Any

import can

from bridge.can_io import SHAREABLE_INTERFACES, open_bus
from bridge.config import BridgeConfig
from bridge.errors import BridgeError
from bridge.escs.drivers import flush_safe_values, make_driver
from bridge.output.mailbox import InputSnapshot, LoopStats, MotorTestBlock, SentCommands
from bridge.output.output_loop import STOP_SIGNALS, LoopSetup, OutputLoop, run_in_process

log = logging.getLogger(__name__)


def loop_mode(config: BridgeConfig) -> str:
    """Where the loop runs: ``[output] loop``, with auto meaning a process of its own for the
    interfaces several processes can open."""
    mode = config.output.loop
    if mode == "auto":
        return "process" if config.can.interface in SHAREABLE_INTERFACES else "thread"
    return mode


class LoopRunner:
    """Runs the control loop in a process of its own or in a thread of this one."""

    def __init__(
        self,
        setup: LoopSetup,
        motor_tests: MotorTestBlock,
        snapshot: InputSnapshot,
        stats: LoopStats,
        relay: socket.socket,
        sent: SentCommands | None = None,
    ) -> None:
        self._stats = stats
        config = setup.config
        self.mode = mode = loop_mode(config)
        self._process: Any = None
        self._thread: threading.Thread | None = None
        self._loop: OutputLoop | None = None
        self._relay = relay
        if mode == "process":
            ctx = multiprocessing.get_context("spawn")
            self._process = ctx.Process(
                target=run_in_process,
                args=(setup, motor_tests, snapshot, stats, relay, sent),
                name="esc-bridge-output",
            )
        else:
            self._loop = OutputLoop(setup, motor_tests, snapshot, stats, relay, sent=sent)
            self._thread = threading.Thread(target=self._run_thread, name="esc-bridge-output")
        self.thread_error: BaseException | None = None

    def _run_thread(self) -> None:
        assert self._loop is not None
        try:
            self._loop.run()
        except BaseException as exc:  # noqa: BLE001 - reported by the supervisor
            self.thread_error = exc

    def start(self) -> None:
        if self._process is not None:
            # The child inherits the blocked signals and unblocks them once its handlers are
            # in place: a SIGTERM or SIGHUP to the group while it starts is delivered then, and
            # ends in its shutdown flush instead of killing it half-started.
            blocked = signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)
            try:
                self._process.start()
            finally:
                signal.pthread_sigmask(signal.SIG_SETMASK, blocked)
            self._relay.close()  # the child has its copy; ours would hide the child's death
        elif self._thread is not None:
            self._thread.start()

    def alive(self) -> bool:
        if self._process is not None:
            return bool(self._process.is_alive())
        return self._thread is not None and self._thread.is_alive()

    def wait_for_exit(self, timeout_s: float) -> bool:
        """Block until the loop ends or ``timeout_s`` passes; True when it ended."""
        if self._process is not None:
            return bool(multiprocessing.connection.wait([self._process.sentinel], timeout_s))
        if self._thread is not None:
            self._thread.join(timeout_s)
        return not self.alive()

    def request_stop(self) -> None:
        self._stats["stop_requested"] = 1  # read by the loop every tick, in a process or thread

    def join(self, timeout_s: float) -> None:
        if self._process is not None:
            self._process.join(timeout_s)
            if self._process.is_alive():
                log.error("output loop did not stop in %.1f s; terminating it", timeout_s)
                self._process.kill()
                self._process.join()
        elif self._thread is not None:
            self._thread.join(timeout_s)

    def loop_bus(self) -> can.BusABC | None:
        """The thread-mode loop's bus handle (None in process mode or while it is closed)."""
        return self._loop.bus if self._loop is not None else None

    @property
    def exitcode(self) -> int | None:
        return None if self._process is None else self._process.exitcode


def send_safe_values_after_death(config: BridgeConfig) -> int:
    """The control loop died: send the safe values from here, the survivor, for
    ``shutdown_flush_ms`` on a handle of our own; returns the frames sent (0 when the bus cannot
    be opened: the ESCs' own command timeouts then stop the motors)."""
    try:
        bus = open_bus(config.can, config.bitrate)
    except BridgeError as exc:
        log.error("cannot send safe values after the output loop died: %s", exc)
        return 0
    driver = make_driver(config)
    period_ns = round(1e9 / (config.rate_hz * driver.ticks_per_cycle))
    sent = 0

    def send(frames: list[can.Message]) -> None:
        nonlocal sent
        for frame in frames:
            try:
                bus.send(frame, timeout=0)
            except (can.CanError, OSError):
                continue
            sent += 1

    try:
        flush_safe_values(send, driver, period_ns, max(config.output.shutdown_flush_ms, 100))
    finally:
        bus.shutdown()
    return sent
