"""The stream-rate negotiation (:class:`bridge.mavlink.streams.StreamRequest`) as the real
autopilots answer it: what is asked, when, and what is said."""

from __future__ import annotations

import logging

import pytest

from bridge.mavlink.streams import (
    MAV_RESULT_ACCEPTED,
    MAV_RESULT_DENIED,
    MAV_RESULT_IN_PROGRESS,
    MAV_RESULT_UNSUPPORTED,
    StreamRequest,
    rate_ladder,
    result_name,
)

AUTOPILOT = "autopilot 1/1"


def request(wanted_hz: float = 400.0) -> StreamRequest:
    return StreamRequest("SERVO_OUTPUT_RAW", AUTOPILOT, wanted_hz)


def test_the_ladder_starts_at_the_configured_rate_and_steps_down() -> None:
    assert rate_ladder(400) == (400, 200, 100, 50, 25, 10)
    assert rate_ladder(200) == (200, 100, 50, 25, 10)
    assert rate_ladder(30) == (30, 25, 10)
    assert rate_ladder(5) == (5,)
    assert result_name(2) == "MAV_RESULT_DENIED"
    assert result_name(42) == "MAV_RESULT_42"


def test_nothing_is_asked_at_rate_zero() -> None:
    stream = request(0)
    assert stream.due(0.0, autopilot_heard=True) is None
    assert stream.asked_hz == 0


def test_asks_every_check_until_the_stream_arrives_at_the_rate() -> None:
    stream = request(200)
    assert [stream.due(0.0, autopilot_heard=False) for _ in range(3)] == [200, 200, 200]
    assert stream.due(190.0, autopilot_heard=True) is None  # within 80 %: what was asked
    assert stream.due(170.0, autopilot_heard=True) is None


def test_a_slow_stream_is_asked_again_until_accepted(caplog: pytest.LogCaptureFixture) -> None:
    """PX4: 10 Hz until a request is ACCEPTED; then ~124 Hz for 200 asked, its limit."""
    stream = request(200)
    with caplog.at_level(logging.INFO):
        assert stream.due(10.0, autopilot_heard=True) == 200
        assert stream.due(10.0, autopilot_heard=True) == 200
        stream.on_ack(MAV_RESULT_ACCEPTED)
        assert stream.accepted
        assert stream.due(124.0, autopilot_heard=True) is None
        assert stream.due(124.0, autopilot_heard=True) is None
    assert "autopilot 1/1 ACCEPTED SERVO_OUTPUT_RAW at 200 Hz" in caplog.text
    limit = [r for r in caplog.records if "taking that as its limit" in r.getMessage()]
    assert len(limit) == 1 and limit[0].levelno == logging.WARNING  # said once


def test_a_refusal_steps_down_and_is_said(caplog: pytest.LogCaptureFixture) -> None:
    """ArduCopter: DENIED at 400 Hz (its loop rate), ACCEPTED at 200 Hz."""
    stream = request(400)
    with caplog.at_level(logging.INFO):
        assert stream.due(0.0, autopilot_heard=True) == 400
        stream.on_ack(MAV_RESULT_DENIED)
        assert stream.due(0.0, autopilot_heard=True) == 200
        stream.on_ack(MAV_RESULT_ACCEPTED)
    assert stream.due(200.0, autopilot_heard=True) is None
    assert stream.asked_hz == 200
    messages = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert messages == [
        "autopilot 1/1: SERVO_OUTPUT_RAW at 400 Hz: MAV_RESULT_DENIED; asking for 200 Hz instead"
    ]


def test_refused_at_every_rate_it_stops_asking_until_the_stream_restarts(
    caplog: pytest.LogCaptureFixture,
) -> None:
    stream = request(50)  # 50, 25, 10
    with caplog.at_level(logging.INFO):
        for rate in (50, 25, 10):
            assert stream.due(0.0, autopilot_heard=True) == rate
            stream.on_ack(MAV_RESULT_UNSUPPORTED)
        assert stream.due(0.0, autopilot_heard=True) is None
        assert stream.due(4.0, autopilot_heard=True) is None  # what it sends is taken
        assert stream.due(4.0, autopilot_heard=True) is None
    errors = [r for r in caplog.records if r.levelno == logging.ERROR]
    assert len(errors) == 1 and "the lowest rate tried" in errors[0].getMessage()
    # The stream stops (the autopilot restarted and forgot): the whole ladder again.
    assert stream.due(0.0, autopilot_heard=False) == 50


def test_no_answer_and_no_stream_from_a_present_autopilot_steps_down() -> None:
    stream = request(200)
    asked = [stream.due(0.0, autopilot_heard=True) for _ in range(4)]
    assert asked == [200, 200, 200, 100]
    # An absent autopilot (no HEARTBEAT) cannot answer: that is no reason to step down.
    absent = request(200)
    assert {absent.due(0.0, autopilot_heard=False) for _ in range(10)} == {200}


def test_a_silent_autopilot_with_a_slow_stream_is_reported_once(
    caplog: pytest.LogCaptureFixture,
) -> None:
    stream = request(200)
    with caplog.at_level(logging.INFO):
        asked = [stream.due(10.0, autopilot_heard=True) for _ in range(6)]
    assert asked == [200] * 6  # asking on: the request may have been lost
    silent = [r for r in caplog.records if "does not answer" in r.getMessage()]
    assert len(silent) == 1 and "it arrives at 10 Hz" in silent[0].getMessage()


def test_in_progress_keeps_the_rate() -> None:
    stream = request(200)
    assert stream.due(0.0, autopilot_heard=True) == 200
    stream.on_ack(MAV_RESULT_IN_PROGRESS)
    assert not stream.accepted
    assert stream.due(10.0, autopilot_heard=True) == 200


def test_a_rate_that_falls_after_it_was_accepted_and_met_is_asked_again(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """ArduCopter SITL killed and restarted within a second: its HEARTBEAT never stops for a
    whole check, the new boot forgot the interval and sends a few Hz. The old ACCEPTED must not
    make that rate its limit; one that never reached the rate keeps its limit (PX4's ~124 Hz)."""
    stream = request(20)
    assert stream.due(1.0, autopilot_heard=True) == 20
    stream.on_ack(MAV_RESULT_ACCEPTED)
    # The check where it arrived at 20 Hz was the other request's turn: observed, not due.
    stream.observe(20.0)
    with caplog.at_level(logging.INFO):
        # A second measured a little low (a busy machine) is neither forgotten nor a limit
        # worth asking about again.
        assert stream.due(15.0, autopilot_heard=True) is None
        assert stream.accepted
        assert stream.due(2.0, autopilot_heard=True) == 20  # restarted: asked again
        assert stream.accepted  # an unanswered second ask changes nothing
        stream.on_ack(MAV_RESULT_ACCEPTED)
        assert stream.due(19.0, autopilot_heard=True) is None
    assert "far below the 20 Hz it ACCEPTED: asking again" in caplog.text
    assert "taking that as its limit" not in caplog.text
    # Restarted before the rate was ever measured at 20 Hz: asked again once; an autopilot
    # that ACCEPTS again and still sends 1 Hz has that as its limit (no request every second).
    fresh = request(20)
    assert fresh.due(0.0, autopilot_heard=True) == 20
    fresh.on_ack(MAV_RESULT_ACCEPTED)
    assert fresh.due(1.0, autopilot_heard=True) == 20
    fresh.on_ack(MAV_RESULT_ACCEPTED)
    assert [fresh.due(1.0, autopilot_heard=True) for _ in range(3)] == [None, None, None]
    # Accepted but never met: its limit, not asked again.
    limited = request(200)
    assert limited.due(10.0, autopilot_heard=True) == 200
    limited.on_ack(MAV_RESULT_ACCEPTED)
    assert [limited.due(124.0, autopilot_heard=True) for _ in range(3)] == [None, None, None]
