"""The daemon's reporting: what each state of the control loop is called (STATUSTEXT and log),
and the bridge's health and actuator vectors as the Zenoh publisher takes them.

Called from the publishers' threads: everything here reads shared counters and snapshots, never
waits on the loop.
"""

from __future__ import annotations

import time

from bridge.can_errors import ControllerState
from bridge.config import BridgeConfig
from bridge.daemon.motor_test_control import MotorTestControl
from bridge.daemon.severity import (
    SEVERITY_CRITICAL,
    SEVERITY_INFO,
    SEVERITY_NOTICE,
    SEVERITY_WARNING,
)
from bridge.mavlink.link import MavlinkLink
from bridge.mixing.definition import INPUT_NAMES
from bridge.output.mailbox import InputSnapshot, LoopStats
from bridge.output.safety import SENDING_COMMANDS, LoopState
from bridge.output.transmit import TxState
from bridge.telemetry.fanout import Fanout
from bridge.telemetry.payload import (
    ActuatorsInputPayload,
    ActuatorsOutputPayload,
    CanBusHealth,
    CommandOut,
    HealthPayload,
    InputHealth,
    LinkHealth,
    OutputHealth,
)

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
"""What each state of the loop is reported as, when the loop enters it."""


class HealthReport:
    """The ``bridge/health``, ``actuators/input`` and ``actuators/output`` records of a running
    bridge. The supervisor calls :meth:`sample` a few times a second (the loop's measured rate)."""

    def __init__(
        self,
        config: BridgeConfig,
        stats: LoopStats,
        input_snapshot: InputSnapshot,
        link: MavlinkLink,
        motor_test: MotorTestControl,
    ) -> None:
        self._config = config
        self._stats = stats
        self._input_snapshot = input_snapshot
        self._link = link
        self._motor_test = motor_test
        self.fanout: Fanout | None = None
        """The reader and publishers, once built (their counters and the ESC state)."""
        self._output_ticks = (time.monotonic(), 0)
        self._output_rate_hz = 0.0

    def sample(self) -> None:
        """Measure the loop's tick rate over the last second or more."""
        now_s = time.monotonic()
        since_s, ticks = self._output_ticks
        if now_s - since_s >= 1.0:
            self._output_rate_hz = (self._stats["ticks"] - ticks) / (now_s - since_s)
            self._output_ticks = (now_s, self._stats["ticks"])

    def health(self) -> HealthPayload:
        """The bridge's health: loop state and rates, failsafe, counters."""
        stats, link, fanout = self._stats, self._link.stats, self.fanout
        assert fanout is not None, "the fan-out is built before anything publishes"
        state = LoopState(stats["state"])
        seen = self._input_snapshot.read()
        return HealthPayload(
            state=state.name.lower(),
            failsafe=state not in SENDING_COMMANDS,
            armed=seen is not None and seen.armed,
            motor_test=self._motor_test.snapshot(),
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
                other_address=stats["input_other_address"],
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
            can_bus=self._can_bus(),
            zenoh=fanout.zenoh_health(),
        )

    def _can_bus(self) -> CanBusHealth:
        stats, reader = self._stats, self.fanout.reader if self.fanout else None
        tx_entered = stats.tx_state_entries()
        controller = reader.stats.controller if reader is not None else None
        entered = controller.entered if controller is not None else [0] * len(ControllerState)
        return CanBusHealth(
            tx_state=TxState(stats["tx_state"]).name.lower(),
            ticks_held=stats["ticks_held"],
            tx_probes=stats["tx_probes"],
            stuck=tx_entered[TxState.STUCK],
            down=tx_entered[TxState.DOWN],
            gone=tx_entered[TxState.GONE],
            controller_state=(
                controller.state if controller is not None else ControllerState.ERROR_ACTIVE
            ).name.lower(),
            error_frames=controller.frames if controller is not None else 0,
            error_warning=entered[ControllerState.ERROR_WARNING],
            error_passive=entered[ControllerState.ERROR_PASSIVE],
            bus_off=entered[ControllerState.BUS_OFF],
            restarts=controller.restarts if controller is not None else 0,
            receive_overflows=controller.receive_overflows if controller is not None else 0,
            reader_reopens=reader.stats.reopens if reader is not None else 0,
        )

    def actuators_input(self) -> ActuatorsInputPayload | None:
        """What came in: the autopilot's newest outputs (present channels) and their mix."""
        seen = self._input_snapshot.read()
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
        assert self.fanout is not None, "the fan-out is built before anything publishes"
        escs = self.fanout.table.snapshot(time.monotonic_ns())
        return ActuatorsOutputPayload(
            state=LoopState(self._stats["state"]).name.lower(),
            commands=tuple(
                CommandOut(
                    motor=esc.motor, node_id=esc.node_id, value=esc.command, unit=esc.command_unit
                )
                for esc in escs
            ),
        )
