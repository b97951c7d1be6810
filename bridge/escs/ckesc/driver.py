"""The CKESC command driver: RawCommand_12b (one frame per group of four channels), 14b or 10b.

All throttle groups go out in one tick (the ESCs read them as one command), so a cycle is one
tick. Every value is limited to 0..full scale here, whatever the stages before did.
"""

from __future__ import annotations

from collections.abc import Sequence

import can

from bridge.escs import ckesc, uavcan_v0
from bridge.escs.drivers import unit_fraction


class CkescDriver:
    """RawCommand_12b (one frame per group of four channels), 14b or 10b throttle frames."""

    ticks_per_cycle = 1

    def __init__(self, command: str, channels: Sequence[int]) -> None:
        self._command = command
        self._channel_index = [channel - 1 for channel in channels]
        self._full_scale = ckesc.THROTTLE_10B_MAX if command == "10b" else ckesc.THROTTLE_MAX
        self._throttles = [0] * ckesc.MAX_CHANNELS
        self._groups = sorted({index // 4 + 1 for index in self._channel_index})
        self._transfer_ids = uavcan_v0.TransferIds()
        self._zeros = [0.0] * len(self._channel_index)
        self._fractions: Sequence[float] = ()  # whose throttles are in self._throttles

    def tick_frames(self, tick: int, fractions: Sequence[float]) -> list[can.Message]:
        # The throttles change with the input, not the tick: a tick that repeats the last
        # input only encodes (its transfer IDs are new). NaN never equals itself: recomputed.
        if fractions != self._fractions:
            self._fractions = ()  # until every throttle is written: a raise leaves none cached
            throttles = self._throttles
            full_scale = self._full_scale
            for index, fraction in zip(self._channel_index, fractions, strict=True):
                throttles[index] = int(unit_fraction(fraction) * full_scale + 0.5)
            self._fractions = list(fractions)
        throttles = self._throttles
        if self._command == "12b":
            next_id = self._transfer_ids.next
            return [
                ckesc.encode_raw_12b(
                    group, throttles[4 * group - 4 : 4 * group], next_id(ckesc.TYPE_RAW_COMMAND_12B)
                )
                for group in self._groups
            ]
        if self._command == "14b":
            tid = self._transfer_ids.next(ckesc.TYPE_RAW_COMMAND_14B)
            return [ckesc.encode_raw_14b(throttles[:4], tid)]
        return [ckesc.encode_raw_10b(throttles[:6])]

    def safe_frames(self, tick: int) -> list[can.Message]:
        return self.tick_frames(tick, self._zeros)
