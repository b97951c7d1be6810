"""The bridge daemon: the supervisor of the control loop, and the best-effort side.

Start-up validates everything before a frame is sent (config, mixer, bus load, the MAVLink
URLs), then starts the control loop (:mod:`bridge.output.output_loop`: in a real-time process
of its own where the bus allows it), which owns the autopilot's link and the CAN transmit handle and
sends safe values until valid, armed, fresh input arrives. Everything else lives here, in the
main process, and may stall without touching the control path: the MAVLink side of the
autopilot link (relayed by the loop: commands, HEARTBEAT, stream requests, recording), the
ground-station outputs, the CAN reader and the telemetry publishers.

The supervisor samples the loop's counters a few times a second to log and to report each
state transition by STATUSTEXT. On a stop signal (SIGTERM, SIGHUP, SIGQUIT, SIGINT) it asks
the loop to send safe values for ``shutdown_flush_ms`` and exits 0. If the loop dies, it sends
the safe values itself and exits 1, so that the service manager restarts the bridge; if this
process dies, the loop notices at once (its relay reads end of file) and flushes by itself.
A ground station's MAV_CMD_DO_MOTOR_TEST is decided in the main process
(:mod:`bridge.daemon.motor_test_control`) and run by the loop while the autopilot is disarmed.

Beside this module: :mod:`bridge.daemon.loop_runner` (where the loop runs, the safe values
after its death), :mod:`bridge.daemon.motor_test_control`, :mod:`bridge.daemon.health` (what
each loop state is reported as; the health and actuator records the Zenoh publisher takes).
"""

from __future__ import annotations

import logging
import signal
import threading
import time
from pathlib import Path

from bridge.can_io import SHAREABLE_INTERFACES
from bridge.daemon.absence import AbsenceWatch, EscsHeard
from bridge.daemon.address_reports import AddressReports
from bridge.daemon.bus_reports import BusWatch
from bridge.daemon.commands_sent import CommandsSent
from bridge.daemon.health import STATE_REPORTS, HealthReport
from bridge.daemon.loop_runner import LoopRunner, loop_mode, send_safe_values_after_death
from bridge.daemon.motor_test_control import MotorTestControl
from bridge.daemon.preflight import Plan
from bridge.daemon.severity import SEVERITY_CRITICAL, SEVERITY_WARNING
from bridge.errors import LinkError
from bridge.mavlink import load_dialect
from bridge.mavlink.link import MavlinkLink, relayed_msg_ids
from bridge.mavlink.relay import MainConnection, relay_pair
from bridge.mavlink.traffic import TrafficReader
from bridge.output.autopilot_input import InputSetup
from bridge.output.mailbox import InputSnapshot, LoopStats, MotorTestBlock, SentCommands
from bridge.output.motor_test import limits_for
from bridge.output.output_loop import LoopSetup
from bridge.output.safety import SENDING_COMMANDS, LoopState
from bridge.output.transmit import TxState
from bridge.stopping import StopSignals
from bridge.telemetry.fanout import Fanout
from bridge.telemetry.for_config import esc_table
from bridge.telemetry.mcap_channels import BridgeState, metadata
from bridge.telemetry.mcap_out import LogHandler
from bridge.telemetry.recorder import Recording

log = logging.getLogger(__name__)

SUPERVISE_PERIOD_S = 0.1
ERROR_LOG_INTERVAL_S = 1.0  # CAN send failures are summed and logged at most this often
# A spawned interpreter imports the bridge before it reports. That took over 15 s in User-Mode
# Linux's one CPU beside a host at load 16 (tests/linux): a machine that slow would never start
# the bridge with a shorter wait, since every restart waits as long again. Nothing is sent
# meanwhile; the ESCs see no command, as before the start.
LOOP_START_TIMEOUT_S = 60.0


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
        self.sent = SentCommands(n)
        valid_range = plan.valid_range
        # An interface only one handle can open is read through the thread-mode loop's handle.
        shares_loop_bus = config.can.interface not in SHAREABLE_INTERFACES | {"virtual"} and (
            loop_mode(config) == "thread"
        )
        setup = LoopSetup(
            config=config,
            input=InputSetup(
                plan.mixer,
                valid_range,
                plan.input_range,
                relay_outputs=record_dir is not None,
                # Recorded, the link gets every frame; else only what it acts on.
                relay_msg_ids=None if record_dir is not None else relayed_msg_ids(),
            ),
            log_level=logging.getLogger().getEffectiveLevel(),
            bus_receive="all" if shares_loop_bus else "none",
        )
        loop_end, main_end = relay_pair()
        self.runner = LoopRunner(
            setup, self.motor_tests, self.input_snapshot, self.stats, loop_end, self.sent
        )
        self.recording = self._open_recording(Path(record_dir)) if record_dir else None
        mcap = self.recording.mcap if self.recording is not None else None
        tlog = self.recording.tlog if self.recording is not None else None
        relayed = [MainConnection(main_end)]

        def uplink() -> MainConnection:
            if not relayed:
                raise LinkError("the output loop's relay of the autopilot link is gone")
            return relayed.pop()

        # The loop acts on the autopilot's outputs and arming, and counts them. Two inputs per
        # input timeout at least: the loop arms on nothing slower.
        needed_rate_hz = 2000 / config.output.input_timeout_ms
        self.link = MavlinkLink(
            config.mavlink,
            tlog=tlog,
            uplink=uplink,
            needed_rate_hz=needed_rate_hz,
            tlog_tap=mcap.mavlink if mcap is not None else None,
        )
        if mcap is not None:
            mcap.autopilot_clock = self.link.autopilot_boot_usec
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
        self._addresses = AddressReports(config, self.link.statustext)
        self.health_report = HealthReport(
            config, self.stats, self.input_snapshot, self.link, self.motor_test
        )
        self.fanout = Fanout(
            config,
            esc_table(config),
            self.link,
            health=self.health_report.health,
            actuators_input=self.health_report.actuators_input,
            actuators_output=self.health_report.actuators_output,
            shared_bus=self.runner.loop_bus if shares_loop_bus else None,
            recorder=self.recording.can if self.recording is not None else None,
            states=mcap,
        )
        self.health_report.fanout = self.fanout
        # Each ESC's command comes from the loop, not read back off the bus; a recording reads
        # every frame anyway and takes them there (the reader), each as sent.
        self.commands_sent = (
            CommandsSent(config, self.sent, self.fanout.table) if mcap is None else None
        )
        self._stop = threading.Event()
        self._absence: AbsenceWatch | None = None  # from when the loop and the reader run
        self._bus_watch = BusWatch(self._report)
        self._reported_state = LoopState.STARTING
        self._stop_reason = ""
        self._entered = [0] * len(LoopState)
        self._last_errors = 0
        self._errors_logged_at = 0.0
        self._tick_errors = 0

    def _open_recording(self, directory: Path) -> Recording:
        config = self._config
        mavlink = config.mavlink
        autopilot = (mavlink.autopilot_system_id, mavlink.autopilot_component_id)
        pairs = config.telemetry.pole_pairs
        return Recording.open(
            directory,
            config.can,
            traffic=TrafficReader(
                load_dialect(),
                mavlink.source,
                autopilot,
                (mavlink.autopilot_system_id, mavlink.component_id),
            ),
            metadata=metadata(
                config.output.protocol,
                config.escs.ids,
                mixer=self._plan.mixer.name,
                rate_hz=str(config.rate_hz),
                pole_pairs=",".join(map(str, pairs)) if isinstance(pairs, tuple) else str(pairs),
            ),
        )

    def stop(self, reason: str = "") -> None:
        """Stop: the loop starts its safe flush on its next tick (the request is one store to
        shared memory), and the supervisor winds down, logging ``reason`` (e.g. the signal's
        name) then. Called again (every stop signal calls it, from the thread of
        :class:`~bridge.stopping.StopSignals`), it changes nothing."""
        self._stop_reason = self._stop_reason or reason
        # Stopping before the loop is asked to: the loop, done with its flush, is never taken
        # for a loop that died.
        self._stop.set()
        self.runner.request_stop()

    def _log_stop_reason(self) -> None:
        if self._stop_reason:
            log.info("%s: stopping", self._stop_reason)

    def run(self) -> int:
        """Run until stopped; the exit code. The recording, if any, gets the log from here on
        and is closed at the end."""
        handler = LogHandler(self.recording.mcap) if self.recording is not None else None
        if handler is not None:
            logging.getLogger().addHandler(handler)
        try:
            return self._run()
        finally:
            if handler is not None:
                logging.getLogger().removeHandler(handler)
            if self.recording is not None:
                self.recording.close()

    def _run(self) -> int:
        config = self._config
        log.info(
            "esc-bridge: %s x%d (%s), mixer %s, %d Hz, loop in a %s; %s",
            config.output.protocol,
            len(config.escs.ids),
            config.family.driver(config.esc_setup).kind,
            self._plan.mixer.name,
            config.rate_hz,
            self.runner.mode,
            self._plan.load_text,
        )
        if self._stop.is_set():
            self._log_stop_reason()
            log.info("stopped before starting: nothing was sent")
            return 0
        self.link.start()
        try:
            self.runner.start()
            self._await_loop_start()
            self.fanout.start()
            # Counted from here: the loop's process may take seconds to start on a busy machine.
            self._absence = AbsenceWatch(config, time.monotonic_ns(), log.log)
            while not self._stop.is_set():
                if self.runner.wait_for_exit(SUPERVISE_PERIOD_S):
                    if self._stop.is_set() and LoopState(self.stats["state"]) == LoopState.STOPPED:
                        # Asked to stop during the wait (a stop signal), and the loop ended
                        # after its own flush: a stop, not a death.
                        break
                    return self._loop_died()
                self._watch()
            self._log_stop_reason()
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

    def _watch(self) -> None:
        stats = self.stats
        now_ns = time.monotonic_ns()
        self.link.note_outputs(stats["input_outputs"], now_ns)
        reader = self.fanout.reader
        if self._absence is not None:
            self._absence.check(
                now_ns,
                self.link.stats,
                None
                if reader is None
                else lambda: EscsHeard(
                    self.fanout.table.snapshot(now_ns),
                    reader.stats.frames,
                    self.fanout.table.unknown_frames,
                ),
            )
        self.health_report.sample()
        if self.commands_sent is not None:
            self.commands_sent.update()
        self._report_states()
        self._bus_watch.check(now_ns, stats, None if reader is None else reader.stats)
        self._addresses.check(stats)
        self.motor_test.watch()
        tick_errors = stats["tick_errors"]
        if tick_errors != self._tick_errors:
            self._report(SEVERITY_CRITICAL, "ESC out: FAULT encoding commands, motors safe")
            log.error("%d ticks could not encode commands; safe values were sent", tick_errors)
            self._tick_errors = tick_errors
        errors = stats["send_errors"]
        now = time.monotonic()
        if stats["tx_state"] != TxState.MOVING:
            # Reported once as the bus's state (BusWatch): not every second as well.
            self._last_errors = errors
        elif errors != self._last_errors and now - self._errors_logged_at >= ERROR_LOG_INTERVAL_S:
            log.warning(
                "CAN send failures: %d since the last report (%d in all; bus reopened %d times)",
                errors - self._last_errors,
                errors,
                stats["bus_reopens"],
            )
            self._last_errors = errors
            self._errors_logged_at = now

    def _report_states(self) -> None:
        """Report each state the loop entered since the last look, the current one last: a
        failsafe shorter than the watch's period (or than a stall of this process) is still
        told, by its entry count in the loop's statistics."""
        stats = self.stats
        state = LoopState(stats["state"])
        entered = stats.state_entries()
        for passed, (severity, text) in STATE_REPORTS.items():
            if passed != state and entered[passed] != self._entered[passed]:
                self._report(severity, text, state=passed)
        if state in STATE_REPORTS and (
            state != self._reported_state or entered[state] != self._entered[state]
        ):
            severity, text = STATE_REPORTS[state]
            self._report(severity, text, state=state)
        self._reported_state = state
        self._entered = entered

    def _log_loop_summary(self) -> None:
        stats = self.stats
        lateness = sorted(stats.lateness_us())
        if not lateness:
            return

        def at(fraction: float) -> int:
            return lateness[min(len(lateness) - 1, int(fraction * len(lateness)))]

        log.info(
            "output loop: %d ticks, %d frames, %d send errors, %d ticks held back, %d overruns, "
            "%d immediate sends, %d tick errors, %d decided again, %d left late; wake-up "
            "lateness p50 %d µs, p99 %d µs, max %d µs (last %d ticks)",
            stats["ticks"],
            stats["frames_sent"],
            stats["send_errors"],
            stats["ticks_held"],
            stats["overruns"],
            stats["immediate_sends"],
            stats["tick_errors"],
            stats["redecided"],
            stats["left_late"],
            at(0.5),
            at(0.99),
            lateness[-1],
            len(lateness),
        )

    def _log_telemetry_summary(self) -> None:
        sent = self.fanout.mavlink.stats
        log.info(
            "MAVLink ESC telemetry out: %d ESC_STATUS, %d ESC_INFO, %d ESC_TELEMETRY, %d failed "
            "rounds, %d rounds held up (the longest %.2f s late)",
            sent.esc_status,
            sent.esc_info,
            sent.esc_telemetry,
            sent.errors,
            sent.held_up,
            sent.longest_hold_s,
        )
        reader = self.fanout.reader
        if reader is None:
            return
        stats = reader.stats
        log.info(
            "CAN in: %d frames read, %d telemetry, %d malformed, %d error frames, %d read "
            "errors; %d of %d ESCs online; %s dropped by the kernel",
            stats.frames,
            stats.telemetry,
            stats.malformed,
            stats.controller.frames,
            stats.read_errors,
            sum(1 for esc in self.fanout.table.snapshot(time.monotonic_ns()) if esc.online),
            len(self.fanout.table),
            "?" if stats.kernel_drops is None else stats.kernel_drops,
        )

    def _report(
        self, severity: int, text: str, detail: str = "", state: LoopState | None = None
    ) -> None:
        """``text`` in the log (with ``detail`` after it) and as a STATUSTEXT; a ``state`` the
        loop entered is recorded."""
        level = logging.WARNING if severity <= SEVERITY_WARNING else logging.INFO
        log.log(level, "%s%s", text, f": {detail}" if detail else "")
        self.link.statustext(severity, text)
        if state is not None and self.recording is not None:
            self.recording.mcap.state(
                BridgeState(
                    state=state.name.lower(),
                    failsafe=state not in SENDING_COMMANDS,
                    severity=severity,
                    text=text,
                )
            )


def run(
    checked: Plan,
    record_dir: str | Path | None = None,
    stop_signals: StopSignals | None = None,
) -> int:
    """Run the bridge on a checked plan (:func:`bridge.daemon.preflight.plan`) until a stop signal;
    returns the process exit code.

    ``stop_signals``: the command line's, installed before anything else so that none is lost
    (see :mod:`bridge.stopping`); installed here when not given.

    Raises:
        LinkError: the MAVLink link or the CAN bus could not be opened.
    """
    stop_signals = stop_signals or StopSignals.install()
    supervisor = Supervisor(checked, record_dir)

    def on_signal(sig: signal.Signals) -> None:
        supervisor.stop(sig.name)

    stop_signals.on_stop(on_signal)
    return supervisor.run()
