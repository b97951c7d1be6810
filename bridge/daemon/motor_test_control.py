"""A ground station's MAV_CMD_DO_MOTOR_TEST, on the daemon's side: who may ask, whether the
loop may start it now, handing it to the loop through shared memory, and reporting it as it runs
(the loop itself runs the test and ends it: :mod:`bridge.output.motor_test`)."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from types import ModuleType
from typing import Any

from bridge.config import BridgeConfig
from bridge.daemon.severity import SEVERITY_INFO, SEVERITY_NOTICE, SEVERITY_WARNING
from bridge.output.mailbox import InputSnapshot, LoopStats, MotorTestBlock
from bridge.output.motor_test import (
    Decision,
    MotorTestCommand,
    MotorTestLimits,
    MotorTestPlan,
    Verdict,
    decide,
)
from bridge.output.safety import LoopState
from bridge.telemetry.payload import MotorTestHealth

log = logging.getLogger(__name__)

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
