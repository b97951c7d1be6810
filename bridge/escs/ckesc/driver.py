"""The CKESC command driver: RawCommand_12b (one frame per group of four channels), 14b or 10b.

All throttle groups go out in one tick (the ESCs read them as one command), so a cycle is one
tick. Every value is limited to 0..full scale here, whatever the stages before did.
"""

from __future__ import annotations

from collections.abc import Sequence

import can

from bridge.escs import uavcan_v0
from bridge.escs.ckesc import codec, records
from bridge.escs.drivers import unit_fraction

# The types whose frames end in a tail byte (its transfer ID), as every UAVCAN v0 frame does;
# RawCommand_10b has none.
_TRANSFER_TYPES = {
    "12b": records.TYPE_RAW_COMMAND_12B,
    "14b": records.TYPE_RAW_COMMAND_14B,
}


class CkescDriver:
    """RawCommand_12b (one frame per group of four channels), 14b or 10b throttle frames."""

    ticks_per_cycle = 1

    def __init__(self, command: str, channels: Sequence[int], ids: Sequence[int] = ()) -> None:
        """``channels[i]``: the throttle channel of mixer output i; ``ids[i]``: the node ID of
        its ESC (for messages only)."""
        self.kind = command
        self._ids = tuple(ids)
        self._channels = tuple(channels)
        self._command = command
        self._channel_index = [channel - 1 for channel in channels]
        self._full_scale = records.THROTTLE_10B_MAX if command == "10b" else records.THROTTLE_MAX
        self._throttles = [0] * records.MAX_CHANNELS
        self._groups = sorted({index // 4 + 1 for index in self._channel_index})
        self._transfer_ids = uavcan_v0.TransferIds()
        self._zeros = [0.0] * len(self._channel_index)
        self._fractions: Sequence[float] = ()  # whose throttles self._frames carry
        self._frames: list[can.Message] = []
        # The type whose transfer IDs the tail bytes count (10b frames have no tail byte).
        self._transfer_type = _TRANSFER_TYPES.get(command)

    def prepare(self, fractions: Sequence[float]) -> None:
        # The frames change with the input, not the tick: they are made here, when the input
        # arrives, and a tick that sends them only writes its transfer IDs into their tail
        # bytes. NaN never equals itself: encoded again.
        if fractions != self._fractions:
            self._fractions = ()  # until every frame is made: a raise leaves none cached
            throttles = self._throttles
            full_scale = self._full_scale
            for index, fraction in zip(self._channel_index, fractions, strict=True):
                throttles[index] = int(unit_fraction(fraction) * full_scale + 0.5)
            self._frames = self._encode(throttles)
            self._fractions = list(fractions)

    def tick_frames(self, tick: int, fractions: Sequence[float]) -> list[can.Message]:
        # Made here only when not prepared (slewed commands, safe values, a motor test); the
        # tail bytes are written in place (the frames are sent before the next call).
        self.prepare(fractions)
        frames = self._frames
        transfer_type = self._transfer_type
        if transfer_type is not None:
            next_id = self._transfer_ids.next
            for frame in frames:
                frame.data[-1] = uavcan_v0.tail_byte(next_id(transfer_type))
        return frames

    def _encode(self, throttles: list[int]) -> list[can.Message]:
        """The frames carrying ``throttles``, their transfer IDs still to be written."""
        if self._command == "12b":
            return [
                codec.encode_raw_12b(group, throttles[4 * group - 4 : 4 * group], 0)
                for group in self._groups
            ]
        if self._command == "14b":
            return [codec.encode_raw_14b(throttles[:4], 0)]
        return [codec.encode_raw_10b(throttles[:6])]

    def safe_frames(self, tick: int) -> list[can.Message]:
        return self.tick_frames(tick, self._zeros)

    def describe_command(self, fraction: float) -> str:
        full = self._full_scale
        return f"CKESC throttle {int(fraction * full + 0.5)}/{full}"

    def describe_esc(self, index: int) -> str:
        return f"CKESC node {self._ids[index]}, throttle channel {self._channels[index]}"
