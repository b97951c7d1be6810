"""Simulated DroneCAN ESC nodes: pure state machines with an explicit clock, like the CKESC and
FT simulators (:mod:`bridge.sim.base`), put on a bus by :mod:`bridge.sim.runner`.

Each ESC follows its slot (``esc_index``) of every ``uavcan.equipment.esc.RawCommand`` on the
bus, from any node, and publishes ``uavcan.equipment.esc.Status`` and
``uavcan.protocol.NodeStatus`` from its own node ID. Frames are read and written with the
``dronecan`` package (:mod:`bridge.escs.dronecan.codec`), not with the bridge's hand encoder,
so a simulated flight checks that encoder end to end. The ESCs of one :func:`make_escs` call
share one decoder: the runner hands each of them the same frame, which is decoded once.

Decisions where the standard is silent (what common DroneCAN ESC firmware does):

- A value ``v`` of the ESC's slot drives the motor at duty ``v / 8191``; a forward-only ESC
  treats a negative value as 0, a reversible one (``reversible=True``) runs backwards.
- A RawCommand too short to reach the ESC's slot leaves the ESC's command as it was.
- No RawCommand for :data:`COMMAND_TIMEOUT_S` (500 ms): the motor is released (duty 0) and
  counted in ``stats.timeouts``.
- Status every :data:`STATUS_PERIOD_S` (50 ms) and NodeStatus every second, from power-up,
  commanded or not. Status: supply voltage, supply current, MOSFET temperature (in kelvin), rpm
  (signed), power rating = |duty| in percent, error count = malformed frames seen.
  NodeStatus: health OK, or ERROR under an over-temperature or over-current fault.
- Faults (:class:`~bridge.sim.base.Faults`): ``over_temperature`` reports 300 °C,
  ``over_current`` 5000 A, ``corrupt`` breaks every transfer's CRC (Status) or tail byte
  (NodeStatus), ``silent`` sends nothing (commands still act), ``stuck_motor`` blocks the rotor.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Final

import can

from bridge.errors import FrameError
from bridge.escs.dronecan.codec import (
    KELVIN_OFFSET,
    Decoder,
    DronecanFrame,
    EscStatus,
    NodeStatus,
    RawCommand,
    Sender,
)
from bridge.escs.dronecan.keys import DronecanKeys
from bridge.escs.dronecan.wire import COMMAND_MAX, HEALTH_ERROR, HEALTH_OK, MODE_OPERATIONAL
from bridge.escs.family import EscSetup
from bridge.sim.base import Faults, SimEsc
from bridge.sim.motor import Motor, MotorParams

__all__ = [
    "COMMAND_TIMEOUT_S",
    "NODE_ID_BASE",
    "NODE_STATUS_PERIOD_S",
    "STATUS_PERIOD_S",
    "DronecanSimStats",
    "SimDronecanEsc",
    "make_escs",
    "simulators",
]

COMMAND_TIMEOUT_S: Final = 0.5
STATUS_PERIOD_S: Final = 0.05
NODE_STATUS_PERIOD_S: Final = 1.0
NODE_ID_BASE: Final = 20
"""A simulated ESC's node ID is this plus its ESC index unless given."""
OVER_TEMPERATURE_C: Final = 300.0
OVER_CURRENT_A: Final = 5000.0
_EPS_S: Final = 1e-9


@dataclass
class DronecanSimStats:
    """Counters of one simulated DroneCAN ESC."""

    commands: int = 0
    """RawCommand transfers that reached this ESC's slot."""
    bad_frames: int = 0
    """Frames of our types that broke their transfer (its error count)."""
    timeouts: int = 0
    status_transfers: int = 0
    node_status_transfers: int = 0


class _CommandReader:
    """One decoder shared by the ESCs on a bus: the same frame object is decoded once."""

    __slots__ = ("_decoder", "_last", "_last_error", "_last_frame")

    def __init__(self) -> None:
        self._decoder = Decoder()
        self._last: can.Message | None = None
        self._last_frame: DronecanFrame | None = None
        self._last_error = False

    def read(self, msg: can.Message) -> tuple[DronecanFrame | None, bool]:
        """The transfer ``msg`` completes (if any) and whether it broke one."""
        if msg is not self._last:
            self._last = msg
            try:
                self._last_frame, self._last_error = self._decoder.decode(msg), False
            except FrameError:
                self._last_frame, self._last_error = None, True
        return self._last_frame, self._last_error


class SimDronecanEsc:
    """One simulated DroneCAN ESC following slot ``esc_index`` (0..19) from node
    ``can_node_id`` (1..125; default :data:`NODE_ID_BASE` + index). Its :attr:`node_id` for the
    runner (faults, look-ups) is the ESC number, index + 1, the ID the bridge knows it by
    (``[escs] ids``; ArduPilot's "ESC 1" is index 0).

    Raises:
        ValueError: an index or node ID out of range.
    """

    def __init__(
        self,
        esc_index: int,
        *,
        can_node_id: int | None = None,
        motor: Motor | None = None,
        reversible: bool = False,
        reader: _CommandReader | None = None,
    ) -> None:
        if not 0 <= esc_index <= 19:
            raise ValueError(f"esc_index={esc_index!r} outside 0..19")
        node = NODE_ID_BASE + esc_index if can_node_id is None else can_node_id
        if not 1 <= node <= 125:
            raise ValueError(f"can_node_id={node!r} outside 1..125")
        self.esc_index = esc_index
        self.node_id = esc_index + 1
        self.can_node_id = node
        self.motor = motor or Motor()
        self.faults = Faults()
        self.reversible = reversible
        self.stats = DronecanSimStats()
        self.command: int | None = None
        """The value of the last RawCommand that reached this ESC's slot."""
        self._reader = reader or _CommandReader()
        self._sender = Sender(node)
        self._last_command_s: float | None = None
        self._last_poll_s: float | None = None
        self._next_status_s: float | None = None
        self._next_node_status_s: float | None = None
        self._started_s: float | None = None

    @property
    def commanded(self) -> bool:
        """True while a command is in force (less than 500 ms old)."""
        return self._last_command_s is not None

    def handle(self, msg: can.Message, now_s: float) -> list[can.Message]:
        """Follow ``msg`` if it completes a RawCommand reaching this ESC's slot; never answers."""
        frame, broken = self._reader.read(msg)
        if broken:
            self.stats.bad_frames += 1
            return []
        if frame is None or not isinstance(frame.message, RawCommand):
            return []
        commands = frame.message.commands
        if self.esc_index >= len(commands):
            return []
        value = commands[self.esc_index]
        self.command = value
        if value < 0 and not self.reversible:
            value = 0
        self.motor.set_duty(value / COMMAND_MAX)
        self.stats.commands += 1
        self._last_command_s = now_s
        return []

    def _expire(self, now_s: float) -> None:
        last = self._last_command_s
        if last is not None and now_s - last >= COMMAND_TIMEOUT_S - _EPS_S:
            self._last_command_s = None
            self.stats.timeouts += 1
            self.motor.set_duty(0.0)

    def poll(self, now_s: float, supply_v: float) -> list[can.Message]:
        """Advance the motor to ``now_s``, drop a command older than 500 ms, and return the
        Status and NodeStatus transfers due (at most one of each per call: no bursts)."""
        motor = self.motor
        motor.stuck = self.faults.stuck_motor
        self._expire(now_s)
        dt = 0.0 if self._last_poll_s is None else max(0.0, now_s - self._last_poll_s)
        self._last_poll_s = now_s
        motor.step(dt, supply_v)
        if self._started_s is None:
            self._started_s = self._next_status_s = self._next_node_status_s = now_s
        frames: list[can.Message] = []
        if self._due("_next_status_s", STATUS_PERIOD_S, now_s):
            frames += self._status_frames(supply_v)
        if self._due("_next_node_status_s", NODE_STATUS_PERIOD_S, now_s):
            frames += self._node_status_frames(now_s)
        return frames

    def _due(self, attribute: str, period_s: float, now_s: float) -> bool:
        due: float = getattr(self, attribute)
        if now_s + _EPS_S < due:
            return False
        due += period_s
        setattr(self, attribute, due if due > now_s else now_s + period_s)
        return True

    def _status_frames(self, supply_v: float) -> list[can.Message]:
        if self.faults.silent:
            return []
        motor = self.motor
        current = OVER_CURRENT_A if self.faults.over_current else motor.current_a
        temp_c = OVER_TEMPERATURE_C if self.faults.over_temperature else motor.mos_temp_c
        status = EscStatus(
            esc_index=self.esc_index,
            error_count=self.stats.bad_frames,
            voltage_v=supply_v,
            current_a=current,
            temperature_k=temp_c + KELVIN_OFFSET,
            rpm=max(-(1 << 17), min((1 << 17) - 1, round(motor.rpm))),
            power_rating_pct=min(127, round(abs(motor.duty) * 100)),
        )
        frames = self._sender.frames(status)
        if self.faults.corrupt:
            frames[0].data[0] ^= 0xFF  # the transfer CRC's low byte: never matches again
        self.stats.status_transfers += 1
        return frames

    def _node_status_frames(self, now_s: float) -> list[can.Message]:
        if self.faults.silent:
            return []
        started = self._started_s if self._started_s is not None else now_s
        faulty = self.faults.over_temperature or self.faults.over_current
        status = NodeStatus(
            uptime_s=int(now_s - started),
            health=HEALTH_ERROR if faulty else HEALTH_OK,
            mode=MODE_OPERATIONAL,
        )
        frames = self._sender.frames(status)
        if self.faults.corrupt:
            frames[0].data[-1] |= 0x20  # a first frame with the toggle set: no transfer
        self.stats.node_status_transfers += 1
        return frames


def make_escs(
    esc_indices: Sequence[int],
    *,
    motor_params: MotorParams | None = None,
    reversible: Sequence[bool] | None = None,
) -> list[SimDronecanEsc]:
    """Simulated ESCs for ``esc_indices`` (node IDs :data:`NODE_ID_BASE` + index), each with a
    motor of its own, sharing one command decoder.

    Raises:
        ValueError: an index out of range, given twice, or a ``reversible`` list of another
            length.
    """
    indices = list(esc_indices)
    if len(set(indices)) != len(indices):
        raise ValueError(f"esc_indices={indices!r}: expected distinct indices")
    flags = [False] * len(indices) if reversible is None else list(reversible)
    if len(flags) != len(indices):
        raise ValueError(f"reversible={flags!r}: one flag per ESC ({len(indices)})")
    reader = _CommandReader()
    return [
        SimDronecanEsc(index, motor=Motor(motor_params), reversible=flag, reader=reader)
        for index, flag in zip(indices, flags, strict=True)
    ]


def simulators(setup: EscSetup[DronecanKeys], motor_params: MotorParams | None) -> list[SimEsc]:
    """A simulated DroneCAN ESC for each ESC number of ``setup.ids`` (esc_index = number - 1)."""
    return list(make_escs([number - 1 for number in setup.ids], motor_params=motor_params))
