"""The output loop: the hot path and the safety path.

Every tick it reads the newest commands from the mailbox, decides whether they may be sent
(armed, fresh, valid, not stopping) and sends either them, rate-limited by the slew limiter, or
the safe values. While the autopilot is disarmed a motor test from the mailbox (a ground
station's MAV_CMD_DO_MOTOR_TEST, see :mod:`bridge.motor_test`) takes the place of the safe
values: one motor at its test throttle, every other one safe, until the test's time is up or
the autopilot arms, whichever comes first. It sleeps to absolute deadlines on the monotonic
clock, so it does not drift; a tick it wakes too late for is counted as an overrun and skipped,
never caught up in a burst.

Nothing here blocks, logs or waits on another part of the bridge: sends are non-blocking and
a failed one is counted (the bus is reopened with backoff when it is gone), the mailbox and the
counters are lock-free shared memory, and the supervisor reads the counters to log and report.
Run in a process of its own (the default where the bus allows it), the loop is also free of the
main process's GIL; with SCHED_FIFO priority (root or CAP_SYS_NICE) it wakes within tens of µs.
"""

from __future__ import annotations

import gc
import logging
import os
import random
import select
import signal
import time
from dataclasses import dataclass
from multiprocessing.connection import Connection

import can

from bridge.can_io import is_transient, open_bus
from bridge.config import BridgeConfig
from bridge.errors import BridgeError
from bridge.escs.drivers import make_driver
from bridge.mailbox import LATENESS_RING, CommandMailbox, LoopState, LoopStats, MotorTest
from bridge.mixer import MixerDefinition, SlewLimiter
from bridge.motor_test import test_frames

log = logging.getLogger(__name__)

REOPEN_BACKOFF_S = (0.1, 2.0)  # first and longest wait before reopening a bus that is gone
PARENT_CHECK_TICKS = 64  # how often a loop process checks that its supervisor still lives
IMMEDIATE_MAX_RATE_FACTOR = 2  # latency = "immediate" sends at most this many times the rate


@dataclass(frozen=True)
class LoopSetup:
    """Everything the loop needs, picklable so it can start a process of its own."""

    config: BridgeConfig  # with the ESC lists filled in
    mixer: MixerDefinition  # the loop applies its slew limits
    log_level: int = logging.INFO


def set_realtime(priority: int) -> bool:
    """Ask for SCHED_FIFO at ``priority`` for the calling thread; False when not permitted."""
    if priority <= 0 or not hasattr(os, "sched_setscheduler"):
        return False
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (PermissionError, OSError):
        return False
    return True


class OutputLoop:
    """One output loop over one bus. :meth:`run` returns after the shutdown flush."""

    def __init__(
        self,
        setup: LoopSetup,
        mailbox: CommandMailbox,
        stats: LoopStats,
        wake_fd: int | None,
    ) -> None:
        config = setup.config
        self._config = config
        self._mailbox = mailbox
        self._stats = stats
        self._wake_fd = wake_fd if config.output.latency == "immediate" else None
        self._driver = make_driver(config)
        self._slew = SlewLimiter.for_definition(setup.mixer)
        self._zeros = [0.0] * len(setup.mixer.outputs)
        self._period_ns = round(1e9 / (config.rate_hz * self._driver.ticks_per_cycle))
        self._timeout_ns = config.output.input_timeout_ms * 1_000_000
        self._flush_ns = config.output.shutdown_flush_ms * 1_000_000
        self._bus: can.BusABC | None = None
        self._reopen_at_ns = 0
        self._backoff_s = REOPEN_BACKOFF_S[0]

    @property
    def bus(self) -> can.BusABC | None:
        """The bus handle in use (None while closed), for a reader sharing it in thread mode."""
        return self._bus

    def request_stop(self) -> None:
        """Start the shutdown flush (also what the supervisor's ``stop_requested`` does)."""
        self._stats["stop_requested"] = 1

    def run(self) -> None:
        stats = self._stats
        try:
            self._bus = open_bus(self._config.can, self._config.bitrate)
        except BridgeError:
            stats["state"] = LoopState.FAILED
            raise
        stats["realtime"] = set_realtime(self._config.output.realtime_priority)
        # The loop allocates nothing that needs the cycle collector; a collection pass in the
        # middle of a tick would cost milliseconds, so it is frozen out for the loop's life.
        gc.collect()
        gc.freeze()
        gc.disable()
        try:
            self._loop()
        finally:
            gc.enable()
            stats["state"] = LoopState.STOPPED
            if self._bus is not None:
                self._bus.shutdown()

    def _loop(self) -> None:
        # One flat function on purpose: locals, not attribute look-ups, on every tick.
        counters = self._stats.counters
        slot = self._stats.slot
        state_i, ticks_i, sent_i = slot("state"), slot("ticks"), slot("frames_sent")
        overruns_i, immediate_i = slot("overruns"), slot("immediate_sends")
        lateness_count_i, stop_i = slot("lateness_count"), slot("stop_requested")
        tick_errors_i, test_motor_i = slot("tick_errors"), slot("motor_test_motor")
        lateness = self._stats.lateness_ring
        mailbox, driver, slew = self._mailbox, self._driver, self._slew
        require_armed = self._config.output.require_armed
        period_ns, timeout_ns = self._period_ns, self._timeout_ns
        min_gap_ns = period_ns // IMMEDIATE_MAX_RATE_FACTOR
        keepalive_ns = period_ns * 3 // 2
        wake_fd = self._wake_fd
        monotonic_ns, sleep = time.monotonic_ns, time.sleep
        parent = os.getppid()
        # A motor test (MAV_CMD_DO_MOTOR_TEST): the newest one read and when it ends; a vector
        # of zeros but for the motor under test, made once and updated in place.
        test: MotorTest | None = None
        test_seq = test_until_ns = 0
        test_index = -1
        test_fractions = [0.0] * len(self._zeros)

        state = LoopState.NO_INPUT
        counters[state_i] = state
        stop_at_ns = 0
        tick = 0
        last_ns = next_ns = monotonic_ns()
        while True:
            input_tick = False
            delay_ns = next_ns - monotonic_ns()
            if wake_fd is not None:
                while delay_ns > 0 and select.select([wake_fd], [], [], delay_ns / 1e9)[0]:
                    os.read(wake_fd, 4096)
                    # Fresh input goes out now, or as soon as the frame-rate cap allows: never
                    # within min_gap of the last frame, so an input flood cannot flood the bus.
                    next_ns = min(next_ns, max(monotonic_ns(), last_ns + min_gap_ns))
                    input_tick = True
                    delay_ns = next_ns - monotonic_ns()
            elif delay_ns > 0:
                sleep(delay_ns / 1e9)
            now = monotonic_ns()
            n = counters[lateness_count_i]
            lateness[n % LATENESS_RING] = (now - next_ns) // 1000
            counters[lateness_count_i] = n + 1

            if not stop_at_ns and (
                counters[stop_i] or (tick % PARENT_CHECK_TICKS == 0 and os.getppid() != parent)
            ):
                stop_at_ns = now + self._flush_ns
            commands = mailbox.read()
            fresh_test = mailbox.read_motor_test(test_seq)  # the one extra read per tick
            if fresh_test is not None:
                test, test_seq, test_until_ns = fresh_test, fresh_test.seq, fresh_test.until_ns
            testing = False
            if now < test_until_ns:
                if mailbox.read_armed():
                    test_until_ns = 0  # arming ends a motor test for good, at once
                else:
                    testing = True
            if stop_at_ns:
                new_state = LoopState.STOPPING
            elif testing:
                new_state = LoopState.MOTOR_TEST
            elif commands is None:
                new_state = LoopState.NO_INPUT
            elif require_armed and not mailbox.read_armed():
                new_state = LoopState.DISARMED
            elif now - commands.time_ns > timeout_ns:
                new_state = LoopState.STALE
            elif not commands.valid:
                new_state = LoopState.INVALID
            else:
                new_state = LoopState.RUNNING
            if new_state != state:
                if new_state == LoopState.RUNNING:
                    slew.reset(self._zeros)  # after any safe spell, spool up from stopped
                if state == LoopState.MOTOR_TEST and test_index >= 0:
                    test_fractions[test_index] = 0.0
                    test_index = -1
                    counters[test_motor_i] = 0
                state = new_state
                counters[state_i] = state

            frames = None
            if state == LoopState.MOTOR_TEST and test is not None:
                index = test.index_at(now)
                if index != test_index:
                    if test_index >= 0:
                        test_fractions[test_index] = 0.0
                    test_index = index
                    counters[test_motor_i] = index + 1
                if index >= 0:
                    test_fractions[index] = test.fraction
                    try:
                        frames = test_frames(driver, tick, test_fractions, index)
                    except Exception:  # noqa: BLE001 - as below: safe values this tick
                        counters[tick_errors_i] += 1
            elif state == LoopState.RUNNING and commands is not None:
                try:
                    frames = driver.tick_frames(
                        tick, slew.apply(commands.fractions, (now - last_ns) / 1e9)
                    )
                # Any fault in mixing or encoding means safe values this tick, never a dead loop.
                except Exception:  # noqa: BLE001
                    counters[tick_errors_i] += 1
            if frames is None:
                frames = driver.safe_frames(tick)
            counters[sent_i] += self._send(frames, now)
            counters[ticks_i] += 1
            last_ns = now
            tick += 1

            if stop_at_ns and now >= stop_at_ns:
                return
            if input_tick:
                # Re-phased to the input: the fixed tick becomes a keep-alive that fires only
                # when the next input is late, so it never races an input arriving on time.
                counters[immediate_i] += 1
                next_ns = now + keepalive_ns
                continue
            next_ns += period_ns
            behind_ns = now - next_ns
            if behind_ns >= period_ns:
                missed = behind_ns // period_ns
                next_ns += missed * period_ns
                counters[overruns_i] += missed

    def _send(self, frames: list[can.Message], now_ns: int) -> int:
        """Send without blocking; count failures; reopen a bus that is gone, with backoff."""
        bus = self._bus
        if bus is None:
            if now_ns < self._reopen_at_ns:
                return 0
            bus = self._reopen()
            if bus is None:
                return 0
        sent = 0
        for frame in frames:
            try:
                bus.send(frame, timeout=0)
            except (can.CanError, OSError) as exc:
                self._stats["send_errors"] += 1
                if not is_transient(exc):
                    bus.shutdown()
                    self._bus = None
                    self._reopen_at_ns = now_ns + int(self._backoff_s * 1e9)
                break  # the rest of this tick would fail the same way
            sent += 1
        return sent

    def _reopen(self) -> can.BusABC | None:
        try:
            self._bus = open_bus(self._config.can, self._config.bitrate)
        except BridgeError:
            wait_s = self._backoff_s * (0.5 + random.random())  # jitter: no lock-step retries
            self._backoff_s = min(self._backoff_s * 2, REOPEN_BACKOFF_S[1])
            self._reopen_at_ns = time.monotonic_ns() + int(wait_s * 1e9)
            return None
        self._backoff_s = REOPEN_BACKOFF_S[0]
        self._stats["bus_reopens"] += 1
        return self._bus


def run_in_process(
    setup: LoopSetup, mailbox: CommandMailbox, stats: LoopStats, wake: Connection | None
) -> None:
    """Entry point of the loop's own process (spawned by the supervisor)."""
    logging.basicConfig(
        level=setup.log_level, format="%(asctime)s %(levelname)s esc-bridge[output] %(message)s"
    )
    # Ctrl-C reaches the whole process group; the supervisor decides when the loop stops, and
    # SIGTERM sent to this process alone still ends in the shutdown flush.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    loop = OutputLoop(setup, mailbox, stats, wake.fileno() if wake is not None else None)
    signal.signal(signal.SIGTERM, lambda _signum, _frame: loop.request_stop())
    try:
        loop.run()
    except BridgeError as exc:
        log.error("%s", exc)
        raise SystemExit(1) from None
