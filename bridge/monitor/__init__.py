"""``esc-bridge monitor``: a live table of every ESC, from a bridge over Zenoh or from the bus.

:mod:`bridge.monitor.view` turns telemetry dicts into a table (pure functions);
:mod:`bridge.monitor.sources` gives the latest dicts per vehicle; :func:`schedule` paces the
redraws. The CLI prints; nothing here does.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator

from bridge.monitor.sources import (
    DEFAULT_PREFIX,
    STALE_AFTER_S,
    CanSource,
    Source,
    ZenohSource,
    check_prefix,
    monitor_zenoh_config,
    prefix_of,
)
from bridge.monitor.view import (
    FAILURE_NAMES,
    VehicleState,
    failure_names,
    plain_text,
    render_table,
    waiting_text,
)

LIVE_PERIOD_S = 0.1
"""Redraw period of the live view (10 Hz)."""
PLAIN_PERIOD_S = 1.0
"""Period of the plain-text tables printed when stdout is not a terminal."""


STOP_POLL_S = 0.05
"""How often a schedule looks at its stop flag while it waits for the next redraw."""


def schedule(
    period_s: float,
    duration_s: float | None = None,
    stopped: Callable[[], bool] = lambda: False,
) -> Iterator[bool]:
    """Yield at once and then every ``period_s`` (never in a burst after a stall); when
    ``duration_s`` has passed or ``stopped()`` says so (Ctrl-C), yield ``True`` once more (the
    final redraw) and stop."""
    start = time.monotonic()
    end = None if duration_s is None else start + duration_s
    due = start
    while True:
        now = time.monotonic()
        if (end is not None and now >= end) or stopped():
            yield True
            return
        yield False
        due = max(due + period_s, now)
        wake = due if end is None else min(due, end)
        while (left := wake - time.monotonic()) > 0 and not stopped():
            time.sleep(min(left, STOP_POLL_S))


__all__ = [
    "DEFAULT_PREFIX",
    "FAILURE_NAMES",
    "LIVE_PERIOD_S",
    "PLAIN_PERIOD_S",
    "STALE_AFTER_S",
    "CanSource",
    "Source",
    "VehicleState",
    "ZenohSource",
    "check_prefix",
    "failure_names",
    "monitor_zenoh_config",
    "plain_text",
    "prefix_of",
    "render_table",
    "schedule",
    "waiting_text",
]
