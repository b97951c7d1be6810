"""MAVLink 2 signing on the link: signed input accepted, unsigned, badly signed and replayed input
refused and counted, outputs signing too (real pymavlink peers on 127.0.0.1).
"""

from __future__ import annotations

import linkpeer
from conftest import free_port
from linkpeer import (
    ACCEPTED,
    KEY,
    USER_1,
    MakeLink,
    MakePeer,
    command,
    receive_acks,
    servo,
    wait_messages,
    wait_until,
)
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

make_peer = linkpeer.make_peer
make_link = linkpeer.make_link
udp_address = linkpeer.udp_address


def test_signing_accepts_signed_and_rejects_unsigned_bad_and_replayed(
    make_link: MakeLink, make_peer: MakePeer, udp_address: str
) -> None:
    link = make_link(f"udpin:{udp_address}", signing_key=KEY.hex(), heartbeat_hz=10.0)
    signed = make_peer(f"udpout:{udp_address}", key=KEY)
    unsigned = make_peer(f"udpout:{udp_address}")
    wrong_key = make_peer(f"udpout:{udp_address}", key=bytes(32))
    stats = link.stats

    signed.send(servo(signed.mav, 0, [1500]))
    wait_messages(link, 1, "the signed message")
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

    # Taken: 1500, the replay's first copy (1800) and 2000; the forgery refused.
    wait_messages(link, 3, "the genuine stream taken again after the forgery")
    assert stats.messages == 3 and stats.rejected_unsigned == 4
    assert stats.bad_data == 0  # refusals are counted as such, not as bad data
    bridge_heartbeat = signed.wait_for("HEARTBEAT")  # the signed peer refuses unsigned ones
    assert bridge_heartbeat.get_signed()


def test_with_a_signing_key_outputs_sign_and_refuse_unsigned_commands(
    make_link: MakeLink, make_peer: MakePeer, udp_address: str
) -> None:
    gcs_address = f"127.0.0.1:{free_port()}"
    signed = make_peer(f"udpin:{gcs_address}", system=255, component=190, key=KEY)
    link = make_link(
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
