"""Commands to the bridge (COMMAND_LONG) through a real link: who is addressed, the handlers' order,
which answer wins, and where the COMMAND_ACK goes.
"""

from __future__ import annotations

from typing import Any

import linkpeer
from conftest import free_port
from linkpeer import (
    ACCEPTED,
    USER_1,
    USER_2,
    USER_3,
    MakeLink,
    MakePeer,
    command,
    receive_acks,
    receive_until,
)
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

make_peer = linkpeer.make_peer
make_link = linkpeer.make_link
udp_address = linkpeer.udp_address


def test_commands_addressed_to_the_bridge_reach_the_handler_and_are_acked(
    make_link: MakeLink, make_peer: MakePeer, udp_address: str
) -> None:
    link = make_link(f"udpin:{udp_address}", stream_rate_hz=0.0)
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
    link = make_link(f"udpin:{udp_address}", stream_rate_hz=0.0)
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
    link = make_link(
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
