"""The link against real pymavlink endpoints on 127.0.0.1 (one set of free ports per test): motor
outputs and arming to the sink, foreign senders, junk, STATUSTEXT, extra outputs, closing.
"""

from __future__ import annotations

import math
import random
import threading
import time

import linkpeer
import pytest
from linkpeer import (
    ARMED,
    TIMEOUT_S,
    MakeLink,
    MakePeer,
    Sink,
    assert_vector,
    free_port,
    heartbeat,
    servo,
    wait_until,
)
from pymavlink.dialects.v10 import ardupilotmega as mavlink1
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from bridge.config import MavlinkConfig
from bridge.mavlink.link import MavlinkLink

make_peer = linkpeer.make_peer
make_link = linkpeer.make_link
udp_address = linkpeer.udp_address


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
