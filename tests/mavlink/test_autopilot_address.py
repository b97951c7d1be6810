"""The autopilot's address on a datagram link: who may take it, when it moves, what is refused."""

from __future__ import annotations

import pytest

from bridge.mavlink.autopilot_address import AutopilotAddress, address_code, address_text

S = 1_000_000_000
AUTOPILOT = ("127.0.0.1", 14555)
OTHER = ("127.0.0.1", 40000)
RESTARTED = ("10.0.0.2", 14555)


def test_udpin_takes_the_first_sender_and_refuses_others_while_it_speaks() -> None:
    address = AutopilotAddress(None, move_after_ns=3 * S)
    assert address.address is None and address.may_take(0)
    assert address.take(AUTOPILOT, 1 * S) is False  # the first: no move
    assert (address.heard_ns, address.moves) == (1 * S, 0)
    assert address.address == AUTOPILOT
    address.heard_ns = 2 * S  # the caller: a datagram from the autopilot at 2 s
    assert not address.may_take(2 * S + 1)
    assert not address.may_take(5 * S)  # silent for exactly the window: still its place
    address.refuse(OTHER)
    address.refuse(RESTARTED)
    assert (address.refused, address.refused_from) == (2, RESTARTED)
    assert address.address == AUTOPILOT


def test_udpin_moves_once_the_old_address_has_been_silent_past_the_window() -> None:
    address = AutopilotAddress(None, move_after_ns=3 * S)
    address.take(AUTOPILOT, 1 * S)
    assert address.may_take(4 * S + 1)
    assert address.take(RESTARTED, 4 * S + 1) is True
    assert (address.address, address.heard_ns, address.moves) == (RESTARTED, 4 * S + 1, 1)
    assert not address.may_take(5 * S)  # the new one holds it as the old one did


def test_udpout_is_the_configured_peer_for_good() -> None:
    address = AutopilotAddress(AUTOPILOT, move_after_ns=3 * S)
    assert address.fixed and address.address == AUTOPILOT
    assert not address.may_take(0)
    assert not address.may_take(3600 * S)  # however long it is silent


def test_udpout_to_this_host_expects_answers_from_loopback() -> None:
    """Linux sends a datagram for 0.0.0.0 to this host, whose answer comes from 127.0.0.1."""
    address = AutopilotAddress(("0.0.0.0", 14550), move_after_ns=S)
    assert address.address == ("127.0.0.1", 14550)


def test_a_window_that_is_not_positive_is_refused() -> None:
    with pytest.raises(ValueError, match="move_after_ns=0: expected a positive duration"):
        AutopilotAddress(None, move_after_ns=0)


@pytest.mark.parametrize(
    ("address", "code"),
    [
        (("127.0.0.1", 14550), 0x7F000001 << 16 | 14550),
        (("0.0.0.1", 0), 1 << 16),
        (("255.255.255.255", 65535), (1 << 48) - 1),
    ],
)
def test_address_codes_fit_a_counter_slot_and_read_back(
    address: tuple[str, int], code: int
) -> None:
    assert address_code(address) == code
    assert code < 1 << 63  # an int64 slot
    assert address_text(code) == f"{address[0]}:{address[1]}"
