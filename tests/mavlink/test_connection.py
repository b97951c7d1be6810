"""The link's connections: TCP reconnects with backoff, a serial device (a pty), an autopilot that
cannot be reached, an output that fails and comes back.
"""

from __future__ import annotations

import os
import select
import socket
import subprocess
import sys
import time

import linkpeer
import pytest
from conftest import free_port
from linkpeer import TIMEOUT_S, MakeLink, MakePeer, Peer, servo, wait_messages, wait_until
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from bridge.config import MavlinkConfig
from bridge.errors import LinkError
from bridge.mavlink.link import MavlinkLink

make_peer = linkpeer.make_peer
make_link = linkpeer.make_link
udp_address = linkpeer.udp_address


def stream_until_received(autopilot: Peer, link: MavlinkLink, pwm: int) -> None:
    """Send SERVO_OUTPUT_RAW every 20 ms (serving the link meanwhile) until the link reads one."""
    deadline = time.monotonic() + TIMEOUT_S
    before = link.stats.messages
    while link.stats.messages == before:
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
        link = make_link(f"tcp:{address}")
    else:
        link = make_link(f"tcpin:{address}")
        autopilot = make_peer(f"tcp:{address}", retries=0)
    stream_until_received(autopilot, link, 1100)

    autopilot.close()
    if server == "autopilot":
        time.sleep(0.3)  # the bridge keeps trying meanwhile
        autopilot = make_peer(f"tcpin:{address}")
    else:
        wait_until(lambda: link.stats.reconnects == 1, "the bridge listening again")
        autopilot = make_peer(f"tcp:{address}", retries=0)
    stream_until_received(autopilot, link, 1200)

    assert link.stats.reconnects == 1


def test_serial_device_url_reads_a_pty(make_link: MakeLink) -> None:
    pytest.importorskip("serial", reason="serial links need pyserial")
    controller, device = os.openpty()
    try:
        link = make_link(f"serial:{os.ttyname(device)}:921600", stream_rate_hz=0.0)
        autopilot = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
        os.write(controller, servo(autopilot, 0, [1100]).pack(autopilot))

        wait_messages(link, 1, "the SERVO_OUTPUT_RAW written to the pty")
        ready, _, _ = select.select([controller], [], [], TIMEOUT_S)  # never block for ever
        assert ready, "nothing written to the serial device"
        beat = autopilot.parse_buffer(os.read(controller, 4096))
        assert beat is not None and beat[0].get_type() == "HEARTBEAT"
        link.close()  # before the pty goes away, which the link would take for a lost device
    finally:
        os.close(controller)
        os.close(device)


def test_unreachable_autopilot_is_a_link_error() -> None:
    url = f"tcp:127.0.0.1:{free_port(socket.SOCK_STREAM)}"  # nothing listens there
    with pytest.raises(LinkError, match=f"cannot open MAVLink '{url}'"):
        MavlinkLink(MavlinkConfig(url=url)).start()


def test_a_failing_output_never_stops_the_autopilot_link_and_reconnects(
    make_link: MakeLink, make_peer: MakePeer, udp_address: str
) -> None:
    dead = f"127.0.0.1:{free_port(socket.SOCK_STREAM)}"  # nothing listens there, yet
    gcs_address = f"127.0.0.1:{free_port()}"
    gcs = make_peer(f"udpin:{gcs_address}")
    link = make_link(
        f"udpin:{udp_address}",
        outputs=(f"tcp:{dead}", f"udpout:{gcs_address}"),
        heartbeat_hz=10.0,
    )
    autopilot = make_peer(f"udpout:{udp_address}")

    autopilot.send(servo(autopilot.mav, 0, [1100]))
    wait_messages(link, 1, "the autopilot's output")
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


IMPORT_SCRIPT = """
import sys
{first}
from bridge.mavlink.connection import mavutil
conn = mavutil.mavlink_connection("udpin:127.0.0.1:0")
conn.close()
print("numpy" in sys.modules, hasattr(sys.modules["pymavlink.mavextra"], "Quaternion"))
"""


@pytest.mark.parametrize(
    ("first", "expected"),
    [("", "False False"), ("import numpy", "True True")],
    ids=["alone", "numpy-already-loaded"],
)
def test_mavutil_is_loaded_without_numpy_unless_a_process_has_it(first: str, expected: str) -> None:
    """numpy (installed here by the plot extra) is left out of a process that has not loaded it:
    most of mavutil's load time, for quaternions the bridge never uses. A process that loaded
    numpy first keeps mavutil's quaternions."""
    pytest.importorskip("numpy", reason="pip install -e '.[plot]' installs numpy")
    done = subprocess.run(
        [sys.executable, "-c", IMPORT_SCRIPT.format(first=first)],
        capture_output=True,
        text=True,
        timeout=30,
        check=True,
    )
    assert done.stdout.split() == expected.split()
