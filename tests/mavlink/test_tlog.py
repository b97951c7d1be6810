"""The link's recording: every frame received and sent, once, in .tlog form."""

from __future__ import annotations

import itertools
import threading
import time
from pathlib import Path
from typing import Any

import linkpeer
from conftest import free_port
from linkpeer import (
    ACCEPTED,
    USER_1,
    MakeLink,
    MakePeer,
    command,
    heartbeat,
    receive_until,
    servo,
    wait_messages,
)
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from bridge.config import MavlinkConfig
from bridge.mavlink.link import MavlinkLink

make_peer = linkpeer.make_peer
make_link = linkpeer.make_link
udp_address = linkpeer.udp_address


def test_tlog_records_everything_received_and_sent_once(
    make_link: MakeLink, make_peer: MakePeer, udp_address: str, tmp_path: Path
) -> None:
    gcs_address = f"127.0.0.1:{free_port()}"
    gcs = make_peer(f"udpin:{gcs_address}", system=255, component=190)
    path = tmp_path / "bridge.tlog"
    with path.open("wb") as tlog:
        link = MavlinkLink(
            MavlinkConfig(
                url=f"udpin:{udp_address}", outputs=(f"udpout:{gcs_address}",), stream_rate_hz=0
            ),
            tlog=tlog,
        )
        with link:
            link.start()
            link.add_command_handler(lambda msg: ACCEPTED)
            autopilot = make_peer(f"udpout:{udp_address}")
            autopilot.send(heartbeat(autopilot.mav, armed=True))
            autopilot.send(servo(autopilot.mav, 0, [1234]))
            wait_messages(link, 2, "the autopilot's HEARTBEAT and output")
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
            wait_messages(link, 202, "every output")
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
