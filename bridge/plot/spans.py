"""The spans of a flight: the autopilot armed, the bridge in failsafe or in a motor test, and
every ESC commanded to stop while armed. Pure functions of the tlog's events and the commands.

- armed: from the autopilot's HEARTBEAT armed bit; a HEARTBEAT stream that stops ends the span
  :data:`ARMING_TIMEOUT_S` after the last one, as the bridge's own ``arming_timeout_ms`` default
  does;
- failsafe and motor test: from the bridge's own ``ESC out: ...`` STATUSTEXTs (its state
  reports, recorded in the tlog as it sent them), each until the next state report;
- stopped while armed: from the commands on the bus, where the last command of every ESC
  stops its motor (the bridge's safe values) while the autopilot was armed, however short
  (the bridge's state reports come from a supervisor that looks a few times a second and can
  miss a short failsafe; the bus shows every one), but for the hand-over at arming and
  disarming (:data:`HANDOVER_S`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Final

from bridge.plot.recording import Heartbeat, StatusText

ARMING_TIMEOUT_S: Final = 3.0
"""An armed autopilot whose HEARTBEATs stop counts as disarmed this long after the last one."""
HANDOVER_S: Final = 0.25
"""Every ESC commanded to stop for this long or less at the start or the end of an armed span
is the bridge taking the new arming state a moment before or after the tlog logs it, not
shown; within an armed span every stop is shown, however short."""
STATE_PREFIX: Final = "ESC out: "
"""How the bridge's STATUSTEXTs about its output state begin
(``bridge.daemon.health.STATE_REPORTS``)."""
SEVERITY_CRITICAL: Final = 2
"""MAV_SEVERITY_CRITICAL: the bridge's failsafe states are reported so."""

# Span kinds.
ARMED: Final = "armed"
FAILSAFE: Final = "failsafe"
MOTOR_TEST: Final = "motor test"
STOPPED_ARMED: Final = "stopped while armed"


@dataclass(frozen=True, slots=True)
class Span:
    """A stretch of the flight: the autopilot armed, the bridge in failsafe, ..."""

    kind: str
    """:data:`ARMED`, :data:`FAILSAFE`, :data:`MOTOR_TEST` or :data:`STOPPED_ARMED`."""
    start_s: float
    end_s: float
    label: str
    """What it was, in words (the bridge's text for its own states)."""

    def shifted(self, by_s: float) -> Span:
        return Span(self.kind, self.start_s - by_s, self.end_s - by_s, self.label)


# -- spans ----------------------------------------------------------------------------------------


def armed_spans(
    heartbeats: Sequence[Heartbeat], end_s: float, lost_after_s: float = ARMING_TIMEOUT_S
) -> list[Span]:
    """Where the autopilot was armed: from an armed HEARTBEAT to the next disarmed one, or to
    ``lost_after_s`` after the last armed one when none followed in time (cut at ``end_s``)."""
    spans: list[Span] = []
    start: float | None = None
    last = 0.0
    for beat in heartbeats:
        if start is not None and beat.t_s - last > lost_after_s:
            spans.append(Span(ARMED, start, last + lost_after_s, "armed (HEARTBEAT lost)"))
            start = None
        if beat.armed:
            start = beat.t_s if start is None else start
            last = beat.t_s
        elif start is not None:
            spans.append(Span(ARMED, start, beat.t_s, "armed"))
            start = None
    if start is not None:
        lost = last + lost_after_s < end_s
        label = "armed (HEARTBEAT lost)" if lost else "armed"
        spans.append(Span(ARMED, start, min(end_s, last + lost_after_s), label))
    return spans


def bridge_state(text: StatusText) -> str | None:
    """The output state a bridge STATUSTEXT reports: :data:`FAILSAFE` (a critical ``ESC out:``
    state: input stale or invalid, HEARTBEAT lost, outputs too slow), :data:`MOTOR_TEST`, another
    state's first words (``armed``, ``disarmed``, ...), or None for a text that is no state
    (other messages, and ``ESC out: FAULT ...``, which the bridge sends within a state)."""
    if not text.text.startswith(STATE_PREFIX):
        return None
    body = text.text[len(STATE_PREFIX) :]
    if body.startswith("FAULT"):
        return None
    if body.startswith("MOTOR TEST"):
        return MOTOR_TEST
    if text.severity <= SEVERITY_CRITICAL:
        return FAILSAFE
    return body.split(",")[0]


def bridge_spans(texts: Sequence[StatusText], end_s: float) -> list[Span]:
    """The bridge's failsafe and motor-test states, each from its STATUSTEXT to the next state's
    (or ``end_s``)."""
    states = [(text, kind) for text in texts if (kind := bridge_state(text)) is not None]
    spans: list[Span] = []
    for i, (text, kind) in enumerate(states):
        if kind not in (FAILSAFE, MOTOR_TEST):
            continue
        until = states[i + 1][0].t_s if i + 1 < len(states) else end_s
        spans.append(Span(kind, text.t_s, until, text.text[len(STATE_PREFIX) :]))
    return spans


def stopped_while_armed(
    all_stopped: Sequence[tuple[float, bool]],
    armed: Sequence[Span],
    handover_s: float = HANDOVER_S,
) -> list[Span]:
    """Where every ESC was commanded to stop while the autopilot was armed. ``all_stopped``:
    (time, every ESC's last command is a stop) at each change. A stop that reaches the start
    or the end of an armed span counts only when longer than ``handover_s``: shorter, it is the
    bridge taking the HEARTBEAT's new state a moment before or after the tlog has it."""
    spans: list[Span] = []
    stops: list[tuple[float, float]] = []
    for i, (t_s, stopped) in enumerate(all_stopped):
        if stopped:
            until = all_stopped[i + 1][0] if i + 1 < len(all_stopped) else math.inf
            stops.append((t_s, until))
    for arm in armed:
        for start, end in stops:
            a, b = max(start, arm.start_s), min(end, arm.end_s)
            if b <= a:
                continue
            touches = a == arm.start_s or b == arm.end_s
            if touches and b - a <= handover_s:
                continue
            spans.append(Span(STOPPED_ARMED, a, b, "every ESC commanded to stop while armed"))
    return spans
