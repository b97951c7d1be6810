"""The commands the output loop sent, into the ESC state.

Each ESC's ``command`` (in ``actuators/output`` and each ``esc/<n>/telemetry``) comes from what
the loop says it sent (:class:`~bridge.output.mailbox.SentCommands`, written when the commands
change), not from reading the bridge's own frames back off the bus, which woke the CAN reader
for every command frame. The frames of one cycle are made again here by the family's own
driver and read by its own decoder, so the values and units are those a read-back gives.
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import can

from bridge.config import BridgeConfig
from bridge.errors import CodecError
from bridge.escs import registry
from bridge.escs.drivers import make_driver
from bridge.escs.family import CommandSeen
from bridge.output.mailbox import SENT_COMMANDS, SENT_TEST, Sent, SentCommands
from bridge.output.motor_test import test_frames
from bridge.telemetry.reader import StateRecorder
from bridge.telemetry.state import EscTable


def take_commands(
    table: EscTable,
    commands: Sequence[CommandSeen],
    time_s: float,
    recorder: StateRecorder | None = None,
) -> None:
    """The bridge's commands into the ESC state and, when they changed, to ``recorder`` (the
    MCAP's ``/bridge/commands``): the one place both take them from, at ``time_s`` (wall)."""
    if table.note_commands(commands) and recorder is not None:
        recorder.commands(table.last_commands(), time_s)


class CommandsSent:
    """Brings the loop's newest commands into ``table``; :meth:`update` now and then (the
    supervisor's watch, a few times a second)."""

    def __init__(
        self,
        config: BridgeConfig,
        sent: SentCommands,
        table: EscTable,
        recorder: StateRecorder | None = None,
    ) -> None:
        self._family = registry.family(config.output.protocol)
        self._driver = make_driver(config)  # a copy of the loop's: its frames, never sent
        self._sent = sent
        self._table = table
        self._recorder = recorder
        self._seq = 0

    def update(self) -> None:
        """Take the loop's commands if they changed since the last call."""
        if self._sent.seq() == self._seq:
            return
        record = self._sent.read()
        if record is None:
            return
        self._seq = record.seq
        take_commands(self._table, self._commands(record), time.time(), self._recorder)

    def _commands(self, record: Sent) -> list[CommandSeen]:
        driver, family = self._driver, self._family
        frames: list[can.Message] = []
        for tick in range(driver.ticks_per_cycle):
            if record.kind == SENT_COMMANDS:
                frames += driver.tick_frames(tick, record.fractions)
            elif record.kind == SENT_TEST:
                frames += test_frames(driver, tick, record.fractions, record.test_index)
            else:
                frames += driver.safe_frames(tick)
        seen: list[CommandSeen] = []
        for frame in frames:
            try:
                decoded = family.decode(frame, self._table.node_set)
            except CodecError:
                continue
            if decoded is not None and family.telemetry(decoded) is None:
                seen += family.commands_seen(decoded)
        return seen
