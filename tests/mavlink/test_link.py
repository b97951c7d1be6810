"""The link against real pymavlink endpoints on 127.0.0.1 (one set of free ports per test): the
autopilot's HEARTBEATs, foreign senders, junk, STATUSTEXT, extra outputs, closing. What the
autopilot's outputs mean is the control loop's (tests/mavlink/test_actuators.py, the output
loop's tests): the link counts them and leaves them to the loop that owns the link.
"""

from __future__ import annotations

import random
import threading
import time

import linkpeer
import pytest
from conftest import free_port
from linkpeer import TIMEOUT_S, MakeLink, MakePeer, heartbeat, servo, wait_messages, wait_until
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from bridge.config import MavlinkConfig
from bridge.mavlink.link import MavlinkLink

make_peer = linkpeer.make_peer
make_link = linkpeer.make_link
udp_address = linkpeer.udp_address


def test_heartbeats_are_taken_only_from_the_autopilot(
    make_link: MakeLink, make_peer: MakePeer, udp_address: str
) -> None:
    link = make_link(f"udpin:{udp_address}")
    autopilot = make_peer(f"udpout:{udp_address}")
    other_vehicle = make_peer(f"udpout:{udp_address}", system=2)

    autopilot.send(heartbeat(autopilot.mav, armed=True))
    wait_until(lambda: link.stats.last_heartbeat_ns > 0, "the autopilot's HEARTBEAT")
    first = link.stats.last_heartbeat_ns
    other_vehicle.send(heartbeat(other_vehicle.mav, armed=True))
    wait_until(lambda: link.stats.ignored_foreign == 1, "the foreign HEARTBEAT")
    assert link.stats.last_heartbeat_ns == first
    autopilot.send(heartbeat(autopilot.mav, armed=False))

    wait_until(lambda: link.stats.last_heartbeat_ns > first, "the autopilot's next HEARTBEAT")
    assert link.stats.last_heartbeat_ns <= time.monotonic_ns()
    assert link.stats.messages == 3


def test_foreign_system_or_component_is_ignored_and_counted(
    make_link: MakeLink, make_peer: MakePeer, udp_address: str
) -> None:
    link = make_link(f"udpin:{udp_address}")
    other_system = make_peer(f"udpout:{udp_address}", system=2)
    other_component = make_peer(f"udpout:{udp_address}", component=2)
    autopilot = make_peer(f"udpout:{udp_address}")

    other_system.send(servo(other_system.mav, 0, [1900]))
    other_component.send(servo(other_component.mav, 0, [1800]))
    other_component.send(other_component.mav.statustext_encode(6, b"not an output"))
    wait_messages(link, 3, "the foreign messages")
    autopilot.send(servo(autopilot.mav, 0, [1100]))

    wait_messages(link, 4, "the autopilot's message")
    assert link.stats.ignored_foreign == 2  # the STATUSTEXT is no output: not counted


def test_junk_is_counted_and_the_link_keeps_working(
    make_link: MakeLink, make_peer: MakePeer, udp_address: str
) -> None:
    link = make_link(f"udpin:{udp_address}")
    autopilot = make_peer(f"udpout:{udp_address}")

    autopilot.write(b"\x00junk without a MAVLink start byte")
    bad_crc = bytearray(servo(autopilot.mav, 0, [1100]).pack(autopilot.mav))
    bad_crc[-1] ^= 0xFF
    autopilot.write(bytes(bad_crc))
    wait_until(lambda: link.stats.bad_data == 2, "two stretches of bad data")
    autopilot.send(servo(autopilot.mav, 0, [1200]))
    wait_messages(link, 1, "the good message after the junk")

    rng = random.Random(7)
    for _ in range(50):
        autopilot.write(bytes(rng.randrange(256) for _ in range(rng.randint(1, 300))))
    # Random bytes can leave the parser inside a claimed frame; valid frames resynchronise it.
    deadline = time.monotonic() + TIMEOUT_S
    read = link.stats.messages
    while link.stats.messages == read:
        assert time.monotonic() < deadline, "the link stopped reading after junk"
        autopilot.send(servo(autopilot.mav, 0, [1300]))
        time.sleep(0.02)
    assert link.stats.bad_data > 2
    assert link.stats.reconnects == 0


def test_statustext_is_cut_to_50_ascii_characters(make_link: MakeLink, make_peer: MakePeer) -> None:
    url = f"127.0.0.1:{free_port()}"
    autopilot = make_peer(f"udpin:{url}")
    link = make_link(f"udpout:{url}", stream_rate_hz=0.0)

    link.statustext(mavlink2.MAV_SEVERITY_WARNING, "ESC 3 " + "x" * 40 + "µ" + "y" * 20)

    text = autopilot.wait_for("STATUSTEXT")
    assert text.severity == mavlink2.MAV_SEVERITY_WARNING
    assert text.text == "ESC 3 " + "x" * 40 + "?" + "yyy"
    with pytest.raises(ValueError, match="severity 8"):
        link.statustext(8, "no such severity")


def test_close_is_idempotent_and_stops_the_threads(udp_address: str) -> None:
    MavlinkLink(MavlinkConfig()).close()  # never started: nothing to clean up
    url = f"udpin:{udp_address}"
    with MavlinkLink(MavlinkConfig(url=url)) as link:
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
    link = make_link(f"udpin:{udp_address}", outputs=(f"udpout:{gcs_address}",), heartbeat_hz=10.0)
    autopilot = make_peer(f"udpout:{udp_address}")
    autopilot.send(heartbeat(autopilot.mav, armed=False))
    wait_messages(link, 1, "the autopilot's HEARTBEAT")
    beat = autopilot.wait_for("HEARTBEAT")  # the autopilot link works as before
    assert (beat.get_srcSystem(), beat.get_srcComponent()) == (1, 191)
    to_gcs = gcs.receive(0.3)  # from the start: a HEARTBEAT and the first stream request
    beat = next(m for _, m in to_gcs if m.get_type() == "HEARTBEAT")
    assert (beat.get_srcSystem(), beat.get_srcComponent()) == (1, 191)
    assert "COMMAND_LONG" not in [m.get_type() for _, m in to_gcs]  # requests: autopilot only

    link.statustext(mavlink2.MAV_SEVERITY_INFO, "to everyone")
    assert gcs.wait_for("STATUSTEXT").text == "to everyone"
    assert autopilot.wait_for("STATUSTEXT").text == "to everyone"

    # Motor outputs and arming on an output are not the autopilot's, even when they claim to be
    # 1/1: counted as the output's, never taken as the autopilot's.
    gcs.send(servo(gcs.mav, 0, [1800]))
    fake = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    gcs.write(servo(fake, 0, [1900]).pack(fake))
    heartbeat_ns = link.stats.last_heartbeat_ns
    gcs.write(heartbeat(fake, armed=True).pack(fake))
    wait_until(lambda: link.output_stats[0].messages == 3, "the output's three messages")
    autopilot.send(servo(autopilot.mav, 0, [1100]))
    wait_messages(link, 2, "the autopilot's output")
    assert link.stats.messages == 2  # the autopilot's HEARTBEAT and output only
    assert link.stats.last_heartbeat_ns == heartbeat_ns
    assert link.output_stats[0].url == f"udpout:{gcs_address}"
    assert link.output_stats[0].sent > 0
