"""The bridge daemon: MAVLink motor outputs -> mixer -> mailbox -> output loop -> CAN.

Start-up validates everything before a frame is sent (config, mixer, bus load, the MAVLink
URL), then starts the output loop, which sends safe values until valid, armed, fresh input
arrives. The supervisor (this module, in the main process) never touches the hot path: it
samples the loop's counters a few times a second to log and to report each state transition
by STATUSTEXT, and on SIGINT/SIGTERM asks the loop to send safe values for
``shutdown_flush_ms`` and stop. A ground station's MAV_CMD_DO_MOTOR_TEST is decided here
(:class:`MotorTestControl`) and run by the loop while the autopilot is disarmed.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import os
import signal
import threading
import time
from collections.abc import Callable
from multiprocessing.connection import Connection
from pathlib import Path
from types import FrameType, ModuleType
from typing import Any

import can

from bridge.can_io import SHAREABLE_INTERFACES
from bridge.config import BridgeConfig
from bridge.errors import LinkError
from bridge.fanout import Fanout
from bridge.mailbox import CommandMailbox, LoopState, LoopStats
from bridge.mavlink_in import MavlinkLink
from bridge.mixer import INPUT_NAMES, PWM_RANGE_US, AxisChannels, Mixer
from bridge.motor_test import (
    Decision,
    MotorTestCommand,
    MotorTestLimits,
    MotorTestPlan,
    Verdict,
    decide,
    limits_for,
)
from bridge.output_loop import LoopSetup, OutputLoop, run_in_process
from bridge.preflight import Plan as Plan  # re-exported (mypy --strict): daemon.plan still works
from bridge.preflight import plan as plan
from bridge.record import Recording
from bridge.telemetry.state import EscTable

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
}
# A motor test starts only while the autopilot's arming state is this fresh (HEARTBEAT: 1 Hz).
ARMING_STATE_MAX_AGE_NS = 3_000_000_000
# Loop states in which a motor test cannot start: the loop is not (or no longer) sending.
NOT_SENDING = frozenset(
    {LoopState.STARTING, LoopState.STOPPING, LoopState.STOPPED, LoopState.FAILED}
)


class MixerSink:
    """Receives the autopilot's outputs on the MAVLink thread, mixes, fills the mailbox."""

    def __init__(
        self,
        mixer: Mixer,
        mailbox: CommandMailbox,
        wake: Connection | None,
        axes: AxisChannels | None = None,
    ) -> None:
        self._mixer = mixer
        self._axes = axes
        self._mailbox = mailbox
        self._wake_fd = wake.fileno() if wake is not None else None
        self._armed = False
        self.armed_at_ns = 0  # monotonic time of the last arming state heard; 0 = never
        self.mixer_errors = 0
        # The newest input and mix, for the telemetry publishers (replaced, never mutated).
        self.last_input: tuple[list[float], list[float] | None, int] | None = None

    def on_actuators(self, values: list[float], time_ns: int) -> None:
        if self._axes is not None:
            self._axes.fill(values)
        try:
            fractions = self._mixer.mix(values, self._armed)
        except Exception:  # any mixer fault must become a safe output, never a crash
            self.mixer_errors += 1
            log.exception("mixer failed; sending safe values")
            fractions = None
        self._mailbox.write(fractions, time_ns)
        self.last_input = (values, fractions, time_ns)
        if self._wake_fd is not None:
            # A full pipe means a wake-up is already pending: the loop reads the newest anyway.
            with contextlib.suppress(BlockingIOError):
                os.write(self._wake_fd, b"\x01")

    def on_armed(self, armed: bool, time_ns: int) -> None:
        self._armed = armed
        self.armed_at_ns = time_ns
        self._mailbox.write_armed(armed, time_ns)

    @property
    def armed(self) -> bool:
        return self._armed


class MotorTestControl:
    """MAV_CMD_DO_MOTOR_TEST: checked on a MAVLink reader thread (:meth:`handle_command`),
    handed to the output loop through the mailbox, followed and reported by the supervisor
    (:meth:`watch`).

    A valid test (:func:`bridge.motor_test.decide`) starts only while the autopilot is known to
    be disarmed (its arming state heard within :data:`ARMING_STATE_MAX_AGE_NS`) and the loop
    is sending; otherwise MAV_RESULT_TEMPORARILY_REJECTED, with a STATUSTEXT saying why. A new
    command replaces a running test; throttle 0 stops it. The loop ends a test by itself at its
    time or the moment the autopilot arms; this class only reports it.
    """

    def __init__(
        self,
        limits: MotorTestLimits,
        mailbox: CommandMailbox,
        sink: MixerSink,
        stats: LoopStats,
        report: Callable[[int, str], None],
        dialect: ModuleType,
    ) -> None:
        self._limits = limits
        self._mailbox = mailbox
        self._sink = sink
        self._stats = stats
        self._report = report
        self._command_id: int = dialect.MAV_CMD_DO_MOTOR_TEST
        self._results = {v: int(getattr(dialect, f"MAV_RESULT_{v.value}")) for v in Verdict}
        # Commands come from every connection's reader thread and the supervisor cancels: the
        # lock keeps the mailbox's motor-test block to one writer at a time.
        self._lock = threading.Lock()
        self._running: tuple[MotorTestPlan, int] | None = None  # the plan and its end, ns
        self._reported_motor = 0

    def handle_command(self, msg: Any) -> int | None:
        """The link's command handler: a MAV_RESULT for DO_MOTOR_TEST, None for the others."""
        if msg.command != self._command_id:
            return None
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
            self._mailbox.stop_motor_test()
            self._running = None
            return decision
        now = time.monotonic_ns()
        sink = self._sink
        if sink.armed:
            why = "vehicle armed"
        elif not sink.armed_at_ns or now - sink.armed_at_ns > ARMING_STATE_MAX_AGE_NS:
            why = "autopilot not heard"
        elif LoopState(self._stats["state"]) in NOT_SENDING:
            why = "bridge not sending"
        else:
            on_ns = round(plan.on_s * 1e9)
            step_ns = on_ns + round(plan.gap_s * 1e9)
            self._mailbox.write_motor_test(
                plan.first, plan.count, plan.fraction, now, on_ns, step_ns
            )
            self._running = (plan, now + round(plan.total_s * 1e9))
            self._reported_motor = 0
            return decision
        return Decision(Verdict.TEMPORARILY_REJECTED, f"Motor test refused: {why}")

    def watch(self) -> None:
        """From the supervisor, a few times a second: report each motor of a sequence as it
        starts, and the end of a test (its time, or the autopilot arming)."""
        with self._lock:
            if self._running is None:
                return
            plan, until_ns = self._running
            motor = self._stats["motor_test_motor"]
            if self._sink.armed:
                self._mailbox.stop_motor_test()  # the loop has stopped it already
                self._running = None
                text = "Motor test: stopped, vehicle armed"
            elif time.monotonic_ns() >= until_ns:
                self._running = None
                text = "Motor test: done, motors safe"
            elif plan.count > 1 and motor and motor != self._reported_motor:
                self._reported_motor = motor
                text = f"Motor test: motor {motor}"
            else:
                return
        self._report(SEVERITY_INFO, text)

    def snapshot(self) -> dict[str, Any] | None:
        """The running test for the health report, or None."""
        with self._lock:
            running = self._running
        if running is None:
            return None
        plan, until_ns = running
        return {
            "motor": self._stats["motor_test_motor"] or None,  # None between two motors
            "motors": list(range(plan.first + 1, plan.first + plan.count + 1)),
            "throttle": plan.fraction,
            "remaining_s": round(max(0.0, (until_ns - time.monotonic_ns()) / 1e9), 2),
        }


class LoopRunner:
    """Runs the output loop in a process of its own or in a thread of this one."""

    def __init__(self, setup: LoopSetup, mailbox: CommandMailbox, stats: LoopStats) -> None:
        self._stats = stats
        config = setup.config
        mode = config.output.loop
        if mode == "auto":
            mode = "process" if config.can.interface in SHAREABLE_INTERFACES else "thread"
        self.mode = mode
        ctx = multiprocessing.get_context("spawn")
        self._wake_reader: Connection | None = None
        self.wake_writer: Connection | None = None
        if config.output.latency == "immediate":
            self._wake_reader, self.wake_writer = ctx.Pipe(duplex=False)
            os.set_blocking(self.wake_writer.fileno(), False)
        self._process: Any = None
        self._thread: threading.Thread | None = None
        self._loop: OutputLoop | None = None
        wake_fd = self._wake_reader
        if mode == "process":
            self._process = ctx.Process(
                target=run_in_process,
                args=(setup, mailbox, stats, wake_fd),
                name="esc-bridge-output",
            )
        else:
            fd = wake_fd.fileno() if wake_fd is not None else None
            self._loop = OutputLoop(setup, mailbox, stats, fd)
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
            self._process.start()
        elif self._thread is not None:
            self._thread.start()

    def alive(self) -> bool:
        if self._process is not None:
            return bool(self._process.is_alive())
        return self._thread is not None and self._thread.is_alive()

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


class Supervisor:
    """Starts the parts, watches the loop, reports transitions, stops cleanly."""

    def __init__(self, plan: Plan, record_dir: str | Path | None = None) -> None:
        self._plan = plan
        config = plan.config
        self._config = config
        n = len(plan.mixer.outputs)
        self.mailbox = CommandMailbox(n)
        self.stats = LoopStats()
        setup = LoopSetup(
            config=config, mixer=plan.mixer, log_level=logging.getLogger().getEffectiveLevel()
        )
        self.runner = LoopRunner(setup, self.mailbox, self.stats)
        axes = None
        if config.mixer.axis_channels:
            channel_range = plan.input_range or PWM_RANGE_US
            axes = AxisChannels(config.mixer.axis_channels, channel_range)
        self.sink = MixerSink(Mixer(plan.mixer), self.mailbox, self.runner.wake_writer, axes)
        self.recording = Recording.open(Path(record_dir), config.can) if record_dir else None
        tlog = self.recording.tlog if self.recording is not None else None
        self.link = MavlinkLink(config.mavlink, self.sink, tlog=tlog)
        self.motor_test = MotorTestControl(
            limits_for(plan.mixer, plan.input_range, config.output.motor_test_max_s),
            self.mailbox,
            self.sink,
            self.stats,
            self._report,
            self.link.dialect,
        )
        self.link.add_command_handler(self.motor_test.handle_command)
        # An interface only one handle can open is read through the thread-mode loop's handle.
        own_handle = config.can.interface in SHAREABLE_INTERFACES | {"virtual"} or (
            self.runner.mode == "process"
        )
        self.fanout = Fanout(
            config,
            EscTable.for_config(config),
            self.link,
            health=self.health,
            actuators_input=self.actuators_input,
            actuators_output=self.actuators_output,
            shared_bus=None
            if own_handle or self.runner.mode == "process"
            else self.runner.loop_bus,
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
        self._stop.set()

    def run(self) -> int:
        config = self._config
        log.info(
            "esc-bridge: %s x%d (%s), mixer %s, %d Hz, loop in a %s; %s",
            config.output.protocol,
            len(config.escs.ids),
            config.escs.ckesc_command if config.output.protocol == "ckesc" else config.escs.ft_mode,
            self._plan.mixer.name,
            config.rate_hz,
            self.runner.mode,
            self._plan.load_text,
        )
        self.link.start()
        try:
            self.runner.start()
            self._await_loop_start()
            self.fanout.start()
            while not self._stop.wait(SUPERVISE_PERIOD_S):
                if not self.runner.alive():
                    self._report(SEVERITY_CRITICAL, "ESC out: FAULT output loop died")
                    log.error("output loop ended unexpectedly (exit code %s)", self.runner.exitcode)
                    return 1
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

    def health(self) -> dict[str, Any]:
        """The bridge's health: loop state and rates, failsafe, counters."""
        stats, link = self.stats, self.link.stats
        state = LoopState(stats["state"])
        return {
            "state": state.name.lower(),
            "failsafe": state != LoopState.RUNNING,
            "armed": self.sink.armed,
            "motor_test": self.motor_test.snapshot(),
            "output": {
                "rate_hz": round(self._output_rate_hz, 1),
                "configured_rate_hz": self._config.rate_hz,
                "ticks": stats["ticks"],
                "frames_sent": stats["frames_sent"],
                "send_errors": stats["send_errors"],
                "overruns": stats["overruns"],
                "tick_errors": stats["tick_errors"],
                "bus_reopens": stats["bus_reopens"],
                "realtime": bool(stats["realtime"]),
            },
            "input": {
                "rate_hz": round(link.output_rate_hz, 1),
                "outputs": link.outputs,
                "messages": link.messages,
                "bad_data": link.bad_data,
                "mixer_errors": self.sink.mixer_errors,
            },
            "escs_online": sum(
                1 for esc in self.fanout.table.snapshot(time.monotonic_ns()) if esc.online
            ),
            **self.fanout.counters(),
        }

    def actuators_input(self) -> dict[str, Any] | None:
        """What came in: the autopilot's newest outputs (present channels) and their mix."""
        last = self.sink.last_input
        if last is None:
            return None
        values, fractions, time_ns = last
        return {
            "source": self._config.mavlink.source,
            "armed": self.sink.armed,
            "age_ms": round((time.monotonic_ns() - time_ns) / 1e6, 1),
            "channels": {
                name: value
                for name, value in zip(INPUT_NAMES, values, strict=False)
                if value == value  # NaN: channel absent
            },
            "mixed": fractions,
        }

    def actuators_output(self) -> dict[str, Any] | None:
        """What went out: the last command on the bus for each ESC (read back) and why."""
        escs = self.fanout.table.snapshot(time.monotonic_ns())
        return {
            "state": LoopState(self.stats["state"]).name.lower(),
            "commands": [
                {
                    "motor": esc.motor,
                    "node_id": esc.node_id,
                    "value": esc.command,
                    "unit": esc.command_unit,
                }
                for esc in escs
            ],
        }

    def _watch(self) -> None:
        stats = self.stats
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
            "%d of %d ESCs online",
            stats.frames,
            stats.telemetry,
            stats.malformed,
            stats.read_errors,
            sum(1 for esc in self.fanout.table.snapshot(time.monotonic_ns()) if esc.online),
            len(self.fanout.table),
        )

    def _report(self, severity: int, text: str) -> None:
        level = logging.WARNING if severity <= SEVERITY_WARNING else logging.INFO
        log.log(level, "%s", text)
        self.link.statustext(severity, text)


def run(config: BridgeConfig, record_dir: str | Path | None = None) -> int:
    """Run the bridge until SIGINT or SIGTERM; returns the process exit code.

    Raises:
        ConfigError: the configuration is invalid (before anything is sent).
        LinkError: the MAVLink link or the CAN bus could not be opened.
    """
    supervisor = Supervisor(plan(config), record_dir)

    def on_signal(signum: int, _frame: FrameType | None) -> None:
        log.info("%s: stopping", signal.Signals(signum).name)
        supervisor.stop()

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        return supervisor.run()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
