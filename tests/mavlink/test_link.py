"""MAVLink input against real pymavlink endpoints on 127.0.0.1 (one set of free ports per test).

A :class:`Peer` plays the autopilot, or an intruder: a pymavlink connection whose codec is
pinned to a MAVLink 1 or MAVLink 2 dialect module, so what goes on the wire does not depend
on the ``MAVLINK20`` environment variable that ``mavutil`` reads.
"""

from __future__ import annotations

import itertools
import logging
import math
import os
import random
import select
import socket
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from pymavlink import mavutil
from pymavlink.dialects.v10 import ardupilotmega as mavlink1
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from bridge.config import MavlinkConfig
from bridge.errors import ConfigError, LinkError
from bridge.mavlink.endpoints import ACCEPTED_URL_FORMS, DEFAULT_BAUD, Endpoint, parse_url
from bridge.mavlink.link import INPUT_VECTOR_LEN, MavlinkLink
from bridge.mixer import INPUT_NAMES

KEY = bytes(range(32))
ARMED = mavlink2.MAV_MODE_FLAG_SAFETY_ARMED
TIMEOUT_S = 3.0


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    with socket.socket(socket.AF_INET, kind) as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


def wait_until(predicate: Callable[[], bool], what: str, timeout_s: float = TIMEOUT_S) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.005)


def assert_vector(values: list[float], expected: dict[str, float]) -> None:
    """The named inputs (``ch1``.., ``roll``..) hold these values; every other one is NaN."""
    assert len(values) == INPUT_VECTOR_LEN == 36
    for name, value in zip(INPUT_NAMES, values, strict=True):
        if name in expected:
            assert value == pytest.approx(expected[name]), name
        else:
            assert math.isnan(value), f"{name} = {value}, expected NaN"


class Sink:
    """Records what the link delivers, in order; optionally raises on the first deliveries."""

    def __init__(self, fail_first: int = 0) -> None:
        self.events: list[tuple[str, Any, int]] = []
        self._fail = fail_first
        self._cond = threading.Condition()

    def on_actuators(self, values: list[float], time_ns: int) -> None:
        with self._cond:
            if self._fail:
                self._fail -= 1
                raise RuntimeError("sink fault")
            self.events.append(("values", values, time_ns))
            self._cond.notify_all()

    def on_armed(self, armed: bool, time_ns: int) -> None:
        with self._cond:
            self.events.append(("armed", armed, time_ns))
            self._cond.notify_all()

    def vectors(self) -> list[list[float]]:
        with self._cond:
            return [e[1] for e in self.events if e[0] == "values"]

    def armed(self) -> list[bool]:
        with self._cond:
            return [e[1] for e in self.events if e[0] == "armed"]

    def wait_vectors(self, n: int) -> list[list[float]]:
        with self._cond:
            ok = self._cond.wait_for(
                lambda: sum(e[0] == "values" for e in self.events) >= n, TIMEOUT_S
            )
        assert ok, f"expected {n} input vectors, got {len(self.vectors())}"
        return self.vectors()

    def wait_armed(self, n: int) -> list[bool]:
        with self._cond:
            ok = self._cond.wait_for(
                lambda: sum(e[0] == "armed" for e in self.events) >= n, TIMEOUT_S
            )
        assert ok, f"expected {n} arming reports, got {self.armed()}"
        return self.armed()


class Peer:
    """A pymavlink endpoint on loopback with a MAVLink 1 or 2 codec, optionally signing."""

    def __init__(
        self,
        url: str,
        system: int = 1,
        component: int = 1,
        codec: Any = mavlink2,
        key: bytes | None = None,
        **opts: Any,
    ) -> None:
        self.conn: Any = mavutil.mavlink_connection(
            url, source_system=system, source_component=component, **opts
        )
        self.mav: Any = codec.MAVLink(self.conn, srcSystem=system, srcComponent=component)
        self.mav.robust_parsing = True
        self.conn.mav = self.mav  # so that setup_signing configures this codec
        if key is not None:
            self.conn.setup_signing(
                key, sign_outgoing=True, allow_unsigned_callback=lambda *_: False, link_id=0
            )

    def send(self, msg: Any) -> None:
        self.mav.send(msg)

    def write(self, data: bytes) -> None:
        self.conn.write(data)

    def receive(self, duration_s: float) -> list[tuple[float, Any]]:
        """Everything decoded within ``duration_s``, with monotonic receive times."""
        got: list[tuple[float, Any]] = []
        deadline = time.monotonic() + duration_s
        while time.monotonic() < deadline:
            self.conn.select(0.01)
            data = self.conn.recv(4096)
            if data:
                now = time.monotonic()
                got.extend((now, m) for m in self.mav.parse_buffer(data) or [])
        return got

    def drain(self) -> list[tuple[float, Any]]:
        """Everything decoded that is waiting now, without waiting."""
        got: list[tuple[float, Any]] = []
        while data := self.conn.recv(4096):
            now = time.monotonic()
            got.extend((now, m) for m in self.mav.parse_buffer(data) or [])
        return got

    def wait_for(self, kind: str) -> Any:
        deadline = time.monotonic() + TIMEOUT_S
        while time.monotonic() < deadline:
            for _, msg in self.receive(0.02):
                if msg.get_type() == kind:
                    return msg
        raise AssertionError(f"no {kind} within {TIMEOUT_S} s")

    def close(self) -> None:
        self.conn.close()


def servo(mav: Any, port: int, pwm: list[int]) -> Any:
    """SERVO_OUTPUT_RAW of ``pwm`` (padded with 0 = no output) for this codec's channel count."""
    n = 8 if isinstance(mav, mavlink1.MAVLink) else 16
    return mav.servo_output_raw_encode(0, port, *(pwm + [0] * n)[:n])


def heartbeat(mav: Any, armed: bool) -> Any:
    base_mode = mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (ARMED if armed else 0)
    return mav.heartbeat_encode(
        mavlink2.MAV_TYPE_QUADROTOR,
        mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA,
        base_mode,
        0,
        mavlink2.MAV_STATE_ACTIVE,
    )


MakeLink = Callable[..., tuple[MavlinkLink, Sink]]
MakePeer = Callable[..., Peer]


@pytest.fixture
def make_peer() -> Iterator[MakePeer]:
    peers: list[Peer] = []

    def make(url: str, **kwargs: Any) -> Peer:
        peer = Peer(url, **kwargs)
        peers.append(peer)
        return peer

    yield make
    for peer in peers:
        peer.close()


@pytest.fixture
def make_link(make_peer: MakePeer) -> Iterator[MakeLink]:
    """Start a link on a URL with config overrides; closed at the end of the test, before the
    peers (requested here for that order), so that closing does not look like a lost link."""
    links: list[MavlinkLink] = []

    def make(url: str, sink: Sink | None = None, **config: Any) -> tuple[MavlinkLink, Sink]:
        sink = sink or Sink()
        link = MavlinkLink(MavlinkConfig(url=url, **config), sink)
        links.append(link)
        link.start()
        return link, sink

    yield make
    for link in links:
        link.close()


@pytest.fixture
def udp_address() -> str:
    """The bridge listens here (udpin); peers send to it (udpout)."""
    return f"127.0.0.1:{free_port()}"


# -- motor outputs ----------------------------------------------------------------------------


def test_servo_output_raw_ports_fill_channels_and_zero_is_absent(
    make_link: MakeLink, make_peer: MakePeer, udp_address: str
) -> None:
    _, sink = make_link(f"udpin:{udp_address}")
    autopilot = make_peer(f"udpout:{udp_address}")
    port0 = {f"ch{i}": 1000.0 + i for i in range(1, 17) if i != 2}  # ch2 = 0: no output
    port1 = {"ch17": 1700.0, "ch32": 1800.0}

    autopilot.send(servo(autopilot.mav, 0, [1001, 0, *range(1003, 1017)]))
    assert_vector(sink.wait_vectors(1)[0], port0)
    autopilot.send(servo(autopilot.mav, 1, [1700] + [0] * 14 + [1800]))
    assert_vector(sink.wait_vectors(2)[1], port0 | port1)
    # Port 1 arrived since the last port 0, so it is still carried...
    autopilot.send(servo(autopilot.mav, 0, [1500]))
    assert_vector(sink.wait_vectors(3)[2], {"ch1": 1500.0} | port1)
    # ...but once it misses a round of port 0 it is absent, not frozen at its last values.
    autopilot.send(servo(autopilot.mav, 0, [1600]))
    assert_vector(sink.wait_vectors(4)[3], {"ch1": 1600.0})


def test_servo_output_raw_over_mavlink1_carries_eight_channels(
    make_link: MakeLink, make_peer: MakePeer, udp_address: str
) -> None:
    link, sink = make_link(f"udpin:{udp_address}")
    autopilot = make_peer(f"udpout:{udp_address}", codec=mavlink1)
    frame = servo(autopilot.mav, 0, list(range(1101, 1109))).pack(autopilot.mav)
    assert frame[0] == mavlink1.PROTOCOL_MARKER_V1  # really a MAVLink 1 frame

    autopilot.write(frame)
    autopilot.send(heartbeat(autopilot.mav, armed=True))

    assert_vector(sink.wait_vectors(1)[0], {f"ch{i}": 1100.0 + i for i in range(1, 9)})
    assert sink.wait_armed(1) == [True]
    assert link.stats.bad_data == 0


def test_actuator_output_status_uses_the_active_mask(
    make_link: MakeLink, make_peer: MakePeer, udp_address: str
) -> None:
    _, sink = make_link(f"udpin:{udp_address}", source="actuator_output_status")
    autopilot = make_peer(f"udpout:{udp_address}")
    actuator = [0.25 * i for i in range(32)]
    actuator[5] = math.inf  # active but not a number: absent, never full scale
    active = 1 << 0 | 1 << 2 | 1 << 5 | 1 << 31

    autopilot.send(autopilot.mav.actuator_output_status_encode(0, active, actuator))

    assert_vector(sink.wait_vectors(1)[0], {"ch1": 0.0, "ch3": 0.5, "ch32": 7.75})


def test_hil_actuator_controls_report_arming_before_the_controls(
    make_link: MakeLink, make_peer: MakePeer, udp_address: str
) -> None:
    _, sink = make_link(f"udpin:{udp_address}", source="hil_actuator_controls")
    autopilot = make_peer(f"udpout:{udp_address}")
    controls = [0.5, -0.25, 0.125, 1.0] + [0.0] * 12
    hil = mavlink2.MAV_MODE_FLAG_HIL_ENABLED

    autopilot.send(autopilot.mav.hil_actuator_controls_encode(0, controls, hil | ARMED, 0))
    autopilot.send(autopilot.mav.hil_actuator_controls_encode(0, controls, hil, 0))

    sink.wait_vectors(2)
    assert [(kind, value) for kind, value, _ in sink.events if kind == "armed"] == [
        ("armed", True),
        ("armed", False),
    ]
    assert [kind for kind, _, _ in sink.events] == ["armed", "values", "armed", "values"]
    expected = {f"ch{i + 1}": value for i, value in enumerate(controls)}
    assert_vector(sink.vectors()[0], expected)


def test_actuator_control_target_group_0_fills_the_axes(
    make_link: MakeLink, make_peer: MakePeer, udp_address: str
) -> None:
    link, sink = make_link(
        f"udpin:{udp_address}", source="actuator_control_target", component_id=191
    )
    autopilot = make_peer(f"udpout:{udp_address}")
    mav = autopilot.mav
    controls = [0.5, -0.25, 0.125, 0.75, 1.0, 1.0, 1.0, 1.0]
    axes = {"roll": 0.5, "pitch": -0.25, "yaw": 0.125, "thrust": 0.75}

    autopilot.send(mav.actuator_control_target_encode(0, 1, controls))  # group 1: not ours
    autopilot.send(mav.set_actuator_control_target_encode(0, 0, 1, 1, controls))  # to 1/1
    autopilot.send(mav.actuator_control_target_encode(0, 0, controls))
    autopilot.send(mav.set_actuator_control_target_encode(0, 0, 1, 191, controls))  # to us
    autopilot.send(mav.set_actuator_control_target_encode(0, 0, 0, 0, controls))  # broadcast

    vectors = sink.wait_vectors(3)
    wait_until(lambda: link.stats.messages == 5, "five messages")
    assert len(sink.vectors()) == 3
    assert link.stats.outputs == 3
    for vector in vectors:
        assert_vector(vector, axes)


def test_sink_fault_drops_one_message_and_reading_goes_on(
    make_link: MakeLink, make_peer: MakePeer, udp_address: str
) -> None:
    link, sink = make_link(f"udpin:{udp_address}", sink=Sink(fail_first=1))
    autopilot = make_peer(f"udpout:{udp_address}")

    autopilot.send(servo(autopilot.mav, 0, [1100]))
    autopilot.send(servo(autopilot.mav, 0, [1200]))

    assert_vector(sink.wait_vectors(1)[0], {"ch1": 1200.0})
    assert link.stats.handler_errors == 1


# -- arming and senders -----------------------------------------------------------------------


def test_heartbeat_arming_transitions_only_from_the_autopilot(
    make_link: MakeLink, make_peer: MakePeer, udp_address: str
) -> None:
    link, sink = make_link(f"udpin:{udp_address}")
    autopilot = make_peer(f"udpout:{udp_address}")
    other_vehicle = make_peer(f"udpout:{udp_address}", system=2)

    autopilot.send(heartbeat(autopilot.mav, armed=True))
    assert sink.wait_armed(1) == [True]
    autopilot.send(heartbeat(autopilot.mav, armed=False))
    assert sink.wait_armed(2) == [True, False]
    other_vehicle.send(heartbeat(other_vehicle.mav, armed=True))
    wait_until(lambda: link.stats.ignored_foreign == 1, "the foreign HEARTBEAT")
    autopilot.send(heartbeat(autopilot.mav, armed=False))

    assert sink.wait_armed(3) == [True, False, False]
    assert 0 < link.stats.last_heartbeat_ns <= time.monotonic_ns()
    assert link.stats.last_heartbeat_ns == sink.events[-1][2]


def test_foreign_system_or_component_is_ignored_and_counted(
    make_link: MakeLink, make_peer: MakePeer, udp_address: str
) -> None:
    link, sink = make_link(f"udpin:{udp_address}")
    other_system = make_peer(f"udpout:{udp_address}", system=2)
    other_component = make_peer(f"udpout:{udp_address}", component=2)
    autopilot = make_peer(f"udpout:{udp_address}")

    other_system.send(servo(other_system.mav, 0, [1900]))
    other_component.send(servo(other_component.mav, 0, [1800]))
    other_component.send(other_component.mav.statustext_encode(6, b"not an output"))
    wait_until(lambda: link.stats.messages == 3, "the foreign messages")
    autopilot.send(servo(autopilot.mav, 0, [1100]))

    assert_vector(sink.wait_vectors(1)[0], {"ch1": 1100.0})
    wait_until(lambda: link.stats.messages == 4, "the autopilot's message")
    assert len(sink.vectors()) == 1
    assert link.stats.ignored_foreign == 2  # the STATUSTEXT is no output: not counted
    assert link.stats.outputs == 1


def test_signing_accepts_signed_and_rejects_unsigned_bad_and_replayed(
    make_link: MakeLink, make_peer: MakePeer, udp_address: str
) -> None:
    link, sink = make_link(f"udpin:{udp_address}", signing_key=KEY.hex(), heartbeat_hz=10.0)
    signed = make_peer(f"udpout:{udp_address}", key=KEY)
    unsigned = make_peer(f"udpout:{udp_address}")
    wrong_key = make_peer(f"udpout:{udp_address}", key=bytes(32))
    stats = link.stats

    signed.send(servo(signed.mav, 0, [1500]))
    sink.wait_vectors(1)
    unsigned.send(servo(unsigned.mav, 0, [1600]))
    wait_until(lambda: stats.rejected_unsigned == 1, "the unsigned message refused")
    wrong_key.send(servo(wrong_key.mav, 0, [1700]))
    wait_until(lambda: stats.rejected_unsigned == 2, "the badly signed message refused")

    replayed = servo(signed.mav, 0, [1800]).pack(signed.mav)
    signed.write(replayed)
    signed.write(replayed)
    wait_until(lambda: stats.rejected_unsigned == 3, "the replay refused")

    # A forged packet claiming the latest possible timestamp must not make the genuine
    # stream look like a replay (pymavlink alone would record the timestamp first).
    forged = bytearray(servo(signed.mav, 0, [1900]).pack(signed.mav))
    forged[-12:-6] = b"\xff" * 6
    signed.write(bytes(forged))
    wait_until(lambda: stats.rejected_unsigned == 4, "the forged message refused")
    signed.send(servo(signed.mav, 0, [2000]))

    sink.wait_vectors(3)
    assert [v[0] for v in sink.vectors()] == [1500.0, 1800.0, 2000.0]
    assert stats.bad_data == 0  # refusals are counted as such, not as bad data
    bridge_heartbeat = signed.wait_for("HEARTBEAT")  # the signed peer refuses unsigned ones
    assert bridge_heartbeat.get_signed()


def test_junk_is_counted_and_the_link_keeps_working(
    make_link: MakeLink, make_peer: MakePeer, udp_address: str
) -> None:
    link, sink = make_link(f"udpin:{udp_address}")
    autopilot = make_peer(f"udpout:{udp_address}")

    autopilot.write(b"\x00junk without a MAVLink start byte")
    bad_crc = bytearray(servo(autopilot.mav, 0, [1100]).pack(autopilot.mav))
    bad_crc[-1] ^= 0xFF
    autopilot.write(bytes(bad_crc))
    wait_until(lambda: link.stats.bad_data == 2, "two stretches of bad data")
    autopilot.send(servo(autopilot.mav, 0, [1200]))
    assert_vector(sink.wait_vectors(1)[0], {"ch1": 1200.0})

    rng = random.Random(7)
    for _ in range(50):
        autopilot.write(bytes(rng.randrange(256) for _ in range(rng.randint(1, 300))))
    # Random bytes can leave the parser inside a claimed frame; valid frames resynchronise it.
    deadline = time.monotonic() + TIMEOUT_S
    while not any(v[0] == 1300.0 for v in sink.vectors()):
        assert time.monotonic() < deadline, "the link stopped delivering after junk"
        autopilot.send(servo(autopilot.mav, 0, [1300]))
        time.sleep(0.02)
    assert link.stats.bad_data > 2
    assert link.stats.reconnects == 0


# -- what the bridge sends ----------------------------------------------------------------------


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


def stream(peer: Peer, seconds: float, rate_hz: float) -> list[tuple[float, Any]]:
    """Stream SERVO_OUTPUT_RAW and a HEARTBEAT a second at about ``rate_hz`` for ``seconds``;
    what the peer received meanwhile."""
    received: list[tuple[float, Any]] = []
    start = next_beat = time.monotonic()
    sent = 0
    while (now := time.monotonic()) < start + seconds:
        if now >= next_beat:
            peer.send(heartbeat(peer.mav, armed=False))
            next_beat += 1.0
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
    link, sink = make_link(
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
    flowing = stream(autopilot, 2.6, rate_hz=60)
    sent_hz = len(sink.vectors()) / (time.monotonic() - start)
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
    make_link(f"udpout:{url}", stream_rate_hz=200.0, autopilot_heartbeat_hz=0.0)

    unanswered = interval_requests(stream(autopilot, 2.5, rate_hz=40))
    assert len(unanswered) >= 2, "a slow stream, no answer: asked again every second"
    assert {rate for _, _, rate in unanswered} == {200.0}

    with caplog.at_level(logging.INFO, logger="bridge"):
        ack(autopilot, mavlink2.MAV_RESULT_ACCEPTED)
        answered = interval_requests(stream(autopilot, 3.0, rate_hz=40))
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
    make_link(f"udpout:{url}", stream_rate_hz=50.0, autopilot_heartbeat_hz=20.0)

    requests = interval_requests(stream(autopilot, 2.7, rate_hz=60))
    heartbeat_requests = [r for r in requests if r[1] == mavlink2.MAVLINK_MSG_ID_HEARTBEAT]
    assert heartbeat_requests, f"no HEARTBEAT request in {requests}"
    assert {rate for _, _, rate in heartbeat_requests} == {20.0}
    # Refusals meant for a ground station's request (forwarded by the autopilot) change nothing.
    ack(autopilot, mavlink2.MAV_RESULT_DENIED, target=(255, 190))
    later = interval_requests(stream(autopilot, 2.2, rate_hz=60))
    assert later and {rate for _, _, rate in later} == {20.0}


def test_a_stream_too_slow_for_the_input_timeout_is_reported(
    make_peer: MakePeer, caplog: pytest.LogCaptureFixture
) -> None:
    url = f"127.0.0.1:{free_port()}"
    link = MavlinkLink(
        MavlinkConfig(url=f"udpin:{url}", stream_rate_hz=0.0, autopilot_heartbeat_hz=0.0),
        Sink(),
        needed_rate_hz=20.0,
    )
    link.start()
    try:
        autopilot = make_peer(f"udpout:{url}")
        with caplog.at_level(logging.INFO, logger="bridge"):
            stream(autopilot, 2.5, rate_hz=10)
    finally:
        link.close()
    assert "arrives at 10 Hz, too slow for input_timeout_ms (it needs 20 Hz or more)" in (
        caplog.text
    )
    assert "not asked for a rate" in caplog.text


def test_statustext_is_cut_to_50_ascii_characters(make_link: MakeLink, make_peer: MakePeer) -> None:
    url = f"127.0.0.1:{free_port()}"
    autopilot = make_peer(f"udpin:{url}")
    link, _ = make_link(f"udpout:{url}", stream_rate_hz=0.0)

    link.statustext(mavlink2.MAV_SEVERITY_WARNING, "ESC 3 " + "x" * 40 + "µ" + "y" * 20)

    text = autopilot.wait_for("STATUSTEXT")
    assert text.severity == mavlink2.MAV_SEVERITY_WARNING
    assert text.text == "ESC 3 " + "x" * 40 + "?" + "yyy"
    with pytest.raises(ValueError, match="severity 8"):
        link.statustext(8, "no such severity")


# -- transports and lifecycle -------------------------------------------------------------------


def stream_until_received(autopilot: Peer, sink: Sink, pwm: int) -> None:
    """Send SERVO_OUTPUT_RAW every 20 ms (serving the link meanwhile) until the sink has it."""
    deadline = time.monotonic() + TIMEOUT_S
    while not any(v[0] == pwm for v in sink.vectors()):
        assert time.monotonic() < deadline, f"ch1 = {pwm} never arrived"
        autopilot.receive(0.02)  # a tcpin peer accepts the bridge's connection here
        autopilot.send(servo(autopilot.mav, 0, [pwm]))


@pytest.mark.parametrize("server", ["autopilot", "bridge"])
def test_tcp_link_reconnects_when_the_autopilot_side_drops(
    make_link: MakeLink, make_peer: MakePeer, server: str
) -> None:
    address = f"127.0.0.1:{free_port(socket.SOCK_STREAM)}"
    if server == "autopilot":  # like ArduPilot SITL: the autopilot listens
        autopilot = make_peer(f"tcpin:{address}")
        link, sink = make_link(f"tcp:{address}")
    else:
        link, sink = make_link(f"tcpin:{address}")
        autopilot = make_peer(f"tcp:{address}", retries=0)
    stream_until_received(autopilot, sink, 1100)

    autopilot.close()
    if server == "autopilot":
        time.sleep(0.3)  # the bridge keeps trying meanwhile
        autopilot = make_peer(f"tcpin:{address}")
    else:
        wait_until(lambda: link.stats.reconnects == 1, "the bridge listening again")
        autopilot = make_peer(f"tcp:{address}", retries=0)
    stream_until_received(autopilot, sink, 1200)

    assert link.stats.reconnects == 1


def test_serial_device_url_reads_a_pty(make_link: MakeLink) -> None:
    pytest.importorskip("serial", reason="serial links need pyserial")
    controller, device = os.openpty()
    try:
        link, sink = make_link(f"serial:{os.ttyname(device)}:921600", stream_rate_hz=0.0)
        autopilot = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
        os.write(controller, servo(autopilot, 0, [1100]).pack(autopilot))

        assert_vector(sink.wait_vectors(1)[0], {"ch1": 1100.0})
        ready, _, _ = select.select([controller], [], [], TIMEOUT_S)  # never block for ever
        assert ready, "nothing written to the serial device"
        beat = autopilot.parse_buffer(os.read(controller, 4096))
        assert beat is not None and beat[0].get_type() == "HEARTBEAT"
        link.close()  # before the pty goes away, which the link would take for a lost device
    finally:
        os.close(controller)
        os.close(device)


@pytest.mark.parametrize(
    ("url", "expected"),
    [
        ("udpin:0.0.0.0:14550", Endpoint("udpin:0.0.0.0:14550", "udpin", "0.0.0.0:14550")),
        ("udpout:localhost:14550", Endpoint("udpout:localhost:14550", "udpout", "localhost:14550")),
        ("tcp:127.0.0.1:5760", Endpoint("tcp:127.0.0.1:5760", "tcp", "127.0.0.1:5760")),
        ("tcpin:0.0.0.0:5760", Endpoint("tcpin:0.0.0.0:5760", "tcpin", "0.0.0.0:5760")),
        (
            "serial:/dev/ttyAMA0:921600",
            Endpoint("serial:/dev/ttyAMA0:921600", "serial", "/dev/ttyAMA0", 921600),
        ),
        ("serial:/dev/ttyACM0", Endpoint("serial:/dev/ttyACM0", "serial", "/dev/ttyACM0")),
        ("/dev/ttyUSB0", Endpoint("/dev/ttyUSB0", "serial", "/dev/ttyUSB0", DEFAULT_BAUD)),
        ("/dev/ttyUSB0:57600", Endpoint("/dev/ttyUSB0:57600", "serial", "/dev/ttyUSB0", 57600)),
        (  # by-path names contain colons; only a trailing :digits is a baud rate
            "serial:/dev/serial/by-path/platform-usb-0:1.3:1.0-port0:57600",
            Endpoint(
                "serial:/dev/serial/by-path/platform-usb-0:1.3:1.0-port0:57600",
                "serial",
                "/dev/serial/by-path/platform-usb-0:1.3:1.0-port0",
                57600,
            ),
        ),
    ],
)
def test_parse_url_accepts_the_documented_forms(url: str, expected: Endpoint) -> None:
    assert parse_url(url) == expected


@pytest.mark.parametrize(
    "url",
    [
        "",
        "udpin:127.0.0.1",
        "udpin:127.0.0.1:abc",
        "udpin:127.0.0.1:70000",
        "udp:127.0.0.1:14550",
        "tcp::5760",
        "serial:ttyAMA0",
        "serial:/dev/ttyAMA0:0",
        "flight.tlog",
    ],
)
def test_malformed_url_is_a_config_error_naming_it(url: str) -> None:
    with pytest.raises(ConfigError) as raised:
        MavlinkLink(MavlinkConfig(url=url), Sink()).start()
    assert repr(url) in str(raised.value)
    assert ACCEPTED_URL_FORMS in str(raised.value)


def test_unreachable_autopilot_is_a_link_error() -> None:
    url = f"tcp:127.0.0.1:{free_port(socket.SOCK_STREAM)}"  # nothing listens there
    with pytest.raises(LinkError, match=f"cannot open MAVLink '{url}'"):
        MavlinkLink(MavlinkConfig(url=url), Sink()).start()


def test_close_is_idempotent_and_stops_the_threads(udp_address: str) -> None:
    MavlinkLink(MavlinkConfig(), Sink()).close()  # never started: nothing to clean up
    url = f"udpin:{udp_address}"
    with MavlinkLink(MavlinkConfig(url=url), Sink()) as link:
        link.start()
        with pytest.raises(RuntimeError, match="started once"):
            link.start()
        assert sum(url in t.name for t in threading.enumerate()) == 2
    assert not any(url in t.name for t in threading.enumerate())
    link.close()
    link.send(link.mav.heartbeat_encode(0, 0, 0, 0, 0))  # dropped and counted, no error
    assert link.stats.send_failures == 1


# -- extra outputs, commands and recording ------------------------------------------------------

USER_1 = mavlink2.MAV_CMD_USER_1
USER_2 = mavlink2.MAV_CMD_USER_2
USER_3 = mavlink2.MAV_CMD_USER_3
ACCEPTED = mavlink2.MAV_RESULT_ACCEPTED


def command(peer: Peer, cmd: int, target: tuple[int, int], param1: float = 0) -> None:
    peer.send(peer.mav.command_long_encode(*target, cmd, 0, param1, 0, 0, 0, 0, 0, 0))


def receive_until(peer: Peer, predicate: Callable[[Any], bool]) -> list[Any]:
    """Everything ``peer`` receives up to and including the first message matching."""
    got: list[Any] = []
    deadline = time.monotonic() + TIMEOUT_S
    while time.monotonic() < deadline:
        for _, msg in peer.receive(0.02):
            got.append(msg)
            if predicate(msg):
                return got
    raise AssertionError(f"nothing matching within {TIMEOUT_S} s; got {len(got)} messages")


def receive_acks(peer: Peer, n: int) -> list[Any]:
    """The first ``n`` COMMAND_ACKs ``peer`` receives, and any that follow within 0.2 s."""
    acks: list[Any] = []
    deadline = time.monotonic() + TIMEOUT_S
    while len(acks) < n:
        assert time.monotonic() < deadline, f"{len(acks)} of {n} COMMAND_ACKs"
        acks += [m for _, m in peer.receive(0.02) if m.get_type() == "COMMAND_ACK"]
    return acks + [m for _, m in peer.receive(0.2) if m.get_type() == "COMMAND_ACK"]


def test_outputs_get_everything_sent_but_can_never_move_a_motor(
    make_link: MakeLink, make_peer: MakePeer, udp_address: str
) -> None:
    gcs_address = f"127.0.0.1:{free_port()}"
    gcs = make_peer(f"udpin:{gcs_address}", system=255, component=190)
    link, sink = make_link(
        f"udpin:{udp_address}", outputs=(f"udpout:{gcs_address}",), heartbeat_hz=10.0
    )
    autopilot = make_peer(f"udpout:{udp_address}")
    autopilot.send(heartbeat(autopilot.mav, armed=False))
    assert sink.wait_armed(1) == [False]
    beat = autopilot.wait_for("HEARTBEAT")  # the autopilot link works as before
    assert (beat.get_srcSystem(), beat.get_srcComponent()) == (1, 191)
    to_gcs = gcs.receive(0.3)  # from the start: a HEARTBEAT and the first stream request
    beat = next(m for _, m in to_gcs if m.get_type() == "HEARTBEAT")
    assert (beat.get_srcSystem(), beat.get_srcComponent()) == (1, 191)
    assert "COMMAND_LONG" not in [m.get_type() for _, m in to_gcs]  # requests: autopilot only

    link.statustext(mavlink2.MAV_SEVERITY_INFO, "to everyone")
    assert gcs.wait_for("STATUSTEXT").text == "to everyone"
    assert autopilot.wait_for("STATUSTEXT").text == "to everyone"

    # Motor outputs and arming on an output are ignored, even when they claim to be 1/1.
    gcs.send(servo(gcs.mav, 0, [1800]))
    fake = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    gcs.write(servo(fake, 0, [1900]).pack(fake))
    gcs.write(heartbeat(fake, armed=True).pack(fake))
    wait_until(lambda: link.output_stats[0].messages == 3, "the output's three messages")
    autopilot.send(servo(autopilot.mav, 0, [1100]))
    assert_vector(sink.wait_vectors(1)[0], {"ch1": 1100.0})
    assert len(sink.vectors()) == 1
    assert sink.armed() == [False]
    assert link.stats.messages == 2  # the autopilot's HEARTBEAT and output only
    assert link.output_stats[0].url == f"udpout:{gcs_address}"
    assert link.output_stats[0].sent > 0


def test_a_failing_output_never_stops_the_autopilot_link_and_reconnects(
    make_link: MakeLink, make_peer: MakePeer, udp_address: str
) -> None:
    dead = f"127.0.0.1:{free_port(socket.SOCK_STREAM)}"  # nothing listens there, yet
    gcs_address = f"127.0.0.1:{free_port()}"
    gcs = make_peer(f"udpin:{gcs_address}")
    link, sink = make_link(
        f"udpin:{udp_address}",
        outputs=(f"tcp:{dead}", f"udpout:{gcs_address}"),
        heartbeat_hz=10.0,
    )
    autopilot = make_peer(f"udpout:{udp_address}")

    autopilot.send(servo(autopilot.mav, 0, [1100]))
    assert_vector(sink.wait_vectors(1)[0], {"ch1": 1100.0})
    autopilot.wait_for("HEARTBEAT")
    gcs.wait_for("HEARTBEAT")  # the other output is unaffected
    wait_until(lambda: link.output_stats[0].send_failures >= 2, "frames counted as not sent")
    assert link.stats.send_failures == 0
    assert link.output_stats[1].send_failures == 0

    listener = make_peer(f"tcpin:{dead}")  # the GCS comes up: the output connects
    deadline = time.monotonic() + 2 * TIMEOUT_S  # the backoff may have reached 1.6 s
    while not any(m.get_type() == "HEARTBEAT" for _, m in listener.receive(0.05)):
        assert time.monotonic() < deadline, "the output never connected"
    assert link.output_stats[0].reconnects == 1
    assert link.stats.reconnects == 0


@pytest.mark.parametrize(
    ("outputs", "problem"),
    [
        (("udp:127.0.0.1:14550",), "'udp:127.0.0.1:14550' is not a connection string"),
        (("udpout:127.0.0.1:14550", "flight.tlog"), "'flight.tlog' is not a connection string"),
        (("tcpin:0.0.0.0:99999",), "port 99999 is not 1..65535"),
        (("udpout:127.0.0.1:14550", "udpout:127.0.0.1:14550"), "the same connection as"),
    ],
)
def test_bad_outputs_are_config_errors_before_anything_opens(
    outputs: tuple[str, ...], problem: str
) -> None:
    address = ("127.0.0.1", free_port(socket.SOCK_STREAM))
    link = MavlinkLink(
        MavlinkConfig(url=f"tcpin:{address[0]}:{address[1]}", outputs=outputs), Sink()
    )
    with pytest.raises(ConfigError) as raised:
        link.start()
    message = str(raised.value)
    assert message.startswith("[mavlink] outputs ")
    assert problem in message
    if "same connection" not in problem:
        assert ACCEPTED_URL_FORMS in message
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(address)  # the autopilot's listener was never opened
    assert not any("mavlink" in t.name and address[0] in t.name for t in threading.enumerate())


def test_an_output_repeating_the_autopilot_url_is_refused(udp_address: str) -> None:
    url = f"udpin:{udp_address}"
    with pytest.raises(ConfigError, match=r"same connection as \[mavlink\] url"):
        MavlinkLink(MavlinkConfig(url=url, outputs=(url,)), Sink()).start()


def test_commands_addressed_to_the_bridge_reach_the_handler_and_are_acked(
    make_link: MakeLink, make_peer: MakePeer, udp_address: str
) -> None:
    link, _ = make_link(f"udpin:{udp_address}", stream_rate_hz=0.0)
    gcs = make_peer(f"udpout:{udp_address}", system=255, component=190)
    ours, to_all, to_vehicle = (1, 191), (0, 0), (1, 0)

    command(gcs, USER_1, ours)  # no handler yet
    (first,) = receive_acks(gcs, 1)
    assert (first.command, first.result) == (USER_1, mavlink2.MAV_RESULT_UNSUPPORTED)

    calls: list[tuple[int, int, int, float]] = []

    def handler(msg: Any) -> int | None:
        calls.append((msg.command, msg.target_system, msg.target_component, msg.param1))
        if msg.command == USER_3:
            raise RuntimeError("handler fault")
        return ACCEPTED if msg.command == USER_1 else None

    link.add_command_handler(handler)
    command(gcs, USER_1, ours)
    command(gcs, USER_1, to_vehicle)
    command(gcs, USER_1, to_all)
    command(gcs, USER_2, ours)  # nobody claims it, and it named us: UNSUPPORTED
    command(gcs, USER_2, to_vehicle)  # nobody claims it, a broadcast: no answer
    command(gcs, USER_1, (1, 1))  # the autopilot's
    command(gcs, USER_1, (2, 191))  # another vehicle's
    command(gcs, USER_3, ours)  # the handler raises: FAILED
    command(gcs, USER_1, ours, param1=99)  # the last one
    acks = receive_acks(gcs, 6)

    assert [(a.command, a.result) for a in acks] == [
        (USER_1, ACCEPTED),
        (USER_1, ACCEPTED),
        (USER_1, ACCEPTED),
        (USER_2, mavlink2.MAV_RESULT_UNSUPPORTED),
        (USER_3, mavlink2.MAV_RESULT_FAILED),
        (USER_1, ACCEPTED),
    ]
    for ack in acks:
        assert (ack.target_system, ack.target_component) == (255, 190)
        assert (ack.get_srcSystem(), ack.get_srcComponent()) == ours
    assert calls == [
        (USER_1, 1, 191, 0.0),
        (USER_1, 1, 0, 0.0),
        (USER_1, 0, 0, 0.0),
        (USER_2, 1, 191, 0.0),
        (USER_2, 1, 0, 0.0),
        (USER_3, 1, 191, 0.0),
        (USER_1, 1, 191, 99.0),
    ]
    assert link.stats.commands == 8  # the first one, unhandled, too
    assert link.stats.handler_errors == 1


def test_several_handlers_are_asked_in_order_and_the_first_answer_wins(
    make_link: MakeLink, make_peer: MakePeer, udp_address: str
) -> None:
    link, _ = make_link(f"udpin:{udp_address}", stream_rate_hz=0.0)
    gcs = make_peer(f"udpout:{udp_address}", system=255, component=190)
    asked: list[tuple[str, int]] = []

    def first(msg: Any) -> int | None:
        asked.append(("first", msg.command))
        if msg.command == USER_3:
            raise RuntimeError("handler fault")
        return ACCEPTED if msg.command == USER_1 else None

    def second(msg: Any) -> int | None:
        asked.append(("second", msg.command))
        return mavlink2.MAV_RESULT_DENIED if msg.command in (USER_1, USER_2) else None

    link.add_command_handler(first)
    link.add_command_handler(second)
    link.add_command_handler(first)  # already there: still asked once
    for cmd in (USER_1, USER_2, USER_3):
        command(gcs, cmd, (1, 191))
    acks = receive_acks(gcs, 3)
    link.remove_command_handler(first)
    command(gcs, USER_1, (1, 191))
    acks += receive_acks(gcs, 1)
    link.remove_command_handler(second)
    link.remove_command_handler(second)  # not there: nothing happens
    command(gcs, USER_1, (1, 191))
    acks += receive_acks(gcs, 1)

    assert [(a.command, a.result) for a in acks] == [
        (USER_1, ACCEPTED),  # the first handler's answer; the second is not asked
        (USER_2, mavlink2.MAV_RESULT_DENIED),  # the first passed it on
        (USER_3, mavlink2.MAV_RESULT_FAILED),  # the first raised and nobody else answered
        (USER_1, mavlink2.MAV_RESULT_DENIED),  # the first was removed
        (USER_1, mavlink2.MAV_RESULT_UNSUPPORTED),  # nobody left
    ]
    assert asked == [
        ("first", USER_1),
        ("first", USER_2),
        ("second", USER_2),
        ("first", USER_3),
        ("second", USER_3),
        ("second", USER_1),
    ]
    assert link.stats.handler_errors == 1


def test_a_command_from_an_output_is_answered_there_only(
    make_link: MakeLink, make_peer: MakePeer
) -> None:
    autopilot_address = f"127.0.0.1:{free_port()}"
    gcs_address = f"127.0.0.1:{free_port()}"
    autopilot = make_peer(f"udpin:{autopilot_address}")
    gcs = make_peer(f"udpin:{gcs_address}", system=255, component=190)
    link, _ = make_link(
        f"udpout:{autopilot_address}", outputs=(f"udpout:{gcs_address}",), stream_rate_hz=0.0
    )
    link.add_command_handler(lambda msg: ACCEPTED)
    gcs.wait_for("HEARTBEAT")  # now the GCS knows where to answer

    command(gcs, USER_1, (1, 191))
    ack = receive_until(gcs, lambda m: m.get_type() == "COMMAND_ACK")[-1]
    assert (ack.result, ack.target_system, ack.target_component) == (ACCEPTED, 255, 190)
    link.statustext(mavlink2.MAV_SEVERITY_INFO, "after the ack")
    before = receive_until(autopilot, lambda m: m.get_type() == "STATUSTEXT")
    assert not [m for m in before if m.get_type() == "COMMAND_ACK"]


def test_tlog_records_everything_received_and_sent_once(
    make_link: MakeLink, make_peer: MakePeer, udp_address: str, tmp_path: Path
) -> None:
    gcs_address = f"127.0.0.1:{free_port()}"
    gcs = make_peer(f"udpin:{gcs_address}", system=255, component=190)
    path = tmp_path / "bridge.tlog"
    with path.open("wb") as tlog:
        sink = Sink()
        link = MavlinkLink(
            MavlinkConfig(
                url=f"udpin:{udp_address}", outputs=(f"udpout:{gcs_address}",), stream_rate_hz=0
            ),
            sink,
            tlog=tlog,
        )
        with link:
            link.start()
            link.add_command_handler(lambda msg: ACCEPTED)
            autopilot = make_peer(f"udpout:{udp_address}")
            autopilot.send(heartbeat(autopilot.mav, armed=True))
            autopilot.send(servo(autopilot.mav, 0, [1234]))
            sink.wait_vectors(1)
            gcs.wait_for("HEARTBEAT")
            command(gcs, USER_1, (1, 191))
            receive_until(gcs, lambda m: m.get_type() == "COMMAND_ACK")
            start_s = time.time()

            def chatter(n: int) -> None:  # several senders at once: records stay whole
                for i in range(50):
                    link.statustext(mavlink2.MAV_SEVERITY_DEBUG, f"thread {n} line {i}")

            threads = [threading.Thread(target=chatter, args=(n,)) for n in range(4)]
            for thread in threads:
                thread.start()
            for pwm in range(1300, 1500):  # meanwhile the reader records what arrives
                autopilot.send(servo(autopilot.mav, 0, [pwm]))
            for thread in threads:
                thread.join()
            sink.wait_vectors(201)
            end_s = time.time()

    recording: Any = mavutil.mavlink_connection(str(path))
    got: list[Any] = []
    while (msg := recording.recv_msg()) is not None:
        got.append(msg)
    recording.close()
    kinds = [(m.get_type(), m.get_srcSystem(), m.get_srcComponent()) for m in got]
    assert ("BAD_DATA", 0, 0) not in kinds
    for expected in [
        ("HEARTBEAT", 1, 1),  # received from the autopilot
        ("SERVO_OUTPUT_RAW", 1, 1),
        ("COMMAND_LONG", 255, 190),  # received on the output
        ("COMMAND_ACK", 1, 191),  # sent
        ("HEARTBEAT", 1, 191),
    ]:
        assert expected in kinds
    recorded_pwm = [m.servo1_raw for m in got if m.get_type() == "SERVO_OUTPUT_RAW"]
    assert recorded_pwm == [1234, *range(1300, 1500)]
    texts = [m.text for m in got if m.get_type() == "STATUSTEXT"]
    assert sorted(texts) == sorted(f"thread {n} line {i}" for n in range(4) for i in range(50))
    sent_seq = [m.get_seq() for m in got if (m.get_srcSystem(), m.get_srcComponent()) == (1, 191)]
    assert len(sent_seq) > 200
    assert all((b - a) % 256 == 1 for a, b in itertools.pairwise(sent_seq))
    stamps = [m._timestamp for m in got]
    assert stamps == sorted(stamps)
    texts_at = [m._timestamp for m in got if m.get_type() == "STATUSTEXT"]
    assert start_s - 0.01 <= texts_at[0] and texts_at[-1] <= end_s + 0.01
    assert link.stats.tlog_errors == 0


def test_with_a_signing_key_outputs_sign_and_refuse_unsigned_commands(
    make_link: MakeLink, make_peer: MakePeer, udp_address: str
) -> None:
    gcs_address = f"127.0.0.1:{free_port()}"
    signed = make_peer(f"udpin:{gcs_address}", system=255, component=190, key=KEY)
    link, _ = make_link(
        f"udpin:{udp_address}",
        outputs=(f"udpout:{gcs_address}",),
        signing_key=KEY.hex(),
        heartbeat_hz=10.0,
    )
    link.add_command_handler(lambda msg: ACCEPTED)
    assert signed.wait_for("HEARTBEAT").get_signed()  # the signed peer refuses unsigned ones

    unsigned = mavlink2.MAVLink(None, srcSystem=255, srcComponent=190)
    frame = unsigned.command_long_encode(1, 191, USER_1, 0, 0, 0, 0, 0, 0, 0, 0).pack(unsigned)
    signed.write(frame)
    wait_until(lambda: link.output_stats[0].rejected_unsigned == 1, "the unsigned command refused")
    command(signed, USER_1, (1, 191))
    (ack,) = receive_acks(signed, 1)
    assert ack.get_signed() and ack.result == ACCEPTED
    assert link.stats.commands == 1
    assert link.stats.rejected_unsigned == 0  # counted where it arrived
