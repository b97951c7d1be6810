"""The bridge daemon: the supervisor of the control loop, and the best-effort side.

Start-up validates everything before a frame is sent (config, mixer, bus load, the MAVLink
URLs), then starts the control loop (:mod:`bridge.output.output_loop`: in a real-time process of its
own where the bus allows it), which owns the autopilot's link and the CAN transmit handle and
sends safe values until valid, armed, fresh input arrives. Everything else lives here, in the
main process, and may stall without touching the control path: the MAVLink side of the
autopilot link (relayed by the loop: commands, HEARTBEAT, stream requests, recording), the
ground-station outputs, the CAN reader and the telemetry publishers.

The supervisor samples the loop's counters a few times a second to log and to report each
state transition by STATUSTEXT. On a stop signal (SIGTERM, SIGHUP, SIGQUIT, SIGINT) it asks
the loop to send safe values for ``shutdown_flush_ms`` and exits 0. If the loop dies, it sends
the safe values itself and exits 1, so that the service manager restarts the bridge; if this
process dies, the loop notices at once (its relay reads end of file) and flushes by itself.
A ground station's MAV_CMD_DO_MOTOR_TEST is decided here (:class:`MotorTestControl`) and run
by the loop while the autopilot is disarmed.
"""

from __future__ import annotations

import logging
import multiprocessing
import multiprocessing.connection
import signal
import socket
import threading
import time
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

import can

from bridge.autopilot_input import InputSetup
from bridge.can_io import SHAREABLE_INTERFACES, open_bus
from bridge.config import BridgeConfig
from bridge.errors import BridgeError, LinkError
from bridge.escs import registry
from bridge.escs.drivers import flush_safe_values, make_driver
from bridge.mavlink.link import MavlinkLink
from bridge.mixing.definition import INPUT_NAMES
from bridge.output.mailbox import InputSnapshot, LoopStats, MotorTestBlock
from bridge.output.motor_test import (
    Decision,
    MotorTestCommand,
    MotorTestLimits,
    MotorTestPlan,
    Verdict,
    decide,
    limits_for,
)
from bridge.output.output_loop import STOP_SIGNALS, LoopSetup, OutputLoop, run_in_process
from bridge.output.safety import SENDING_COMMANDS, LoopState
from bridge.preflight import Plan
from bridge.relay import MainConnection, relay_pair
from bridge.stopping import StopSignals
from bridge.telemetry.fanout import Fanout
from bridge.telemetry.for_config import esc_table
from bridge.telemetry.payload import (
    ActuatorsInputPayload,
    ActuatorsOutputPayload,
    CommandOut,
    HealthPayload,
    InputHealth,
    LinkHealth,
    MotorTestHealth,
    OutputHealth,
)
from bridge.telemetry.recorder import Recording

log = logging.getLogger(__name__)

SUPERVISE_PERIOD_S = 0.1
ERROR_LOG_INTERVAL_S = 1.0  # CAN send failures are summed and logged at most this often
LOOP_START_TIMEOUT_S = 15.0  # a spawned interpreter imports the bridge before it reports
# MAV_SEVERITY values for STATUSTEXT.
SEVERITY_CRITICAL, SEVERITY_WARNING, SEVERITY_NOTICE, SEVERITY_INFO = 2, 4, 5, 6
STATE_REPORTS: dict[LoopState, tuple[int, str]] = {
    LoopState.NO_INPUT: (SEVERITY_NOTICE, "ESC out: safe, waiting for motor outputs"),
    LoopState.DISARMED: (SEVERITY_INFO, "ESC out: disarmed, motors stopped"),
    LoopState.STALE: (SEVERITY_CRITICAL, "ESC out: FAILSAFE input stale, motors stopped"),
    LoopState.INVALID: (SEVERITY_CRITICAL, "ESC out: FAILSAFE invalid input, motors stopped"),
    LoopState.RUNNING: (SEVERITY_INFO, "ESC out: armed, sending motor commands"),
    LoopState.STOPPING: (SEVERITY_NOTICE, "ESC out: shutting down, motors stopped"),
    LoopState.MOTOR_TEST: (SEVERITY_WARNING, "ESC out: MOTOR TEST, one motor may spin"),
    LoopState.HEARTBEAT_LOST: (
        SEVERITY_CRITICAL,
        "ESC out: FAILSAFE autopilot HEARTBEAT lost, motors stopped",
    ),
    LoopState.SLOW_STREAM: (
        SEVERITY_CRITICAL,
        "ESC out: motor outputs too slow to arm on, motors stopped",
    ),
}
# After accepting a motor test, the supervisor allows the loop this long to start it before a
# loop not in MOTOR_TEST means the test was ended (armed, autopilot lost).
MOTOR_TEST_START_GRACE_NS = 300_000_000
# Loop states in which a motor test cannot start: the loop is not (or no longer) sending.
NOT_SENDING = frozenset(
    {LoopState.STARTING, LoopState.STOPPING, LoopState.STOPPED, LoopState.FAILED}
)


class MotorTestControl:
    """MAV_CMD_DO_MOTOR_TEST: checked on a MAVLink reader thread (:meth:`handle_command`),
    handed to the control loop through shared memory, followed and reported by the supervisor
    (:meth:`watch`).

    A command moves a motor, so it is obeyed only when ``[output] motor_test`` is on and it
    comes from a system the configuration allows (``[mavlink] command_senders``: by default the
    ground stations' usual 255 and the autopilot's own system); with a signing key, unsigned
    commands never get this far. Otherwise MAV_RESULT_DENIED. A valid test
    (:func:`bridge.output.motor_test.decide`) starts only while the control loop knows the autopilot
    to be disarmed (its HEARTBEAT within the arming timeout) and is sending; otherwise
    MAV_RESULT_TEMPORARILY_REJECTED, with a STATUSTEXT saying why. A new command replaces a
    running test; throttle 0 stops it. The loop ends a test by itself at its time, the moment
    the autopilot arms or when its HEARTBEAT is lost; this class only reports it.
    """

    def __init__(
        self,
        limits: MotorTestLimits,
        config: BridgeConfig,
        motor_tests: MotorTestBlock,
        snapshot: InputSnapshot,
        stats: LoopStats,
        report: Callable[[int, str], None],
        dialect: ModuleType,
    ) -> None:
        self._limits = limits
        self._enabled = config.output.motor_test
        self._senders = config.command_sender_ids
        self._arming_timeout_ns = config.output.arming_timeout_ms * 1_000_000
        self._motor_tests = motor_tests
        self._snapshot = snapshot
        self._stats = stats
        self._report = report
        self._command_id: int = dialect.MAV_CMD_DO_MOTOR_TEST
        self._results = {v: int(getattr(dialect, f"MAV_RESULT_{v.value}")) for v in Verdict}
        self._denied = int(dialect.MAV_RESULT_DENIED)
        self.refused_senders = 0
        """Motor tests refused because their sender is not allowed."""
        # Commands come from every connection's reader thread and the supervisor cancels: the
        # lock keeps the motor-test block to one writer at a time.
        self._lock = threading.Lock()
        self._running: tuple[MotorTestPlan, int] | None = None  # the plan and its end, ns
        self._reported_motor = 0

    def handle_command(self, msg: Any) -> int | None:
        """The link's command handler: a MAV_RESULT for DO_MOTOR_TEST, None for the others."""
        if msg.command != self._command_id:
            return None
        sender = msg.get_srcSystem()
        if sender not in self._senders:
            self.refused_senders += 1
            if self.refused_senders & (self.refused_senders - 1) == 0:  # 1st, 2nd, 4th, ...
                log.warning(
                    "refused a motor test from system %d: not in [mavlink] command_senders %s "
                    "(%d refused so far)",
                    sender,
                    sorted(self._senders),
                    self.refused_senders,
                )
            return self._denied
        if not self._enabled:
            self._report(SEVERITY_WARNING, "Motor test refused: off in the bridge's config")
            return self._denied
        command = MotorTestCommand(
            msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6
        )
        decision = decide(command, self._limits)
        with self._lock:
            if decision.verdict is Verdict.ACCEPTED:
                decision = self._start(decision)
        severity = SEVERITY_NOTICE if decision.verdict is Verdict.ACCEPTED else SEVERITY_WARNING
        self._report(severity, decision.text)
        return self._results[decision.verdict]

    def _start(self, decision: Decision) -> Decision:
        """Run an accepted decision, or refuse it for now. Called with the lock held."""
        plan = decision.plan
        if plan is None:  # throttle 0: stop, whatever the vehicle does
            self._motor_tests.stop_motor_test()
            self._running = None
            return decision
        now = time.monotonic_ns()
        seen = self._snapshot.read()
        if seen is not None and seen.armed:
            why = "vehicle armed"
        elif (
            seen is None
            or not seen.armed_heard_ns
            or (now - seen.armed_heard_ns > self._arming_timeout_ns)
        ):
            why = "autopilot not heard"
        elif LoopState(self._stats["state"]) in NOT_SENDING:
            why = "bridge not sending"
        else:
            on_ns = round(plan.on_s * 1e9)
            step_ns = on_ns + round(plan.gap_s * 1e9)
            self._motor_tests.write_motor_test(
                plan.first, plan.count, plan.fraction, now, on_ns, step_ns
            )
            self._running = (plan, now + round(plan.total_s * 1e9))
            self._reported_motor = 0
            return decision
        return Decision(Verdict.TEMPORARILY_REJECTED, f"Motor test refused: {why}")

    def watch(self) -> None:
        """From the supervisor, a few times a second: report each motor of a sequence as it
        starts, and the end of a test (its time, the autopilot arming or going silent)."""
        with self._lock:
            if self._running is None:
                return
            plan, until_ns = self._running
            motor = self._stats["motor_test_motor"]
            state = LoopState(self._stats["state"])
            now = time.monotonic_ns()
            if now >= until_ns:
                self._running = None
                text = "Motor test: done, motors safe"
            elif state != LoopState.MOTOR_TEST and now - self._started_ns(plan, until_ns) > (
                MOTOR_TEST_START_GRACE_NS
            ):
                self._motor_tests.stop_motor_test()  # the loop has ended it already
                self._running = None
                text = "Motor test: stopped, armed or autopilot lost"
            elif plan.count > 1 and motor and motor != self._reported_motor:
                self._reported_motor = motor
                text = f"Motor test: motor {motor}"
            else:
                return
        self._report(SEVERITY_INFO, text)

    @staticmethod
    def _started_ns(plan: MotorTestPlan, until_ns: int) -> int:
        return until_ns - round(plan.total_s * 1e9)

    def snapshot(self) -> MotorTestHealth | None:
        """The running test for the health report, or None."""
        with self._lock:
            running = self._running
        if running is None:
            return None
        plan, until_ns = running
        return MotorTestHealth(
            motor=self._stats["motor_test_motor"] or None,  # None between two motors
            motors=tuple(range(plan.first + 1, plan.first + plan.count + 1)),
            throttle=plan.fraction,
            remaining_s=round(max(0.0, (until_ns - time.monotonic_ns()) / 1e9), 2),
        )


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
                args=(setup, motor_tests, snapshot, stats, relay),
                name="esc-bridge-output",
            )
        else:
            self._loop = OutputLoop(setup, motor_tests, snapshot, stats, relay)
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


class Supervisor:
    """Starts the parts, watches the loop, reports transitions, stops cleanly."""

    def __init__(self, plan: Plan, record_dir: str | Path | None = None) -> None:
        self._plan = plan
        config = plan.config
        self._config = config
        n = len(plan.mixer.outputs)
        self.motor_tests = MotorTestBlock(n)
        self.input_snapshot = InputSnapshot(n)
        self.stats = LoopStats()
        valid_range = plan.valid_range
        # An interface only one handle can open is read through the thread-mode loop's handle.
        shares_loop_bus = config.can.interface not in SHAREABLE_INTERFACES | {"virtual"} and (
            loop_mode(config) == "thread"
        )
        setup = LoopSetup(
            config=config,
            input=InputSetup(
                plan.mixer, valid_range, plan.input_range, relay_outputs=record_dir is not None
            ),
            log_level=logging.getLogger().getEffectiveLevel(),
            bus_receive="all" if shares_loop_bus else "none",
        )
        loop_end, main_end = relay_pair()
        self.runner = LoopRunner(setup, self.motor_tests, self.input_snapshot, self.stats, loop_end)
        self.recording = Recording.open(Path(record_dir), config.can) if record_dir else None
        tlog = self.recording.tlog if self.recording is not None else None
        relayed = [MainConnection(main_end)]

        def uplink() -> MainConnection:
            if not relayed:
                raise LinkError("the output loop's relay of the autopilot link is gone")
            return relayed.pop()

        # No input sink: the loop acts on the autopilot's outputs and arming, and counts them.
        # Two inputs per input timeout at least: the loop arms on nothing slower.
        needed_rate_hz = 2000 / config.output.input_timeout_ms
        self.link = MavlinkLink(
            config.mavlink, None, tlog=tlog, uplink=uplink, needed_rate_hz=needed_rate_hz
        )
        self.motor_test = MotorTestControl(
            limits_for(plan.mixer, plan.input_range, config.output.motor_test_max_s),
            config,
            self.motor_tests,
            self.input_snapshot,
            self.stats,
            self._report,
            self.link.dialect,
        )
        self.link.add_command_handler(self.motor_test.handle_command)
        self.fanout = Fanout(
            config,
            esc_table(config),
            self.link,
            health=self.health,
            actuators_input=self.actuators_input,
            actuators_output=self.actuators_output,
            shared_bus=self.runner.loop_bus if shares_loop_bus else None,
            recorder=self.recording.can if self.recording is not None else None,
        )
        self._output_ticks = (time.monotonic(), 0)
        self._output_rate_hz = 0.0
        self._stop = threading.Event()
        self._reported_state = LoopState.STARTING
        self._last_errors = 0
        self._errors_logged_at = 0.0
        self._tick_errors = 0

    def stop(self) -> None:
        """Stop: the loop starts its safe flush on its next tick (the request is one store to
        shared memory, fine from a signal handler), and the supervisor winds down."""
        self.runner.request_stop()
        self._stop.set()

    def run(self) -> int:
        config = self._config
        log.info(
            "esc-bridge: %s x%d (%s), mixer %s, %d Hz, loop in a %s; %s",
            config.output.protocol,
            len(config.escs.ids),
            registry.family(config.output.protocol).command_kind(config),
            self._plan.mixer.name,
            config.rate_hz,
            self.runner.mode,
            self._plan.load_text,
        )
        if self._stop.is_set():
            log.info("stopped before starting: nothing was sent")
            return 0
        self.link.start()
        try:
            self.runner.start()
            self._await_loop_start()
            self.fanout.start()
            while not self._stop.is_set():
                if self.runner.wait_for_exit(SUPERVISE_PERIOD_S):
                    return self._loop_died()
                self._watch()
            self.runner.request_stop()
            self.runner.join(config.output.shutdown_flush_ms / 1000 + 5.0)
            self._watch()
            self._log_loop_summary()
            self._log_telemetry_summary()
            log.info("stopped after sending safe values for %d ms", config.output.shutdown_flush_ms)
            return 0
        finally:
            self.runner.request_stop()
            self.runner.join(1.0)
            self.fanout.close()
            self.link.close()
            if self.recording is not None:
                self.recording.close()

    def _loop_died(self) -> int:
        """The loop ended without being asked: safe values from here, then exit 1 (so that
        systemd restarts the service)."""
        state = LoopState(self.stats["state"])
        sent = 0
        if state != LoopState.STOPPED:  # it did not get to its own flush
            sent = send_safe_values_after_death(self._config)
        log.error(
            "output loop ended unexpectedly (exit code %s, state %s); sent %d safe frames",
            self.runner.exitcode,
            state.name,
            sent,
        )
        self._report(SEVERITY_CRITICAL, "ESC out: FAULT output loop died, motors stopped")
        return 1

    def _await_loop_start(self) -> None:
        deadline = time.monotonic() + LOOP_START_TIMEOUT_S
        while self.stats["state"] == LoopState.STARTING and self.runner.alive():
            if time.monotonic() > deadline:
                raise LinkError(f"output loop did not start within {LOOP_START_TIMEOUT_S:.0f} s")
            time.sleep(0.01)
        if self.stats["state"] in (LoopState.FAILED, LoopState.STARTING) or not self.runner.alive():
            detail = self.runner.thread_error or "see the log above"
            raise LinkError(f"output loop failed to start: {detail}")
        if self.stats["realtime"]:
            log.info(
                "output loop runs with SCHED_FIFO priority %d",
                self._config.output.realtime_priority,
            )
        else:
            log.warning(
                "output loop runs WITHOUT real-time priority (needs root or CAP_SYS_NICE; the "
                "systemd unit grants it): expect ms of jitter when the machine is busy"
            )

    # -- for the telemetry publishers (called from their threads) --------------------------

    def health(self) -> HealthPayload:
        """The bridge's health: loop state and rates, failsafe, counters."""
        stats, link, fanout = self.stats, self.link.stats, self.fanout
        state = LoopState(stats["state"])
        seen = self.input_snapshot.read()
        return HealthPayload(
            state=state.name.lower(),
            failsafe=state not in SENDING_COMMANDS,
            armed=seen is not None and seen.armed,
            motor_test=self.motor_test.snapshot(),
            output=OutputHealth(
                rate_hz=round(self._output_rate_hz, 1),
                configured_rate_hz=self._config.rate_hz,
                ticks=stats["ticks"],
                frames_sent=stats["frames_sent"],
                send_errors=stats["send_errors"],
                overruns=stats["overruns"],
                tick_errors=stats["tick_errors"],
                bus_reopens=stats["bus_reopens"],
                realtime=bool(stats["realtime"]),
            ),
            input=InputHealth(
                rate_hz=round(link.output_rate_hz, 1),
                outputs=stats["input_outputs"],
                messages=stats["input_frames"],
                bad_data=stats["input_bad_crc"],
                invalid=stats["input_invalid"],
                mixer_errors=stats["mixer_errors"],
                age_ms=round(stats["input_age_us"] / 1000, 1),
                out_of_order=stats["input_out_of_order"],
                unsigned=stats["input_unsigned"],
            ),
            # The autopilot link as the loop, its owner, keeps it: what the main process was
            # too slow to take, and what could not be written to the autopilot.
            link=LinkHealth(
                relay_dropped=stats["relay_dropped"],
                sent=stats["link_sent"],
                send_dropped=stats["link_dropped"],
                reconnects=stats["link_reconnects"],
            ),
            escs_online=sum(1 for esc in fanout.table.snapshot(time.monotonic_ns()) if esc.online),
            can_rx=fanout.can_rx(),
            zenoh=fanout.zenoh_health(),
        )

    def actuators_input(self) -> ActuatorsInputPayload | None:
        """What came in: the autopilot's newest outputs (present channels) and their mix."""
        seen = self.input_snapshot.read()
        if seen is None or not seen.inputs:
            return None
        return ActuatorsInputPayload(
            source=self._config.mavlink.source,
            armed=seen.armed,
            age_ms=round((time.monotonic_ns() - seen.produced_ns) / 1e6, 1),
            channels={
                name: value
                for name, value in zip(INPUT_NAMES, seen.inputs, strict=False)
                if value == value  # NaN: channel absent
            },
            mixed=tuple(seen.fractions) if seen.valid else None,
        )

    def actuators_output(self) -> ActuatorsOutputPayload:
        """What went out: the last command on the bus for each ESC (read back) and why."""
        escs = self.fanout.table.snapshot(time.monotonic_ns())
        return ActuatorsOutputPayload(
            state=LoopState(self.stats["state"]).name.lower(),
            commands=tuple(
                CommandOut(
                    motor=esc.motor, node_id=esc.node_id, value=esc.command, unit=esc.command_unit
                )
                for esc in escs
            ),
        )

    def _watch(self) -> None:
        stats = self.stats
        self.link.note_outputs(stats["input_outputs"], time.monotonic_ns())
        now_s = time.monotonic()
        since_s, ticks = self._output_ticks
        if now_s - since_s >= 1.0:
            self._output_rate_hz = (stats["ticks"] - ticks) / (now_s - since_s)
            self._output_ticks = (now_s, stats["ticks"])
        state = LoopState(stats["state"])
        if state != self._reported_state and state in STATE_REPORTS:
            severity, text = STATE_REPORTS[state]
            self._report(severity, text)
        self._reported_state = state
        self.motor_test.watch()
        tick_errors = stats["tick_errors"]
        if tick_errors != self._tick_errors:
            self._report(SEVERITY_CRITICAL, "ESC out: FAULT encoding commands, motors safe")
            log.error("%d ticks could not encode commands; safe values were sent", tick_errors)
            self._tick_errors = tick_errors
        errors = stats["send_errors"]
        now = time.monotonic()
        if errors != self._last_errors and now - self._errors_logged_at >= ERROR_LOG_INTERVAL_S:
            log.warning(
                "CAN send failures: %d since the last report (%d in all; bus reopened %d times)",
                errors - self._last_errors,
                errors,
                stats["bus_reopens"],
            )
            self._last_errors = errors
            self._errors_logged_at = now

    def _log_loop_summary(self) -> None:
        stats = self.stats
        lateness = sorted(stats.lateness_us())
        if not lateness:
            return

        def at(fraction: float) -> int:
            return lateness[min(len(lateness) - 1, int(fraction * len(lateness)))]

        log.info(
            "output loop: %d ticks, %d frames, %d send errors, %d overruns, %d immediate "
            "sends, %d tick errors; wake-up lateness p50 %d µs, p99 %d µs, max %d µs "
            "(last %d ticks)",
            stats["ticks"],
            stats["frames_sent"],
            stats["send_errors"],
            stats["overruns"],
            stats["immediate_sends"],
            stats["tick_errors"],
            at(0.5),
            at(0.99),
            lateness[-1],
            len(lateness),
        )

    def _log_telemetry_summary(self) -> None:
        reader = self.fanout.reader
        if reader is None:
            return
        stats = reader.stats
        log.info(
            "CAN in: %d frames read, %d telemetry, %d malformed, %d read errors; "
            "%d of %d ESCs online; %s dropped by the kernel",
            stats.frames,
            stats.telemetry,
            stats.malformed,
            stats.read_errors,
            sum(1 for esc in self.fanout.table.snapshot(time.monotonic_ns()) if esc.online),
            len(self.fanout.table),
            "?" if stats.kernel_drops is None else stats.kernel_drops,
        )

    def _report(self, severity: int, text: str) -> None:
        level = logging.WARNING if severity <= SEVERITY_WARNING else logging.INFO
        log.log(level, "%s", text)
        self.link.statustext(severity, text)


def run(
    checked: Plan,
    record_dir: str | Path | None = None,
    stop_signals: StopSignals | None = None,
) -> int:
    """Run the bridge on a checked plan (:func:`bridge.preflight.plan`) until a stop signal;
    returns the process exit code.

    ``stop_signals``: the command line's, installed before anything else so that none is lost
    (see :mod:`bridge.stopping`); installed here when not given.

    Raises:
        LinkError: the MAVLink link or the CAN bus could not be opened.
    """
    stop_signals = stop_signals or StopSignals.install()
    supervisor = Supervisor(checked, record_dir)

    def on_signal(sig: signal.Signals) -> None:
        log.info("%s: stopping", sig.name)
        supervisor.stop()

    stop_signals.on_stop(on_signal)
    return supervisor.run()
