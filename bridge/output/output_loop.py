"""The control loop: the hot path and the safety path, autopilot bytes in to CAN frames out.

One thread, in a process of its own where the bus allows it, with SCHED_FIFO priority when
permitted, owns everything between the autopilot and the ESCs: the autopilot's link (read and
decoded by :class:`~bridge.output.autopilot_input.AutopilotInput`, which mixes each input as it
arrives; the ESC driver then makes its frames, so that a tick only decides and sends), the
safety decision (:func:`bridge.output.safety.decide`) and the CAN transmit handle.
Nothing else runs there, so nothing else can hold it up: telemetry, Zenoh, logging and ground
station commands live in the main process, which may stall without consequence.

It waits in ``select`` on the autopilot's link and the relay from the main process until the
next tick's absolute deadline on the monotonic clock, so it does not drift; a tick it wakes too
late for is counted as an overrun and skipped, never caught up in a burst. Every tick it sends
either the newest input's commands, rate-limited by the slew limiter, or the safe values, as
:func:`~bridge.output.safety.decide` says; while the autopilot is disarmed a motor test from the
main process (a ground station's MAV_CMD_DO_MOTOR_TEST, see :mod:`bridge.output.motor_test`)
takes the place of the safe values: one motor at its test throttle, every other one safe.
What one tick does is :meth:`OutputLoop.tick` (a test drives it on its own, after
:meth:`OutputLoop.open`); when ticks happen is the loop's.

It stops with a flush of safe values for ``shutdown_flush_ms`` when asked (the supervisor's
``stop_requested``), on SIGTERM, SIGHUP, SIGQUIT or SIGINT, and when the main process dies (its
end of the relay reads as end of file; its parent id changes). Sends are non-blocking and a
failed one is counted; on SocketCAN a tick is never written behind frames the kernel still
holds (:mod:`bridge.output.transmit`), and a bus that is gone is reopened with a backoff that
grows while it stays gone. Counters are lock-free shared memory that the supervisor samples to
log and report.
"""

from __future__ import annotations

import contextlib
import gc
import logging
import os
import random
import select
import signal
import socket
import time
from dataclasses import dataclass

import can

from bridge.backoff import Backoff
from bridge.can_io import Receive, open_bus
from bridge.config import BridgeConfig
from bridge.errors import BridgeError
from bridge.escs.family import EscDriver
from bridge.mavlink.relay import LoopEnd
from bridge.output.autopilot_input import AutopilotInput, InputSetup
from bridge.output.busload import IMMEDIATE_MAX_RATE_FACTOR
from bridge.output.mailbox import (
    LATENESS_RING,
    SENT_COMMANDS,
    SENT_SAFE,
    SENT_TEST,
    InputSnapshot,
    LoopStats,
    MotorTest,
    MotorTestBlock,
    SentCommands,
)
from bridge.output.motor_test import test_frames
from bridge.output.safety import ControlInputs, LoopState, SafetyLimits, decide, motor_test_ended
from bridge.output.slew import SlewLimiter
from bridge.output.transmit import BusGone, Transmitter, TxState, transmitter_for

log = logging.getLogger(__name__)

# First and longest wait before reopening a bus that is gone; the wait doubles while the
# interface stays unusable (each attempt fails, or the bus opens but no tick goes out) and is
# back to the first once a whole tick went out.
REOPEN_BACKOFF_S = (0.1, 2.0)
PARENT_CHECK_TICKS = 64  # how often the loop checks that its supervisor still lives
STOP_SIGNALS = (signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT, signal.SIGINT)


@dataclass(frozen=True)
class LoopSetup:
    """Everything the loop needs, picklable so it can start a process of its own."""

    config: BridgeConfig  # with the ESC lists filled in
    input: InputSetup
    log_level: int = logging.INFO
    # What the loop's bus handle receives: nothing (it only sends), unless the main process's
    # reader shares it (thread mode on an interface only one handle can open).
    bus_receive: Receive = "none"


def set_realtime(priority: int) -> bool:
    """Ask for SCHED_FIFO at ``priority`` for the calling thread; False when not permitted."""
    if priority <= 0 or not hasattr(os, "sched_setscheduler"):
        return False
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (PermissionError, OSError):
        return False
    return True


def safety_limits(config: BridgeConfig) -> SafetyLimits:
    """The configuration's safety settings in the loop's units."""
    output = config.output
    return SafetyLimits(
        require_armed=output.require_armed,
        input_timeout_ns=output.input_timeout_ms * 1_000_000,
        arming_timeout_ns=output.arming_timeout_ms * 1_000_000,
    )


class CommandSelector:
    """Chooses, each tick, what goes on the bus: the newest input's commands (slew-limited),
    one motor's test throttle, or the safe values, as :func:`~bridge.output.safety.decide` says.

    The loop's per-tick safety path, apart from the loop so that a model-based test can drive
    exactly this code through random sequences of events (``tests/output/test_safety_model.py``).
    """

    def __init__(
        self,
        driver: EscDriver,
        slew: SlewLimiter,
        limits: SafetyLimits,
        inputs: ControlInputs,
        n_outputs: int,
    ) -> None:
        self.driver = driver
        self._slew = slew
        self._slewing = slew.limits
        self._limits = limits
        self._inputs = inputs
        self._zeros = [0.0] * n_outputs
        self.state = LoopState.NO_INPUT
        self.faults = 0
        """Ticks whose commands could not be encoded: the safe values went out instead."""
        # The motor test read last, and a vector of zeros but for the motor under test, made
        # once and updated in place.
        self._test: MotorTest | None = None
        self._test_fractions = [0.0] * n_outputs
        self.test_index = -1
        """The output a motor test spins now, 0-based; -1 = none."""
        self.sent_kind = SENT_SAFE
        self.sent_fractions: list[float] = self._zeros
        """What the last tick's frames carry: its kind (:data:`SENT_COMMANDS`, the commands of
        ``sent_fractions``; :data:`SENT_SAFE`; :data:`SENT_TEST`, motor ``test_index`` at its
        test throttle), for the main process. A new list whenever the commands change."""

    def start_motor_test(self, test: MotorTest) -> None:
        """A motor test read from the main process (count 0: stop any)."""
        self._test = test
        self._inputs.motor_test_until_ns = test.until_ns
        self._test_fractions = list(self._test_fractions)  # new commands: a new list

    def select(
        self, tick: int, now_ns: int, fractions: list[float] | None, dt_s: float
    ) -> list[can.Message]:
        """The frames for ``tick`` at ``now_ns``; ``fractions``: the newest input's mix (None:
        none, or invalid); ``dt_s``: the time since the last tick, for the slew limiter."""
        inputs, limits = self._inputs, self._limits
        if motor_test_ended(inputs, now_ns, limits):
            inputs.motor_test_until_ns = 0  # arming (or losing the autopilot) ends it
        state = decide(inputs, now_ns, limits, self.state)
        if state != self.state:
            if state == LoopState.RUNNING:
                self._slew.reset(self._zeros)  # after any safe spell, spool up from stopped
            if self.state == LoopState.MOTOR_TEST:
                self._spin(-1)
            self.state = state
        driver = self.driver
        try:
            if state == LoopState.MOTOR_TEST and self._test is not None:
                index = self._test.index_at(now_ns)
                self._spin(index)
                if index >= 0:
                    frames = test_frames(driver, tick, self._test_fractions, index)
                    self.sent_kind, self.sent_fractions = SENT_TEST, self._test_fractions
                    return frames
            elif state == LoopState.RUNNING and fractions is not None:
                # Without slew rates the commands are the input's own (a list per input).
                if self._slewing:
                    fractions = self._slew.apply(fractions, dt_s)
                frames = driver.tick_frames(tick, fractions)
                self.sent_kind, self.sent_fractions = SENT_COMMANDS, fractions
                return frames
        # Any fault in slewing or encoding means safe values this tick, never a dead loop.
        except Exception:  # noqa: BLE001
            self.faults += 1
        self.sent_kind = SENT_SAFE
        return driver.safe_frames(tick)

    def prepare(self, fractions: list[float] | None) -> None:
        """Have the driver make a new input's frames now, between ticks, when the next tick
        would send them as they are (running, no slew rates): that tick then only stamps and
        sends them. Decides nothing: the tick still does."""
        if fractions is None or self.state != LoopState.RUNNING or self._slewing:
            return
        # Any fault is the tick's to meet: it makes them again, and sends the safe values if
        # it cannot.
        with contextlib.suppress(Exception):
            self.driver.prepare(fractions)

    def _spin(self, index: int) -> None:
        """Make ``index`` the motor under test (-1: none), the others at 0."""
        if index != self.test_index:
            self._test_fractions = [0.0] * len(self._test_fractions)  # new commands: a new list
            self.test_index = index
        if index >= 0 and self._test is not None:
            self._test_fractions[index] = self._test.fraction


class OutputLoop:
    """The control loop over one autopilot link and one bus. :meth:`run` returns after the
    shutdown flush."""

    def __init__(
        self,
        setup: LoopSetup,
        motor_tests: MotorTestBlock,
        snapshot: InputSnapshot,
        stats: LoopStats,
        relay: socket.socket | None,
        watch_parent: bool = False,
        sent: SentCommands | None = None,
    ) -> None:
        """``watch_parent``: stop when the parent process goes (the loop's own process).
        ``sent``: where the commands sent go for the main process (None: nobody reads them)."""
        config = setup.config
        self._config = config
        self._bus_receive = setup.bus_receive
        self._motor_tests = motor_tests
        self._stats = stats
        driver = config.family.driver(config.esc_setup)
        self._period_ns = round(1e9 / (config.rate_hz * driver.ticks_per_cycle))
        self._flush_ns = config.output.shutdown_flush_ms * 1_000_000
        self._inputs = ControlInputs()
        self._selector = CommandSelector(
            driver,
            SlewLimiter.for_definition(setup.input.mixer),
            safety_limits(config),
            self._inputs,
            len(setup.input.mixer.outputs),
        )
        self._relay = LoopEnd(relay) if relay is not None else None
        self._relay_open = relay is not None
        self._input = AutopilotInput(
            config, setup.input, self._inputs, stats, snapshot, self._relay
        )
        self._bus: can.BusABC | None = None
        self._tx: Transmitter | None = None
        # Ticks may be held back (frames of an earlier one still in the kernel) this long before
        # the bus is reported stuck: as long as the bridge would call its own input stale.
        self._stuck_after_ns = config.output.input_timeout_ms * 1_000_000
        self._reopen_at_ns = 0
        self._backoff = Backoff(*REOPEN_BACKOFF_S)
        # The counts of the transmitters before the current one (a reopen starts a new one).
        self._tx_before = self._held_before = self._probes_before = 0
        # The tick's state: its number, the last one's time, the newest motor test read, when
        # the shutdown flush ends (0: not stopping), the parent to watch (0: none).
        self._tick = 0
        self._last_ns = 0
        self._test_seq = 0
        self._stop_at_ns = 0
        self._parent = os.getppid() if watch_parent else 0
        n_outputs = len(setup.input.mixer.outputs)
        self._sent = sent if sent is not None else SentCommands(n_outputs)
        self._shared_kind, self._shared_fractions = 0, self._selector.sent_fractions
        self._counters = stats.counters
        self._lateness = stats.lateness_ring
        slot = stats.slot
        self._i_state, self._i_ticks = slot("state"), slot("ticks")
        self._i_sent, self._i_tick_errors = slot("frames_sent"), slot("tick_errors")
        self._i_lateness_count, self._i_stop = slot("lateness_count"), slot("stop_requested")
        self._i_test_motor, self._i_redecided = slot("motor_test_motor"), slot("redecided")
        self._i_left_late = slot("left_late")
        self._i_entered = slot("entered_starting")  # + a LoopState: its entry count
        self._i_tx_state, self._i_held = slot("tx_state"), slot("ticks_held")
        self._i_send_errors, self._i_probes = slot("send_errors"), slot("tx_probes")
        self._i_tx_entered = slot("entered_tx_moving")  # + a TxState: its entry count

    @property
    def bus(self) -> can.BusABC | None:
        """The bus handle in use (None while closed), for a reader sharing it in thread mode."""
        return self._bus

    def request_stop(self) -> None:
        """Start the shutdown flush (also what the supervisor's ``stop_requested`` does)."""
        self._stats["stop_requested"] = 1

    def run(self) -> None:
        """Open the bus and the autopilot's link, loop until stopped, flush, close.

        Raises:
            BridgeError: the bus or the link could not be opened (state FAILED).
        """
        # Before open(), which ends the STARTING state: the supervisor reads this flag as soon
        # as the state changes.
        self._stats["realtime"] = set_realtime(self._config.output.realtime_priority)
        self.open()
        # The loop allocates nothing that needs the cycle collector; a collection pass in the
        # middle of a tick would cost milliseconds, so it is frozen out for the loop's life.
        gc.collect()
        gc.freeze()
        gc.disable()
        try:
            self._loop()
        finally:
            gc.enable()
            self.close()

    def open(self) -> None:
        """Open the bus and the autopilot's link (what :meth:`run` does first).

        Raises:
            BridgeError: the bus or the link could not be opened (state FAILED).
        """
        try:
            self._bus = self._open_bus()
            self._tx = transmitter_for(self._bus, self._stuck_after_ns)
            self._input.open()
        except BridgeError:
            self._stats["state"] = LoopState.FAILED
            if self._bus is not None:
                self._bus.shutdown()
            raise
        self._last_ns = time.monotonic_ns()
        self._counters[self._i_state] = self._selector.state

    def close(self) -> None:
        """Close the link, the relay and the bus (state STOPPED)."""
        self._stats["state"] = LoopState.STOPPED
        self._input.close()
        if self._relay is not None:
            self._relay.close()
        if self._bus is not None:
            self._bus.shutdown()

    def read(self, now_ns: int) -> bool:
        """Take what arrived at ``now_ns`` (the autopilot's link, the main process's relay);
        True when a new input was acted on."""
        fresh = self._input.on_readable(now_ns)
        self._exchange_with_main(now_ns)
        return fresh

    def tick(self, now_ns: int, due_ns: int) -> bool:
        """One tick at ``now_ns``, due at ``due_ns``: what the safety decision allows (the
        newest input's commands, a motor test from the main process, or the safe values) goes
        on the bus, and the counters follow. False when the shutdown flush is over."""
        counters = self._counters
        late_us = (now_ns - due_ns) // 1000
        tick = self._tick
        parent = self._parent
        if not self._stop_at_ns and (
            counters[self._i_stop]
            or (parent and tick % PARENT_CHECK_TICKS == 0 and os.getppid() != parent)
        ):
            self._stop_at_ns = now_ns + self._flush_ns
        stop_at_ns = self._stop_at_ns
        self._inputs.stopping = stop_at_ns != 0
        selector = self._selector
        fresh_test = self._motor_tests.read_motor_test(self._test_seq)  # one 8-byte load
        if fresh_test is not None:
            self._test_seq = fresh_test.seq
            selector.start_motor_test(fresh_test)
        frames = selector.select(
            tick, now_ns, self._input.fractions, (now_ns - self._last_ns) / 1e9
        )
        # The decision holds for ``now_ns``; a loop stopped or starved between taking the time
        # and sending (SIGSTOP, swap, a higher-priority task, a virtual CPU the host took away)
        # would carry a decision that may no longer hold: running commands from an input gone
        # stale meanwhile, or older than the inputs that arrived meanwhile. A frame never
        # leaves over a period after the time its decision was made for, nor on what was read
        # before it.
        sending_ns = time.monotonic_ns()
        if sending_ns - now_ns > self._period_ns:
            counters[self._i_redecided] += 1
            self._input.on_readable(sending_ns)
            frames = selector.select(
                tick, sending_ns, self._input.fractions, (sending_ns - now_ns) / 1e9
            )
            now_ns = sending_ns
        # The frames first, the bookkeeping after: the work between the wake-up and the send
        # is the same every tick, so frames leave at even intervals.
        counters[self._i_sent] += self._send(frames, now_ns)
        if frames and time.monotonic_ns() - now_ns > self._period_ns:
            # Held up between the last look at the clock and the frames' leaving (its CPU
            # taken between two instructions): nothing in the process can prevent that, but
            # the frames carried a decision over a period old, so it is counted and logged.
            counters[self._i_left_late] += 1
        n = counters[self._i_lateness_count]
        self._lateness[n % LATENESS_RING] = late_us
        counters[self._i_lateness_count] = n + 1
        sent = selector.sent_fractions
        if sent is not self._shared_fractions or selector.sent_kind != self._shared_kind:
            # What goes out changed (a new input, a motor test, safe values): a new list.
            self._shared_kind, self._shared_fractions = selector.sent_kind, sent
            self._sent.write(selector.sent_kind, selector.test_index, sent)
        state = selector.state
        if state != counters[self._i_state]:
            counters[self._i_entered + state] += 1
        counters[self._i_state] = state
        counters[self._i_test_motor] = selector.test_index + 1
        counters[self._i_tick_errors] = selector.faults
        self._count_tx()
        counters[self._i_ticks] += 1
        self._last_ns = now_ns
        self._tick = tick + 1
        return not stop_at_ns or now_ns < stop_at_ns

    def _loop(self) -> None:
        # When to tick; the tick itself is tick().
        counters = self._counters
        overruns_i, immediate_i = self._stats.slot("overruns"), self._stats.slot("immediate_sends")
        input_side, relay, tick = self._input, self._relay, self.tick
        prepare = self._selector.prepare
        period_ns = self._period_ns
        min_gap_ns = period_ns // IMMEDIATE_MAX_RATE_FACTOR
        keepalive_ns = period_ns * 3 // 2
        immediate = self._config.output.latency == "immediate"
        monotonic_ns, wait = time.monotonic_ns, select.select
        input_tick = False
        next_ns = self._last_ns = monotonic_ns()
        last_input_ns = next_ns - min_gap_ns  # the last tick an input started
        while True:
            delay_ns = next_ns - monotonic_ns()
            if delay_ns > 0:
                # Wait for input, a frame to relay or the tick, whichever comes first. Each
                # input is taken as it arrives, so that a tick only decides and sends: the same
                # work every tick, and at a fixed rate frames that leave at even intervals.
                # Reading and mixing an input at the tick instead made every tick with one
                # later than those without by that work (a period error of about 100 µs at
                # p50, against about 25: bench/cpu.py), for a wake-up less per input.
                link_fd = input_side.fd
                relay_fd = relay.fileno() if relay is not None and self._relay_open else -1
                readers = [fd for fd in (link_fd, relay_fd) if fd is not None and fd >= 0]
                writers = [link_fd] if link_fd is not None and input_side.wants_write else []
                ready, writable, _ = wait(readers, writers, (), delay_ns / 1e9)
                now = monotonic_ns()
                if link_fd in ready and input_side.on_readable(now):
                    # Its frames are made now too, not at the tick that sends them.
                    prepare(input_side.fractions)
                    if immediate:
                        # Fresh input goes out now, or as soon as the frame-rate cap allows:
                        # never within min_gap of the last input's frame, so an input flood
                        # cannot flood the bus. A keep-alive just before it does not hold it
                        # back: keep-alives fire only in the input's gaps (1.5 periods), so
                        # frames stay under twice the rate all the same, and an input a little
                        # early after one (input at half the rate: the keep-alive fires just
                        # min_gap before the next input) is not made to wait for the cap.
                        next_ns = min(next_ns, max(now, last_input_ns + min_gap_ns))
                        input_tick = True
                main_gone = not self._exchange_with_main(now, relay_ready=relay_fd in ready)
                # Woken before the tick: wait again (a main process gone starts the flush now).
                # A wait that timed out is the tick, even a µs early (the timeout's rounding):
                # waiting again for that µs costs a system call and makes the tick later.
                if now < next_ns and (ready or writable) and not main_gone:
                    continue
            else:
                # No wait (the tick is due or late): take what arrived meanwhile.
                now = monotonic_ns()
                input_side.on_readable(now)
                self._exchange_with_main(now)
            if not tick(now, next_ns):
                return
            if input_tick:
                # Re-phased to the input: the fixed tick becomes a keep-alive that fires only
                # when the next input is late, so it never races an input arriving on time.
                input_tick = False
                last_input_ns = now
                counters[immediate_i] += 1
                next_ns = now + keepalive_ns
                continue
            next_ns += period_ns
            behind_ns = now - next_ns
            if behind_ns >= period_ns:
                missed = behind_ns // period_ns
                next_ns += missed * period_ns
                counters[overruns_i] += missed

    def _exchange_with_main(self, now_ns: int, relay_ready: bool = True) -> bool:
        """Write what the main process relayed to the autopilot link (``relay_ready``: there
        may be some) and progress the link; False when the main process is gone (its end of
        the relay closed), once: the shutdown flush starts now."""
        self._input.service(now_ns)
        if not self._relay_open or not relay_ready:
            return True
        try:
            self._input.on_relay()
        except EOFError:
            self._relay_open = False
            if not self._stop_at_ns:
                self._stop_at_ns = now_ns + self._flush_ns
            return False
        return True

    def _send(self, frames: list[can.Message], now_ns: int) -> int:
        """Send without blocking (:mod:`bridge.output.transmit`); reopen a bus that is gone,
        with backoff."""
        tx = self._tx
        if tx is None:
            if now_ns < self._reopen_at_ns:
                return 0
            tx = self._reopen(now_ns)
            if tx is None:
                return 0
        try:
            sent = tx.send_tick(frames, now_ns)
        except BusGone:
            self._close_bus(now_ns)
            return 0
        if sent and sent == len(frames) and self._backoff.grown:
            self._backoff.reset()  # usable: a whole tick went out
        return sent

    def _count_tx(self) -> None:
        """The transmit side's state and counters into the shared statistics."""
        counters, tx = self._counters, self._tx
        state = TxState.GONE if tx is None else tx.state
        if state != counters[self._i_tx_state]:
            counters[self._i_tx_entered + state] += 1
            counters[self._i_tx_state] = state
        if tx is not None:
            counters[self._i_send_errors] = self._tx_before + tx.send_errors
            counters[self._i_held] = self._held_before + tx.ticks_held
            counters[self._i_probes] = self._probes_before + tx.probes

    def _close_bus(self, now_ns: int) -> None:
        """The bus is gone: close it, and try again after the backoff (growing while the
        interface stays unusable)."""
        tx = self._tx
        if tx is not None:
            self._tx_before += tx.send_errors
            self._held_before += tx.ticks_held
            self._probes_before += tx.probes
            self._counters[self._i_send_errors] = self._tx_before
        self._tx = None
        if self._bus is not None:
            self._bus.shutdown()
            self._bus = None
        self._schedule_reopen(now_ns)

    def _schedule_reopen(self, now_ns: int) -> None:
        self._reopen_at_ns = now_ns + int(self._backoff.wait_s(random.random()) * 1e9)

    def _open_bus(self) -> can.BusABC:
        # explain=False: no `ip` process from the loop; preflight read the interface.
        return open_bus(
            self._config.can, self._config.bitrate, receive=self._bus_receive, explain=False
        )

    def _reopen(self, now_ns: int) -> Transmitter | None:
        try:
            bus = self._open_bus()
        except BridgeError:
            self._schedule_reopen(now_ns)
            return None
        self._tx = transmitter_for(bus, self._stuck_after_ns)
        self._bus = bus
        self._stats["bus_reopens"] += 1
        return self._tx


def run_in_process(
    setup: LoopSetup,
    motor_tests: MotorTestBlock,
    snapshot: InputSnapshot,
    stats: LoopStats,
    relay: socket.socket | None,
    sent: SentCommands | None = None,
) -> None:
    """Entry point of the loop's own process (spawned by the supervisor with the stop signals
    blocked, so that none can kill it before its handlers are in place)."""
    loop = OutputLoop(setup, motor_tests, snapshot, stats, relay, watch_parent=True, sent=sent)
    for signum in STOP_SIGNALS:
        # Any of them, to this process alone or to the whole group (a closed terminal, Ctrl-C,
        # systemd), ends in the shutdown flush.
        signal.signal(signum, lambda _signum, _frame: loop.request_stop())
    signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)
    logging.basicConfig(
        level=setup.log_level, format="%(asctime)s %(levelname)s esc-bridge[output] %(message)s"
    )
    try:
        loop.run()
    except BridgeError as exc:
        log.error("%s", exc)
        raise SystemExit(1) from None
