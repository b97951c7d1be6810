"""The DroneCAN output driver: each tick's command fractions as one RawCommand transfer, and
the bridge's NodeStatus once a second.

Every tick addresses every ESC (``ticks_per_cycle`` 1): one RawCommand carries a value per ESC
index up to the highest one in use (unused slots 0), as ArduPilot's ``SRV_send_esc`` does; more
than four slots make it a multi-frame transfer whose frames go out back to back.

Values are limited here, whatever the stages before did: a forward-only ESC gets
``round(fraction x 8191)`` with the fraction held to 0..1, a reversible one (ArduPilot's
``CAN_D1_UC_ESC_RV``) the fraction held to -1..1 (NaN: 0). The safe value is 0 for all.

NodeStatus: the standard asks every node on the bus to publish it at least once a second; ESCs,
autopilots and tools (the DroneCAN GUI tool) learn from it who is on the bus and how it is.
The family interface has no periodic hook, so the driver adds it to the first tick's frames and
then to the first tick at least a second after the previous one (the loop's ticks are not a
clock: missed ticks are skipped, and ``immediate`` latency adds some), safe frames included;
its uptime counts from the driver's creation.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

import can

from bridge.errors import ValueRangeError
from bridge.escs.drivers import signed_fraction, unit_fraction
from bridge.escs.dronecan.wire import (
    COMMAND_MAX,
    DEFAULT_NODE_ID,
    MAX_COMMANDS,
    NODE_STATUS_PERIOD_NS,
    RawCommandEncoder,
    node_status_frame,
)


class DronecanDriver:
    """RawCommand for the ESCs at ``esc_indices`` (one per mixer output, 0..19, distinct)
    from node ``node_id``; ``reversible`` per output (default: none).

    Raises:
        ValueRangeError: no ESC, an index outside 0..19 or given twice, a ``reversible`` list
            of another length, or a node ID outside 1..125.
    """

    ticks_per_cycle = 1

    def __init__(
        self,
        esc_indices: Sequence[int],
        node_id: int = DEFAULT_NODE_ID,
        reversible: Sequence[bool] | None = None,
        *,
        node_status: bool = True,
        clock: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        indices = list(esc_indices)
        if not indices or not all(0 <= index < MAX_COMMANDS for index in indices):
            raise ValueRangeError(f"ESC indices {indices}: 1..20 of them, each 0..19")
        if len(set(indices)) != len(indices):
            raise ValueRangeError(f"ESC indices {indices}: each ESC index once")
        flags = [False] * len(indices) if reversible is None else list(reversible)
        if len(flags) != len(indices):
            raise ValueRangeError(f"reversible {flags}: one flag per ESC ({len(indices)})")
        self._slots = list(zip(indices, flags, strict=True))
        self._commands = [0] * (max(indices) + 1)
        self._zeros = [0] * len(self._commands)
        self._fractions: Sequence[float] = ()  # whose values self._commands holds
        self._encoder = RawCommandEncoder(len(self._commands), node_id)
        self._node_id = node_id
        self._node_status = node_status
        self._clock = clock
        self._started_ns = clock()
        self._status_due_ns = self._started_ns
        self._status_transfer_id = 0

    @property
    def command_slots(self) -> int:
        """Values in each RawCommand (the highest ESC index + 1)."""
        return len(self._commands)

    @property
    def kind(self) -> str:
        return f"RawCommand x{len(self._commands)}"

    def prepare(self, fractions: Sequence[float]) -> None:
        # The RawCommand's frames change with the input, not the tick: made here, and a tick
        # that sends them only writes its transfer ID. NaN never equals itself: made again.
        if fractions != self._fractions:
            self._fractions = ()  # until the frames are made: a raise leaves none kept
            commands = self._commands
            for (index, reverse), fraction in zip(self._slots, fractions, strict=True):
                limited = signed_fraction(fraction) if reverse else unit_fraction(fraction)
                commands[index] = round(limited * COMMAND_MAX)
            self._encoder.prepare(commands)
            self._fractions = list(fractions)

    def describe_command(self, fraction: float) -> str:
        return f"DroneCAN RawCommand {round(fraction * COMMAND_MAX)}"

    def describe_esc(self, index: int) -> str:
        esc_index = self._slots[index][0]
        return f"DroneCAN ESC {esc_index + 1} (esc_index {esc_index})"

    def _with_status(self, frames: list[can.Message]) -> list[can.Message]:
        if not self._node_status:
            return frames
        now = self._clock()
        if now < self._status_due_ns:
            return frames
        # One period on; after a stall, one period from now rather than a burst.
        due = self._status_due_ns + NODE_STATUS_PERIOD_NS
        self._status_due_ns = due if due > now else now + NODE_STATUS_PERIOD_NS
        transfer_id = self._status_transfer_id
        self._status_transfer_id = (transfer_id + 1) & 0x1F
        uptime_s = (now - self._started_ns) // 1_000_000_000
        # A new list: the encoder keeps its own for the next transfer.
        return [*frames, node_status_frame(self._node_id, transfer_id, uptime_s)]

    def tick_frames(self, tick: int, fractions: Sequence[float]) -> list[can.Message]:
        # Made here only when not prepared (slewed commands, a motor test).
        self.prepare(fractions)
        return self._with_status(self._encoder.frames(self._commands))

    def safe_frames(self, tick: int) -> list[can.Message]:
        return self._with_status(self._encoder.frames(self._zeros))
