"""The ESC state's ``command`` from what the loop says it sent, not read back off the bus."""

from __future__ import annotations

import time

import pytest

from bridge.config import build_config
from bridge.daemon.commands_sent import CommandsSent
from bridge.daemon.preflight import plan
from bridge.output.mailbox import SENT_COMMANDS, SENT_SAFE, SENT_TEST, SentCommands
from bridge.telemetry.for_config import esc_table


def _commands(protocol: str, kind: int, index: int, fractions: list[float]) -> list[object]:
    raw = {
        "output": {"protocol": protocol},
        "mixer": {"name": "passthrough-4"},
        "can": {"interface": "virtual", "channel": "commands-sent"},
        "zenoh": {"enabled": False},
    }
    checked = plan(build_config(raw, "test"))
    sent = SentCommands(4)
    table = esc_table(checked.config)
    commands = CommandsSent(checked.config, sent, table)
    commands.update()  # nothing written yet: nothing known
    assert [s.command for s in table.snapshot(time.monotonic_ns())] == [None] * 4
    sent.write(kind, index, fractions)
    commands.update()
    return [(s.command, s.command_unit) for s in table.snapshot(time.monotonic_ns())]


@pytest.mark.parametrize(
    ("kind", "index", "fractions", "expected"),
    [
        (SENT_COMMANDS, -1, [0.0, 0.25, 0.5, 1.0], [0.0, 500.0, 1000.0, 2000.0]),
        (SENT_SAFE, -1, [0.5] * 4, [0.0] * 4),
        (SENT_TEST, 2, [0.0, 0.0, 0.3, 0.0], [0.0, 0.0, 600.0, 0.0]),
    ],
)
def test_ckesc_commands_are_the_throttles_the_loop_sent(
    kind: int, index: int, fractions: list[float], expected: list[float]
) -> None:
    assert _commands("ckesc", kind, index, fractions) == [(v, "throttle") for v in expected]


def test_ft_commands_cover_every_esc_of_the_cycle() -> None:
    # One ESC a tick: the whole cycle's frames are made, so every ESC has its command.
    running = _commands("ft", SENT_COMMANDS, -1, [0.1, 0.2, 0.5, 1.0])
    assert running == [(pytest.approx(v), "current_a") for v in (2.0, 4.0, 10.0, 20.0)]
    # The motor under test at its fraction, the others at their safe value (0 A).
    testing = _commands("ft", SENT_TEST, 1, [0.0, 0.25, 0.0, 0.0])
    assert (
        testing
        == [(0.0, "current_a"), (pytest.approx(5.0), "current_a")] + [(0.0, "current_a")] * 2
    )


def test_a_new_record_is_taken_once() -> None:
    raw = {
        "can": {"interface": "virtual", "channel": "commands-sent-2"},
        "zenoh": {"enabled": False},
    }
    checked = plan(build_config(raw, "test"))
    n = len(checked.mixer.outputs)
    sent, table = SentCommands(n), esc_table(checked.config)
    commands = CommandsSent(checked.config, sent, table)
    sent.write(SENT_COMMANDS, -1, [0.5] * n)
    commands.update()
    assert {s.command for s in table.snapshot(0)} == {1000.0}
    sent.write(SENT_SAFE, -1, [0.5] * n)
    commands.update()
    assert {s.command for s in table.snapshot(0)} == {0.0}
