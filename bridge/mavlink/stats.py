"""The MAVLink link's counters: the autopilot's connection's (and the link-wide ones), and
each extra output's; and the sparse logging that goes with counting trouble."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

__all__ = ["Counters", "LinkStats", "OutputStats", "log_sparsely"]


@dataclass
class LinkStats:
    """Counters of the autopilot's connection (and the link-wide ones), updated in place by
    the link's threads; read them field by field."""

    messages: int = 0
    """Well-formed MAVLink messages received on the autopilot's connection, from any sender."""
    outputs: int = 0
    """Configured output messages from the autopilot handed to the sink (each
    SERVO_OUTPUT_RAW port counts)."""
    ignored_foreign: int = 0
    """HEARTBEATs and configured output messages from any other system or component (a ground
    station's HEARTBEAT counts too)."""
    rejected_unsigned: int = 0
    """With a signing key: messages refused as unsigned, badly signed or replayed."""
    bad_data: int = 0
    """Stretches of bytes that were no valid MAVLink frame (junk, bad CRC, truncation)."""
    reconnects: int = 0
    """Times the connection was reopened after it dropped."""
    output_rate_hz: float = 0.0
    """Output messages per second over the last ~1 s; 0 once none arrived for ~1 s."""
    last_heartbeat_ns: int = 0
    """``time.monotonic_ns()`` of the autopilot's last HEARTBEAT; 0 = none yet."""
    last_output_ns: int = 0
    """``time.monotonic_ns()`` of the last output message handed to the sink; 0 = none yet."""
    send_failures: int = 0
    """Messages not sent to the autopilot because its connection was down (being reopened,
    or closed) or the write failed."""
    handler_errors: int = 0
    """Messages dropped because handling them raised (a fault in the sink or the command
    handler); logged."""
    commands: int = 0
    """COMMAND_LONGs addressed to the bridge, from any connection."""
    tlog_errors: int = 0
    """Frames that could not be appended to the recording (disk full, file closed)."""


@dataclass
class OutputStats:
    """Counters of one extra output, updated in place by its threads."""

    url: str
    """As configured."""
    messages: int = 0
    """Well-formed MAVLink messages received on it (only commands are acted on)."""
    rejected_unsigned: int = 0
    """With a signing key: messages refused as unsigned, badly signed or replayed."""
    bad_data: int = 0
    """Stretches of bytes that were no valid MAVLink frame."""
    reconnects: int = 0
    """Times it was reopened after it dropped (or opened late, after failing at start)."""
    sent: int = 0
    """Frames handed to its transport. pymavlink drops silently what a UDP or listening TCP
    output cannot deliver (no peer yet, unreachable), and those count here too."""
    send_failures: int = 0
    """Frames not sent: the output was down, its queue overflowed, or the write failed."""
    handler_errors: int = 0
    """Messages dropped because handling them raised; logged."""


Counters = LinkStats | OutputStats
"""The counters of one connection: the autopilot's or an output's."""


def log_sparsely(
    logger: logging.Logger, level: int, count: int, text: str, *args: Any, exc_info: bool = False
) -> None:
    """Log the 1st, 2nd, 4th, 8th... occurrence, so a flood of bad input cannot flood the log."""
    if count & (count - 1) == 0:
        logger.log(level, text + " (%d so far)", *args, count, exc_info=exc_info)
