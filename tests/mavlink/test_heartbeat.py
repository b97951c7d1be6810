"""The link's heartbeat thread against a pymavlink autopilot on 127.0.0.1: the bridge's HEARTBEAT,
the stream requests (MAV_CMD_SET_MESSAGE_INTERVAL) and what is logged about the rates.
"""

from __future__ import annotations

import logging
import time
from typing import Any

import linkpeer
import pytest
from conftest import free_port
from linkpeer import MakeLink, MakePeer, Peer, heartbeat, servo
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from bridge.config import MavlinkConfig
from bridge.mavlink.link import MavlinkLink

make_peer = linkpeer.make_peer
make_link = linkpeer.make_link


def interval_requests(received: list[tuple[float, Any]]) -> list[tuple[float, int, float]]:
    """(time, message id, rate Hz) of each MAV_CMD_SET_MESSAGE_INTERVAL among ``received``."""
    return [
        (t, int(m.param1), 1e6 / m.param2)
        for t, m in received
        if m.get_type() == "COMMAND_LONG" and m.command == mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL
    ]


def ack(peer: Peer, result: int, target: tuple[int, int] = (1, 191)) -> None:
    """The autopilot's COMMAND_ACK to a SET_MESSAGE_INTERVAL (addressed to ``target``)."""
    peer.send(
        peer.mav.command_ack_encode(mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL, result, 0, 0, *target)
    )


def stream(
    peer: Peer, seconds: float, rate_hz: float, link: MavlinkLink
) -> list[tuple[float, Any]]:
    """Stream SERVO_OUTPUT_RAW and a HEARTBEAT a second at about ``rate_hz`` for ``seconds``;
    what the peer received meanwhile. Meanwhile, as the control loop that owns the link does,
    tell ``link`` every 0.1 s how many outputs it read (the loop counts what it decodes)."""
    received: list[tuple[float, Any]] = []
    start = next_beat = next_note = time.monotonic()
    sent = 0
    beats = link.stats.messages
    while (now := time.monotonic()) < start + seconds:
        if now >= next_beat:
            peer.send(heartbeat(peer.mav, armed=False))
            beats += 1
            next_beat += 1.0
        if now >= next_note:
            outputs_read = link.stats.messages - beats
            link.note_outputs(outputs_read, time.monotonic_ns())
            next_note += 0.1
        peer.send(servo(peer.mav, 0, [1100]))
        sent += 1
        received += peer.drain()
        time.sleep(max(0.0, start + sent / rate_hz - time.monotonic()))
    return received


def test_heartbeat_and_stream_requests_reach_the_autopilot_until_outputs_flow(
    make_link: MakeLink, make_peer: MakePeer
) -> None:
    url = f"127.0.0.1:{free_port()}"
    autopilot = make_peer(f"udpin:{url}")
    # Asked at 50 Hz, so that a test process on a busy machine can keep up with it.
    link = make_link(
        f"udpout:{url}", heartbeat_hz=5.0, stream_rate_hz=50.0, autopilot_heartbeat_hz=0.0
    )

    silent = autopilot.receive(1.3)
    beats = [m for _, m in silent if m.get_type() == "HEARTBEAT"]
    requests = [(t, m) for t, m in silent if m.get_type() == "COMMAND_LONG"]
    assert len(beats) >= 5
    for beat in beats:
        assert (beat.get_srcSystem(), beat.get_srcComponent()) == (1, 191)
        assert beat.type == mavlink2.MAV_TYPE_ONBOARD_CONTROLLER
        assert beat.autopilot == mavlink2.MAV_AUTOPILOT_INVALID
    assert len(requests) == 2  # at start, and again a second later
    assert 0.8 < requests[1][0] - requests[0][0] < 1.3
    for _, request in requests:
        assert request.command == mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL
        assert (request.target_system, request.target_component) == (1, 1)
        assert request.param1 == mavlink2.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW
        assert request.param2 == 20000.0  # µs: 50 Hz

    # A stream at the rate asked: no more requests, whether answered or not.
    start = time.monotonic()
    flowing = stream(autopilot, 2.6, rate_hz=60, link=link)
    sent_hz = link.stats.outputs / (time.monotonic() - start)
    assert sent_hz > 40, "the test could not stream fast enough to mean anything"
    assert not [r for r in interval_requests(flowing) if r[0] > start + 1.2]
    assert link.stats.output_rate_hz == pytest.approx(sent_hz, rel=0.25)

    # Once the stream stops, the rate falls to 0 and the requests resume.
    autopilot.wait_for("COMMAND_LONG")
    assert link.stats.output_rate_hz == 0.0


def test_a_slow_stream_is_asked_again_until_accepted_then_taken_as_the_limit(
    make_link: MakeLink, make_peer: MakePeer, caplog: pytest.LogCaptureFixture
) -> None:
    """PX4 streams 10 Hz until a request is ACCEPTED (and the first may be lost); once it
    ACCEPTED, what arrives is its best (PX4's SIH sends ~124 Hz when asked 200)."""
    url = f"127.0.0.1:{free_port()}"
    autopilot = make_peer(f"udpin:{url}")
    link = make_link(f"udpout:{url}", stream_rate_hz=200.0, autopilot_heartbeat_hz=0.0)

    unanswered = interval_requests(stream(autopilot, 2.5, rate_hz=40, link=link))
    assert len(unanswered) >= 2, "a slow stream, no answer: asked again every second"
    assert {rate for _, _, rate in unanswered} == {200.0}

    with caplog.at_level(logging.INFO, logger="bridge"):
        ack(autopilot, mavlink2.MAV_RESULT_ACCEPTED)
        answered = interval_requests(stream(autopilot, 3.0, rate_hz=40, link=link))
    assert len(answered) <= 1, f"asked on after ACCEPTED: {answered}"  # one already due
    assert "ACCEPTED SERVO_OUTPUT_RAW at 200 Hz" in caplog.text
    assert "taking that as its limit" in caplog.text


def test_a_denied_rate_steps_down_and_says_so(
    make_link: MakeLink, make_peer: MakePeer, caplog: pytest.LogCaptureFixture
) -> None:
    """ArduCopter DENIES 400 Hz on a 400 Hz loop and accepts 200 Hz."""
    url = f"127.0.0.1:{free_port()}"
    autopilot = make_peer(f"udpin:{url}")
    with caplog.at_level(logging.INFO, logger="bridge"):
        make_link(f"udpout:{url}", stream_rate_hz=400.0, autopilot_heartbeat_hz=0.0)
        first = autopilot.wait_for("COMMAND_LONG")
        assert first.param2 == 2500.0  # µs: 400 Hz
        ack(autopilot, mavlink2.MAV_RESULT_DENIED)
        then = autopilot.wait_for("COMMAND_LONG")
    assert then.param1 == mavlink2.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW
    assert then.param2 == 5000.0  # µs: 200 Hz
    assert "SERVO_OUTPUT_RAW at 400 Hz: MAV_RESULT_DENIED; asking for 200 Hz instead" in (
        caplog.text
    )


def test_the_heartbeat_is_asked_for_too_and_acks_to_others_are_not_ours(
    make_link: MakeLink, make_peer: MakePeer
) -> None:
    url = f"127.0.0.1:{free_port()}"
    autopilot = make_peer(f"udpin:{url}")
    link = make_link(f"udpout:{url}", stream_rate_hz=50.0, autopilot_heartbeat_hz=20.0)

    requests = interval_requests(stream(autopilot, 2.7, rate_hz=60, link=link))
    heartbeat_requests = [r for r in requests if r[1] == mavlink2.MAVLINK_MSG_ID_HEARTBEAT]
    assert heartbeat_requests, f"no HEARTBEAT request in {requests}"
    assert {rate for _, _, rate in heartbeat_requests} == {20.0}
    # Refusals meant for a ground station's request (forwarded by the autopilot) change nothing.
    ack(autopilot, mavlink2.MAV_RESULT_DENIED, target=(255, 190))
    later = interval_requests(stream(autopilot, 2.2, rate_hz=60, link=link))
    assert later and {rate for _, _, rate in later} == {20.0}


def test_a_stream_too_slow_for_the_input_timeout_is_reported(
    make_peer: MakePeer, caplog: pytest.LogCaptureFixture
) -> None:
    url = f"127.0.0.1:{free_port()}"
    link = MavlinkLink(
        MavlinkConfig(url=f"udpin:{url}", stream_rate_hz=0.0, autopilot_heartbeat_hz=0.0),
        needed_rate_hz=20.0,
    )
    link.start()
    try:
        autopilot = make_peer(f"udpout:{url}")
        with caplog.at_level(logging.INFO, logger="bridge"):
            stream(autopilot, 2.5, rate_hz=10, link=link)
    finally:
        link.close()
    assert "arrives at 10 Hz, too slow for input_timeout_ms (it needs 20 Hz or more)" in (
        caplog.text
    )
    assert "not asked for a rate" in caplog.text
    assert "will not arm on it; [mavlink] stream_rate_hz is 0: give it a rate to ask" in (
        caplog.text
    )


def test_outputs_counted_in_batches_give_their_stream_rate() -> None:
    """The control loop reports its count of outputs now and then: a 10 Hz stream (outputs at
    0.05, 0.15, ... s) reported three at once at 0.3 s, then one every 0.1 s. The rate is what
    arrived after the window's first report over the time since it: 10 Hz, not 12 (the three
    reported first arrived before the window began)."""
    link = MavlinkLink(
        MavlinkConfig(url=f"udpin:127.0.0.1:{free_port()}", stream_rate_hz=0.0),
        needed_rate_hz=0.0,
    )  # never started: only its count of outputs is used
    base_ns = time.monotonic_ns()
    total = 3
    link.note_outputs(total, base_ns + 300_000_000)
    for report in range(1, 11):
        total += 1
        link.note_outputs(total, base_ns + 300_000_000 + report * 100_000_000)
    assert link.stats.output_rate_hz == pytest.approx(10.0)
