"""The spans of a flight (bridge/plot/spans.py): armed from the autopilot's HEARTBEATs, failsafe
and motor test from the bridge's own state reports (every text the daemon sends), and every
ESC commanded to stop while armed."""

from __future__ import annotations

import pytest

from bridge.daemon.health import STATE_REPORTS
from bridge.daemon.severity import SEVERITY_CRITICAL
from bridge.plot.recording import Heartbeat, StatusText
from bridge.plot.spans import (
    ARMED,
    ARMING_TIMEOUT_S,
    FAILSAFE,
    MOTOR_TEST,
    STOPPED_ARMED,
    Span,
    armed_spans,
    bridge_spans,
    bridge_state,
    stopped_while_armed,
)


def beats(*pairs: tuple[float, bool]) -> list[Heartbeat]:
    return [Heartbeat(t, armed) for t, armed in pairs]


def text(t_s: float, severity: int, body: str) -> StatusText:
    return StatusText(t_s, severity, body, 1, 191)


def test_armed_from_the_first_armed_heartbeat_to_the_first_disarmed_one() -> None:
    got = armed_spans(beats((0, False), (1, True), (2, True), (3, False), (4, True)), end_s=5)
    assert got == [Span(ARMED, 1, 3, "armed"), Span(ARMED, 4, 5, "armed")]


def test_a_heartbeat_stream_that_stops_ends_the_span_after_the_arming_timeout() -> None:
    lost = ARMING_TIMEOUT_S
    got = armed_spans(beats((1, True), (2, True), (2 + lost + 1, True)), end_s=100)
    assert got == [
        Span(ARMED, 1, 2 + lost, "armed (HEARTBEAT lost)"),
        Span(ARMED, 2 + lost + 1, 3 + 2 * lost, "armed (HEARTBEAT lost)"),
    ]
    assert armed_spans([], end_s=10) == []


def test_every_state_the_bridge_reports_is_classified() -> None:
    kinds = {
        state.name: bridge_state(text(0, severity, body))
        for state, (severity, body) in STATE_REPORTS.items()
    }
    assert {s for s, kind in kinds.items() if kind == FAILSAFE} == {
        "STALE",
        "INVALID",
        "HEARTBEAT_LOST",
        "SLOW_STREAM",
    }
    assert kinds["MOTOR_TEST"] == MOTOR_TEST
    assert kinds["RUNNING"] == "armed" and kinds["DISARMED"] == "disarmed"
    assert all(kind is not None for kind in kinds.values())
    # Sent within a state (daemon.py, on a tick error), and other systems' texts: no state.
    fault = "ESC out: FAULT encoding commands, motors safe"
    assert bridge_state(text(0, SEVERITY_CRITICAL, fault)) is None
    assert bridge_state(text(0, SEVERITY_CRITICAL, "PreArm: Battery below minimum")) is None


def test_failsafe_and_motor_test_last_until_the_next_state() -> None:
    reports = [
        text(1, 6, "ESC out: armed, sending motor commands"),
        text(5, 2, "ESC out: FAILSAFE input stale, motors stopped"),
        text(5.5, 2, "ESC out: FAULT encoding commands, motors safe"),
        text(7, 6, "ESC out: armed, sending motor commands"),
        text(9, 4, "ESC out: MOTOR TEST, one motor may spin"),
        text(12, 2, "ESC out: FAILSAFE autopilot HEARTBEAT lost, motors stopped"),
    ]
    assert bridge_spans(reports, end_s=20) == [
        Span(FAILSAFE, 5, 7, "FAILSAFE input stale, motors stopped"),
        Span(MOTOR_TEST, 9, 12, "MOTOR TEST, one motor may spin"),
        Span(FAILSAFE, 12, 20, "FAILSAFE autopilot HEARTBEAT lost, motors stopped"),
    ]


def test_every_esc_stopped_while_armed_however_short_but_for_the_hand_over() -> None:
    armed = [Span(ARMED, 10.0, 20.0, "armed")]
    changes = [
        (0.0, True),
        (10.1, False),  # 0.1 s after arming: the hand-over, not shown
        (15.0, True),
        (15.05, False),  # 50 ms in mid-flight: shown
        (19.9, True),  # 0.1 s before disarming: the hand-over
    ]
    (short,) = stopped_while_armed(changes, armed)
    assert (short.kind, short.start_s) == (STOPPED_ARMED, 15.0)
    assert short.end_s == pytest.approx(15.05)
    # A bridge that never starts sending after arming: from the arming on.
    late = stopped_while_armed([(0.0, True), (12.0, False)], armed)
    assert [(s.start_s, s.end_s) for s in late] == [(10.0, 12.0)]
    # Stopped to the end of the recording, armed to the end.
    assert [(s.start_s, s.end_s) for s in stopped_while_armed([(14.0, True)], armed)] == [
        (14.0, 20.0)
    ]
    assert stopped_while_armed([(0.0, True)], []) == []
