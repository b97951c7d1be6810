"""SocketCAN error frames read per linux/can/error.h: a table of frames as drivers send them
(the class in the ID, the details in the data bytes), and the controller state they fold into."""

from __future__ import annotations

import pytest

from bridge.can_errors import ControllerErrors, ControllerState, ErrorFrame, decode_error_frame

ACTIVE, WARNING, PASSIVE, BUS_OFF = (
    ControllerState.ERROR_ACTIVE,
    ControllerState.ERROR_WARNING,
    ControllerState.ERROR_PASSIVE,
    ControllerState.BUS_OFF,
)


@pytest.mark.parametrize(
    ("classes", "data", "state", "described"),
    [
        # `cansend can0 20000040#0000000000000000`: bus-off (the ID's flags are masked off).
        (0x20000040, "0000000000000000", BUS_OFF, "bus-off"),
        # can_change_state() to error-passive on the transmit side, with the counters.
        (0x204, "0020000000008800", PASSIVE,
         "controller: transmit error-passive (transmit errors 136, receive errors 0)"),
        (0x004, "0010000000000000", PASSIVE, "controller: receive error-passive"),
        (0x004, "0008000000000000", WARNING, "controller: transmit errors at warning level"),
        (0x004, "0004000000000000", WARNING, "controller: receive errors at warning level"),
        # Both sides named: the worst counts.
        (0x004, "0024000000000000", PASSIVE,
         "controller: receive errors at warning level, transmit error-passive"),
        (0x004, "0040000000000000", ACTIVE, "controller: back to error-active"),
        # can_restart(): restarted, so error-active again.
        (0x100, "0000000000000000", ACTIVE, "controller restarted"),
        # Events that announce no state.
        (0x004, "0001000000000000", None, "controller: receive overflow"),
        (0x004, "0000000000000000", None, "controller problem"),
        (0x020, "0000000000000000", None, "no acknowledgement"),
        (0x088, "0000041900000000", None, "protocol violation: stuffing at ACK slot; bus error"),
        (0x008, "0000810800000000", None,
         "protocol violation: bit, while transmitting at CRC sequence"),
        (0x002, "0700000000000000", None, "lost arbitration at bit 7"),
        (0x002, "0000000000000000", None, "lost arbitration"),
        (0x010, "0000000070000000", None, "transceiver: CAN L shorted to ground"),
        (0x010, "0000000033000000", None, "transceiver: status 0x33"),
        (0x001, "", None, "transmit timeout"),
        (0x000, "", None, "no error class set"),
        # Bus-off wins over a controller byte in the same frame.
        (0x044, "0020000000000000", BUS_OFF, "controller: transmit error-passive; bus-off"),
    ],
)  # fmt: skip
def test_error_frames_as_drivers_send_them(
    classes: int, data: str, state: ControllerState | None, described: str
) -> None:
    frame = decode_error_frame(classes, bytes.fromhex(data))
    assert frame.state == state
    assert frame.describe() == described


def test_details_of_a_frame() -> None:
    assert decode_error_frame(0x104, bytes.fromhex("0001")) == ErrorFrame(
        0x104,
        ACTIVE,
        restarted=True,
        receive_overflow=True,
        problems=("controller: receive overflow", "controller restarted"),
    )
    assert decode_error_frame(0x200, bytes(6) + b"\x60\x80").tx_errors == 0x60


def test_state_names_are_iproute2s() -> None:
    assert [state.text for state in ControllerState] == [
        "ERROR-ACTIVE", "ERROR-WARNING", "ERROR-PASSIVE", "BUS-OFF"
    ]  # fmt: skip


def test_a_bus_off_and_its_restart_fold_into_counts() -> None:
    errors = ControllerErrors()
    for classes, data in [
        (0x004, "0008"),  # warning
        (0x004, "0020"),  # passive
        (0x020, ""),  # no ACK: no state
        (0x040, ""),  # bus-off
        (0x100, ""),  # restarted
        (0x004, "0001"),  # receive overflow: no state
        (0x088, "000004"),  # bus error
    ]:
        errors.note(decode_error_frame(classes, bytes.fromhex(data)))
    assert errors.state == ACTIVE
    assert errors.entered == [1, 1, 1, 1]
    assert (errors.frames, errors.restarts, errors.receive_overflows) == (7, 1, 1)
    assert (errors.no_ack, errors.bus_errors) == (1, 1)
    assert errors.last is not None and errors.last.describe() == (
        "protocol violation: stuffing; bus error"
    )


def test_a_frame_received_ends_a_bus_off_only() -> None:
    errors = ControllerErrors()
    errors.note(decode_error_frame(0x004, b"\x00\x20"))
    errors.note_frame_received()
    assert errors.state == PASSIVE  # a passive controller still receives
    errors.note(decode_error_frame(0x040, b""))
    errors.note_frame_received()
    assert errors.state == ACTIVE
    assert errors.entered == [1, 0, 1, 1]
    errors.note(decode_error_frame(0x040, b""))
    errors.note(decode_error_frame(0x040, b""))  # still bus-off: entered once more, not twice
    assert errors.entered[BUS_OFF] == 2
