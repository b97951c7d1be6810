"""Tests for the VESC codec (bridge/escs/vesc/) against docs/protocols.md §6.

The known frames below were written by hand from the firmware's own encoding rules
(vedderb/bldc 7.01, ``comm/comm_can.c``): the ID is ``packet << 8 | controller_id``, each value
is the quantity times its scale as a big-endian two's-complement integer
(``buffer_append_int32``/``int16``), no CRC. Not one of them comes from the codec.
"""

from __future__ import annotations

import math
import struct

import can
import pytest
from hypothesis import given
from hypothesis import strategies as st

from bridge.errors import DlcError, NotExtendedIdError, ValueRangeError
from bridge.escs.vesc.codec import decode, encode, encode_command
from bridge.escs.vesc.records import (
    COMMAND_PACKETS,
    COMMANDS,
    STATUS_PACKETS,
    HwType,
    NotifyBoot,
    Packet,
    Ping,
    Pong,
    SetCurrent,
    SetCurrentBrake,
    SetCurrentRel,
    SetDuty,
    SetRpm,
    Status,
    Status2,
    Status3,
    Status4,
    Status5,
    Status6,
    VescCommand,
    VescFrame,
    VescMessage,
    can_id,
    parse_id,
)

I32_MIN, I32_MAX = -(2**31), 2**31 - 1
I16_MIN, I16_MAX = -(2**15), 2**15 - 1


def message(arbitration_id: int, data: str, **flags: bool) -> can.Message:
    """An extended data frame of hex ``data`` unless ``flags`` say otherwise."""
    return can.Message(
        arbitration_id=arbitration_id,
        data=bytes.fromhex(data),
        is_extended_id=flags.pop("is_extended_id", True),
        **flags,
    )


# ---------------------------------------------------------------------------------------------
# Known frames, one or more per packet the bridge knows.

KNOWN: list[tuple[VescFrame, int, str]] = [
    # The issue's and docs/protocols.md §6.9's example: 51 A to VESC 23.
    (VescFrame(23, SetCurrent(51.0)), 0x117, "00 00 c7 38"),
    (VescFrame(1, SetDuty(0.5)), 0x001, "00 00 c3 50"),
    (VescFrame(2, SetDuty(-0.25)), 0x002, "ff ff 9e 58"),
    (VescFrame(3, SetCurrent(-2.5)), 0x103, "ff ff f6 3c"),
    (VescFrame(5, SetCurrentBrake(10.0)), 0x205, "00 00 27 10"),
    (VescFrame(10, SetRpm(20000)), 0x30A, "00 00 4e 20"),
    (VescFrame(255, SetRpm(-7000)), 0x3FF, "ff ff e4 a8"),
    (VescFrame(4, SetCurrentRel(0.3)), 0xA04, "00 00 75 30"),
    (VescFrame(0, SetCurrentRel(-1.0)), 0xA00, "ff fe 79 60"),
    (VescFrame(23, Ping(254)), 0x1117, "fe"),
    (VescFrame(254, Pong(23, HwType.VESC)), 0x12FE, "17 00"),
    (VescFrame(9, Pong(23, HwType.VESC_BMS)), 0x1209, "17 01"),
    (VescFrame(23, NotifyBoot("60_MK6")), 0x3917, "36 30 5f 4d 4b 36"),
    (VescFrame(23, Status(35000, 12.3, 0.456)), 0x917, "00 00 88 b8 00 7b 01 c8"),
    # Regenerating: the motor current is negative.
    (VescFrame(23, Status(-1000, -4.5, -0.1)), 0x917, "ff ff fc 18 ff d3 ff 9c"),
    (VescFrame(23, Status2(1.2345, 0.01)), 0xE17, "00 00 30 39 00 00 00 64"),
    (VescFrame(23, Status3(45.6789, 0.0)), 0xF17, "00 06 f8 55 00 00 00 00"),
    (VescFrame(23, Status4(35.5, 48.2, 7.5, 180.0)), 0x1017, "01 63 01 e2 00 4b 23 28"),
    (VescFrame(23, Status5(123456, 25.2)), 0x1B17, "00 01 e2 40 00 fc 00 00"),
    (VescFrame(23, Status6(1.65, 0.0, 3.3, -0.5)), 0x3A17, "06 72 00 00 0c e4 fe 0c"),
]
KNOWN_IDS = [f"0x{arbitration_id:04X}-{data[:5]}" for _, arbitration_id, data in KNOWN]


def test_known_frames_cover_every_packet() -> None:
    assert {arbitration_id >> 8 for _, arbitration_id, _ in KNOWN} == set(Packet)


@pytest.mark.parametrize(("frame", "arbitration_id", "data"), KNOWN, ids=KNOWN_IDS)
def test_encode_known_frame(frame: VescFrame, arbitration_id: int, data: str) -> None:
    msg = encode(frame)
    assert (msg.arbitration_id, msg.data.hex(" ")) == (arbitration_id, data)
    assert msg.dlc == len(bytes.fromhex(data))
    assert msg.is_extended_id and not msg.is_remote_frame and not msg.is_error_frame


@pytest.mark.parametrize(("frame", "arbitration_id", "data"), KNOWN, ids=KNOWN_IDS)
def test_decode_known_frame(frame: VescFrame, arbitration_id: int, data: str) -> None:
    assert decode(message(arbitration_id, data)) == frame


def test_the_firmware_reads_a_pong_without_its_type_byte_as_a_vesc() -> None:
    assert decode(message(0x12FE, "17")) == VescFrame(254, Pong(23, HwType.VESC))


def test_status_5_reserved_bytes_are_ignored() -> None:
    assert decode(message(0x1B17, "00 01 e2 40 00 fc 12 34")) == VescFrame(
        23, Status5(123456, 25.2)
    )


def test_notify_boot_may_be_empty_or_full_and_odd_bytes_do_not_raise() -> None:
    assert decode(message(0x3901, "")) == VescFrame(1, NotifyBoot(""))
    assert decode(message(0x3901, "41 42 43 44 45 46 47 48")) == VescFrame(
        1, NotifyBoot("ABCDEFGH")
    )
    frame = decode(message(0x3901, "ff 41"))
    assert frame is not None and isinstance(frame.message, NotifyBoot)
    assert frame.message.hw_name.endswith("A")


def test_node_id_is_the_controller_id() -> None:
    assert VescFrame(42, SetDuty(0.0)).node_id == 42


# ---------------------------------------------------------------------------------------------
# IDs, packet numbers and what is not ours


def test_packet_numbers_are_the_firmwares() -> None:
    # CAN_PACKET_ID in datatypes.h (firmware 7.01).
    assert {p.name: p.value for p in Packet} == {
        "SET_DUTY": 0,
        "SET_CURRENT": 1,
        "SET_CURRENT_BRAKE": 2,
        "SET_RPM": 3,
        "STATUS": 9,
        "SET_CURRENT_REL": 10,
        "STATUS_2": 14,
        "STATUS_3": 15,
        "STATUS_4": 16,
        "PING": 17,
        "PONG": 18,
        "STATUS_5": 27,
        "NOTIFY_BOOT": 57,
        "STATUS_6": 58,
    }
    assert set(COMMAND_PACKETS.values()) == COMMANDS
    assert len(STATUS_PACKETS) == 6 and not STATUS_PACKETS & COMMANDS


def test_can_id_and_parse_id() -> None:
    assert can_id(23, Packet.SET_CURRENT) == 0x117
    assert can_id(255, Packet.STATUS_6) == 0x3AFF
    assert parse_id(0x3AFF) == (58, 255)
    assert parse_id(0x0500) == (5, 0)
    for bad in (-1, 256):
        with pytest.raises(ValueRangeError, match="controller_id"):
            can_id(bad, Packet.SET_DUTY)
    with pytest.raises(ValueRangeError, match="packet=256"):
        can_id(1, 256)
    for bad_id in (0x10000, 0x1FFFFFFF, -1):
        with pytest.raises(ValueRangeError, match="VESC's ID range"):
            parse_id(bad_id)


@pytest.mark.parametrize(
    "arbitration_id",
    [
        0x10117,  # bit 16 set: not a VESC ID
        0x1FFFFFFF,
        0x0517,  # FILL_RX_BUFFER (5): a VESC packet the bridge does not read
        0x0417,  # SET_POS (4)
        0x0B17,  # SET_CURRENT_BRAKE_REL (11)
        0x4017,  # BMS_STATUS_1 (64)
        0xFF17,
    ],
)
def test_not_ours(arbitration_id: int) -> None:
    assert decode(message(arbitration_id, "00 00 00 00")) is None


@pytest.mark.parametrize(
    ("flags", "match"),
    [
        ({"is_extended_id": False}, "11-bit ID 0x117"),
        ({"is_remote_frame": True}, "remote"),
        ({"is_error_frame": True}, "error frame"),
    ],
)
def test_only_extended_data_frames(flags: dict[str, bool], match: str) -> None:
    with pytest.raises(NotExtendedIdError, match=match):
        decode(message(0x117, "00 00 c7 38", **flags))


# ---------------------------------------------------------------------------------------------
# Malformed frames


@pytest.mark.parametrize(
    ("arbitration_id", "data", "match"),
    [
        (0x017, "00 00 c3", "SET_DUTY \\(0\\), controller 23: 3 data bytes, expected 4"),
        (0x217, "00 00 27 10 00", "SET_CURRENT_BRAKE \\(2\\), controller 23: 5 data bytes"),
        (0x317, "", "SET_RPM"),
        (0x917, "00 00 88 b8 00 7b 01", "STATUS \\(9\\), controller 23: 7 data bytes, expected 8"),
        (0xE17, "00", "STATUS_2"),
        (0x3A17, "00 00", "STATUS_6"),
        (0x1117, "", "PING \\(17\\), controller 23: 0 data bytes, expected 1"),
        (0x1117, "fe 00", "PING"),
        (0x12FE, "", "PONG \\(18\\), controller 254: 0 data bytes, expected 1 or 2"),
        (0x12FE, "17 00 00", "PONG"),
    ],
)
def test_wrong_dlc(arbitration_id: int, data: str, match: str) -> None:
    with pytest.raises(DlcError, match=match):
        decode(message(arbitration_id, data))


@pytest.mark.parametrize("packet", [Packet.SET_CURRENT, Packet.SET_CURRENT_REL])
def test_the_six_byte_off_delay_form_is_refused_naming_why(packet: Packet) -> None:
    # comm_can_set_current_off_delay() in 7.01 sends current then delay; decode_msg() in 6.x and
    # later reads delay then current (5.x read current first): the layout depends on the reader.
    with pytest.raises(DlcError, match="6 data bytes, expected 4 \\(the 6-byte form with an off"):
        decode(message(packet << 8 | 23, "00 00 c7 38 00 64"))


# ---------------------------------------------------------------------------------------------
# Encoding: values, rounding, ranges


def test_values_round_to_the_nearest_step() -> None:
    # 0.57 x 100 000 is 56 999.999... in binary floating point; the firmware's cast would
    # truncate it to 56 999.
    assert encode_command(1, Packet.SET_DUTY, 0.57).data == struct.pack(">i", 57000)
    assert encode_command(1, Packet.SET_CURRENT, 1.0004).data == struct.pack(">i", 1000)
    assert encode_command(1, Packet.SET_CURRENT, 1.0006).data == struct.pack(">i", 1001)
    assert encode_command(1, Packet.SET_RPM, 1234.5).data == struct.pack(">i", 1234)  # ties even
    assert encode(VescFrame(1, Status(0, 0.06, 0.0))).data[4:6] == struct.pack(">h", 1)


def test_range_ends_are_encoded() -> None:
    assert encode_command(1, Packet.SET_DUTY, 1.0).data == struct.pack(">i", 100000)
    assert encode_command(1, Packet.SET_DUTY, -1.0).data == struct.pack(">i", -100000)
    assert encode_command(1, Packet.SET_CURRENT_REL, -1.0).data == struct.pack(">i", -100000)
    assert encode_command(1, Packet.SET_RPM, I32_MAX).data == struct.pack(">i", I32_MAX)
    assert encode_command(1, Packet.SET_CURRENT, I32_MIN / 1000).data == struct.pack(">i", I32_MIN)


@pytest.mark.parametrize(
    ("packet", "value", "match"),
    [
        (
            Packet.SET_DUTY,
            1.0000001,
            "SET_DUTY \\(0\\): duty=1.0000001 outside the allowed range -1..1",
        ),
        (Packet.SET_DUTY, math.nan, "duty=nan outside"),
        (Packet.SET_CURRENT_REL, -1.5, "SET_CURRENT_REL \\(10\\): fraction=-1.5 outside"),
        (Packet.SET_CURRENT, 2147484.0, "current_a=2147484.0 A scales \\(x1000\\) to 2147484000"),
        (Packet.SET_CURRENT_BRAKE, math.inf, "current_a=inf A is not finite"),
        (Packet.SET_RPM, 2.0**31, "does not fit i32"),
        (Packet.SET_RPM, -math.inf, "not finite"),
    ],
)
def test_out_of_range_commands_are_refused(packet: Packet, value: float, match: str) -> None:
    with pytest.raises(ValueRangeError, match=match):
        encode_command(1, packet, value)


def test_bad_controller_ids_and_packets_are_refused() -> None:
    for bad in (-1, 256):
        with pytest.raises(ValueRangeError, match=f"controller_id={bad}"):
            encode_command(bad, Packet.SET_DUTY, 0.0)
        with pytest.raises(ValueRangeError, match="controller_id"):
            encode(VescFrame(bad, Status(0, 0.0, 0.0)))
    with pytest.raises(ValueRangeError, match="not a VESC motor command"):
        encode_command(1, Packet.STATUS, 0.0)


@pytest.mark.parametrize(
    ("record", "match"),
    [
        (Status(I32_MAX + 1, 0.0, 0.0), "erpm=2147483648 does not fit i32"),
        (Status(0, 3276.8, 0.0), "motor_current_a=3276.8 does not fit i16 at scale x10"),
        (Status(0, 0.0, math.nan), "duty=nan"),
        (Status4(0.0, 0.0, 0.0, 655.36), "pid_position_deg=655.36 .* -655.36..655.34"),
        (Status5(0, -3276.9), "input_voltage_v"),
        (Status6(32.768, 0.0, 0.0, 0.0), "adc1_v"),
        (Ping(256), "sender_id=256 outside 0..255"),
        (Pong(23, -1), "hw_type=-1"),
        (NotifyBoot("123456789"), "at most 8 ASCII characters"),
        (NotifyBoot("é"), "ASCII"),
    ],
)
def test_out_of_range_values_are_refused(record: VescMessage, match: str) -> None:
    with pytest.raises(ValueRangeError, match=match):
        encode(VescFrame(1, record))


# ---------------------------------------------------------------------------------------------
# Properties: record -> frame -> record, frame -> record -> frame

controller_ids = st.integers(0, 255)
i32s = st.integers(I32_MIN, I32_MAX)
i16s = st.integers(I16_MIN, I16_MAX)


def _commands() -> st.SearchStrategy[VescCommand]:
    fractions = st.integers(-100_000, 100_000).map(lambda raw: raw / 100_000)
    return st.one_of(
        fractions.map(SetDuty),
        fractions.map(SetCurrentRel),
        i32s.map(lambda raw: SetCurrent(raw / 1000)),
        i32s.map(lambda raw: SetCurrentBrake(raw / 1000)),
        i32s.map(SetRpm),
    )


def _others() -> st.SearchStrategy[VescMessage]:
    return st.one_of(
        st.builds(lambda e, c, d: Status(e, c / 10, d / 1000), i32s, i16s, i16s),
        st.builds(lambda u, c: Status2(u / 10_000, c / 10_000), i32s, i32s),
        st.builds(lambda u, c: Status3(u / 10_000, c / 10_000), i32s, i32s),
        st.builds(
            lambda f, m, i, p: Status4(f / 10, m / 10, i / 10, p / 50), i16s, i16s, i16s, i16s
        ),
        st.builds(lambda t, v: Status5(t, v / 10), i32s, i16s),
        st.builds(
            lambda a, b, c, p: Status6(a / 1000, b / 1000, c / 1000, p / 1000),
            i16s,
            i16s,
            i16s,
            i16s,
        ),
        st.builds(Ping, controller_ids),
        st.builds(Pong, controller_ids, controller_ids),
        st.text(st.characters(min_codepoint=0, max_codepoint=127), max_size=8).map(NotifyBoot),
    )


@given(controller_ids, st.one_of(_commands(), _others()))
def test_record_round_trip(controller_id: int, record: VescMessage) -> None:
    frame = VescFrame(controller_id, record)
    msg = encode(frame)
    assert msg.arbitration_id >> 16 == 0 and msg.arbitration_id & 0xFF == controller_id
    assert decode(msg) == frame


@given(controller_ids, st.sampled_from(sorted(set(Packet) - {Packet.NOTIFY_BOOT})), st.data())
def test_frame_round_trip(controller_id: int, packet: Packet, data: st.DataObject) -> None:
    size = {Packet.PING: 1, Packet.PONG: 2}.get(packet, 8 if packet in STATUS_PACKETS else 4)
    payload = data.draw(st.binary(min_size=size, max_size=size))
    if packet in (Packet.SET_DUTY, Packet.SET_CURRENT_REL):  # only -1..1 is encodable
        payload = struct.pack(">i", data.draw(st.integers(-100_000, 100_000)))
    if packet == Packet.STATUS_5:
        payload = payload[:6] + b"\0\0"  # the reserved bytes are sent as zero
    msg = can.Message(arbitration_id=packet << 8 | controller_id, data=payload, is_extended_id=True)
    frame = decode(msg)
    assert frame is not None
    again = encode(frame)
    assert (again.arbitration_id, bytes(again.data)) == (msg.arbitration_id, payload)


@given(st.integers(0, 0xFFFF), st.binary(max_size=8))
def test_decode_never_raises_anything_but_a_frame_error(
    arbitration_id: int, payload: bytes
) -> None:
    msg = can.Message(arbitration_id=arbitration_id, data=payload, is_extended_id=True)
    try:
        frame = decode(msg)
    except DlcError:
        return
    assert frame is None or frame.controller_id == arbitration_id & 0xFF
