"""Tests for the Flipsky FT codec (bridge/escs/ft/) against docs/protocols.md §4.

Expected bytes are built here independently of the codec: ``struct`` for the fields and the
``crc`` package (bit-by-bit, not table-driven) for CRC-16/MODBUS.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable

import can
import pytest
from crc import Calculator, Crc16
from hypothesis import example, given
from hypothesis import strategies as st

from bridge.errors import (
    CrcError,
    DlcError,
    FrameError,
    NotExtendedIdError,
    ValueRangeError,
)
from bridge.escs.ft import codec, records

REFERENCE_CRC = Calculator(Crc16.MODBUS.value)  # the bitwise register, independent of our table

I32_MIN, I32_MAX = -(2**31), 2**31 - 1
I24_MIN, I24_MAX = -(2**23), 2**23 - 1
I16_MIN, I16_MAX = -(2**15), 2**15 - 1

C = records.Command

# Per command: wire scale, and the largest |raw| the command's range allows (None: i32 alone).
SCALE: dict[records.Command, int] = {
    C.SET_CURRENT_GEAR_CRC16: 100_000,
    C.SET_CURRENT_BRAKE_CRC16: 100_000,
    C.SET_DUTY_GEAR_CRC16: 1_000_000,
    C.SET_CURRENT_PERCENT_CRC16: 100_000,
    C.SET_CURRENT_PERCENT_GEAR_CRC16: 100_000,
    C.SET_CURRENT_BRAKE_PERCENT_CRC16: 100_000,
    C.SET_ERPM_GEAR_CRC16: 1,
    C.SET_POSITION_GEAR_CRC16: 100_000,
    C.SET_ID_CURRENT_CRC16: 100_000,
    C.SET_CURRENT_GEAR: 100_000,
    C.SET_CURRENT_PERCENT_GEAR: 100_000,
    C.SET_DUTY_GEAR: 1_000_000,
    C.SET_ERPM_GEAR: 1,
    C.SET_POSITION_GEAR: 100_000,
    C.SET_CURRENT_BRAKE: 100_000,
    C.SET_CURRENT_BRAKE_PERCENT: 100_000,
}
RAW_LIMIT: dict[records.Command, int | None] = {
    C.SET_CURRENT_GEAR_CRC16: None,
    C.SET_CURRENT_BRAKE_CRC16: None,
    C.SET_DUTY_GEAR_CRC16: 1_000_000,
    C.SET_CURRENT_PERCENT_CRC16: 100_000,
    C.SET_CURRENT_PERCENT_GEAR_CRC16: 100_000,
    C.SET_CURRENT_BRAKE_PERCENT_CRC16: 100_000,
    C.SET_ERPM_GEAR_CRC16: None,
    C.SET_POSITION_GEAR_CRC16: 18_000_000,
    C.SET_ID_CURRENT_CRC16: None,
    C.SET_CURRENT_GEAR: None,
    C.SET_CURRENT_PERCENT_GEAR: 100_000,
    C.SET_DUTY_GEAR: 1_000_000,
    C.SET_ERPM_GEAR: None,
    C.SET_POSITION_GEAR: 18_000_000,
    C.SET_CURRENT_BRAKE: None,
    C.SET_CURRENT_BRAKE_PERCENT: 100_000,
}
# Per command: does the frame carry a gear byte, a CRC, and its DLC (docs/protocols.md §4.3).
GEARED = {C(c) for c in (0x00, 0x02, 0x04, 0x12, 0x13, 0x15, 0x16, 0x17, 0x18, 0x19)}
WITH_CRC = {C(c) for c in (0x00, 0x01, 0x02, 0x03, 0x04, 0x05, 0x12, 0x13, 0x14)}
DLC = {c: 4 + (c in GEARED) + 2 * (c in WITH_CRC) for c in records.Command}
VALID_DLCS: dict[int, set[int]] = {
    **{c: {n} for c, n in DLC.items()},
    C.SET_ID_CURRENT_CRC16: {6, 7},
    **{t: {8} for t in records.Telemetry},
}

# Per command: the record for a value and gear, written out by hand from the spec table.
RECORD: dict[records.Command, Callable[[float, records.Gear], records.FtCommand]] = {
    C.SET_CURRENT_GEAR_CRC16: lambda v, g: records.SetCurrent(v, g, True),
    C.SET_CURRENT_BRAKE_CRC16: lambda v, g: records.SetCurrentBrake(v, True),
    C.SET_DUTY_GEAR_CRC16: lambda v, g: records.SetDuty(v, g, True),
    C.SET_CURRENT_PERCENT_CRC16: lambda v, g: records.SetCurrentPercent(v, None, True),
    C.SET_CURRENT_PERCENT_GEAR_CRC16: lambda v, g: records.SetCurrentPercent(v, g, True),
    C.SET_CURRENT_BRAKE_PERCENT_CRC16: lambda v, g: records.SetCurrentBrakePercent(v, True),
    C.SET_ERPM_GEAR_CRC16: lambda v, g: records.SetErpm(int(v), g, True),
    C.SET_POSITION_GEAR_CRC16: lambda v, g: records.SetPosition(v, g, True),
    C.SET_ID_CURRENT_CRC16: lambda v, g: records.SetIdCurrent(v),
    C.SET_CURRENT_GEAR: lambda v, g: records.SetCurrent(v, g, False),
    C.SET_CURRENT_PERCENT_GEAR: lambda v, g: records.SetCurrentPercent(v, g, False),
    C.SET_DUTY_GEAR: lambda v, g: records.SetDuty(v, g, False),
    C.SET_ERPM_GEAR: lambda v, g: records.SetErpm(int(v), g, False),
    C.SET_POSITION_GEAR: lambda v, g: records.SetPosition(v, g, False),
    C.SET_CURRENT_BRAKE: lambda v, g: records.SetCurrentBrake(v, False),
    C.SET_CURRENT_BRAKE_PERCENT: lambda v, g: records.SetCurrentBrakePercent(v, False),
}
VALUE_FIELD = {
    records.SetCurrent: "current_a",
    records.SetCurrentBrake: "current_a",
    records.SetDuty: "duty",
    records.SetCurrentPercent: "fraction",
    records.SetCurrentBrakePercent: "fraction",
    records.SetErpm: "erpm",
    records.SetPosition: "angle_deg",
    records.SetIdCurrent: "current_a",
}


def message(arbitration_id: int, data: bytes | str, **flags: bool) -> can.Message:
    """An extended data frame unless ``flags`` say otherwise; ``data`` may be hex."""
    payload = bytes.fromhex(data) if isinstance(data, str) else data
    return can.Message(
        arbitration_id=arbitration_id,
        data=payload,
        is_extended_id=flags.pop("is_extended_id", True),
        **flags,
    )


def with_crc(payload: bytes) -> bytes:
    """``payload`` followed by its reference CRC-16/MODBUS, high byte first."""
    return payload + REFERENCE_CRC.checksum(payload).to_bytes(2, "big")


def i24(raw: int) -> bytes:
    return (raw & 0xFFFFFF).to_bytes(3, "big")


def expected_command_bytes(command: records.Command, raw: int, gear: records.Gear) -> bytes:
    payload = struct.pack(">i", raw) + (bytes([gear]) if command in GEARED else b"")
    return with_crc(payload) if command in WITH_CRC else payload


def raw_bounds(command: records.Command) -> tuple[int, int]:
    limit = RAW_LIMIT[command]
    return (I32_MIN, I32_MAX) if limit is None else (-limit, limit)


def value_of(record: records.FtCommand) -> float:
    value: float = getattr(record, VALUE_FIELD[type(record)])
    return value


# ---------------------------------------------------------------------------------------------
# Known frames: docs/protocols.md §4.8 first, then one per command and telemetry type. The bytes
# were produced with struct and the crc package, not with the codec.

KNOWN: list[tuple[records.FtFrame, int, str]] = [
    (
        records.FtFrame(1, records.SetCurrent(50.0, records.Gear.NONE, True)),
        0x00000100,
        "00 4c 4b 40 00 46 73",
    ),
    (records.FtFrame(2, records.SetCurrentBrake(12.5, True)), 0x00000201, "00 13 12 d0 dd fc"),
    (
        records.FtFrame(3, records.SetDuty(-0.25, records.Gear.LOW, True)),
        0x00000302,
        "ff fc 2f 70 01 8d d5",
    ),
    (
        records.FtFrame(4, records.SetCurrentPercent(0.2, None, True)),
        0x00000403,
        "00 00 4e 20 5c 34",
    ),
    (
        records.FtFrame(5, records.SetCurrentPercent(-0.5, records.Gear.MIDDLE, True)),
        0x00000504,
        "ff ff 3c b0 02 0d 34",
    ),
    (
        records.FtFrame(6, records.SetCurrentBrakePercent(0.75, True)),
        0x00000605,
        "00 01 24 f8 66 4b",
    ),
    (
        records.FtFrame(7, records.SetErpm(-30000, records.Gear.HIGH, True)),
        0x00000712,
        "ff ff 8a d0 03 2b 3c",
    ),
    (
        records.FtFrame(8, records.SetPosition(45.6, records.Gear.REVERSE, True)),
        0x00000813,
        "00 45 94 80 04 e3 10",
    ),
    (records.FtFrame(9, records.SetIdCurrent(3.0)), 0x00000914, "00 04 93 e0 9d 2c"),
    (
        records.FtFrame(10, records.SetCurrent(-7.5, records.Gear.LOW, False)),
        0x00000A15,
        "ff f4 8e 50 01",
    ),
    (
        records.FtFrame(11, records.SetCurrentPercent(1.0, records.Gear.HIGH, False)),
        0x00000B16,
        "00 01 86 a0 03",
    ),
    (
        records.FtFrame(12, records.SetDuty(0.2, records.Gear.NONE, False)),
        0x00000C17,
        "00 03 0d 40 00",
    ),
    (
        records.FtFrame(0, records.SetErpm(12000, records.Gear.MIDDLE, False)),
        0x00000018,
        "00 00 2e e0 02",
    ),
    (
        records.FtFrame(255, records.SetPosition(-180.0, records.Gear.NONE, False)),
        0x0000FF19,
        "fe ed 57 80 00",
    ),
    (records.FtFrame(0x7F, records.SetCurrentBrake(40.0, False)), 0x00007F1A, "00 3d 09 00"),
    (records.FtFrame(0x80, records.SetCurrentBrakePercent(0.1, False)), 0x0000801B, "00 00 27 10"),
    (records.FtFrame(1, records.RealtimeData0(-1.5, 2.25)), 0x0000010B, "ff fa 24 00 08 ca 67 41"),
    (
        records.FtFrame(2, records.RealtimeData1(-12345, 0.95)),
        0x0000020C,
        "ff cf c7 00 03 b6 36 fc",
    ),
    (
        records.FtFrame(3, records.RealtimeData2(45.5, 60.25, 50.4)),
        0x0000030D,
        "11 c6 17 89 13 b0 91 53",
    ),
    (
        records.FtFrame(4, records.RealtimeData0(-8388.608, 8388.607)),
        0x0000040B,
        "80 00 00 7f ff ff b3 2f",
    ),
]
KNOWN_IDS = [f"0x{arbitration_id:04X}" for _, arbitration_id, _ in KNOWN]


def test_known_frames_cover_every_command_and_telemetry_type() -> None:
    assert {arbitration_id & 0xFF for _, arbitration_id, _ in KNOWN} == {
        *records.Command,
        *records.Telemetry,
    }


@pytest.mark.parametrize(("frame", "arbitration_id", "data"), KNOWN, ids=KNOWN_IDS)
def test_encode_known_frame(frame: records.FtFrame, arbitration_id: int, data: str) -> None:
    msg = codec.encode(frame)
    assert msg.arbitration_id == arbitration_id
    assert msg.data.hex(" ") == data
    assert msg.dlc == len(bytes.fromhex(data))
    assert msg.is_extended_id
    assert not msg.is_remote_frame
    assert not msg.is_error_frame


@pytest.mark.parametrize(("frame", "arbitration_id", "data"), KNOWN, ids=KNOWN_IDS)
def test_decode_known_frame(frame: records.FtFrame, arbitration_id: int, data: str) -> None:
    assert codec.decode(message(arbitration_id, data)) == frame


def test_node_id_is_esc_id() -> None:
    assert records.FtFrame(42, records.SetIdCurrent(0.0)).node_id == 42


# ---------------------------------------------------------------------------------------------
# CRC


def test_crc_check_value() -> None:
    assert records.crc16_modbus(b"123456789") == 0x4B37
    assert records.crc16_modbus(bytearray(b"123456789")) == 0x4B37
    assert records.crc16_modbus(memoryview(b"123456789")) == 0x4B37
    assert records.crc16_modbus(b"") == 0xFFFF


@given(st.binary(max_size=64))
def test_crc_matches_reference_package(data: bytes) -> None:
    assert records.crc16_modbus(data) == REFERENCE_CRC.checksum(data)


# ---------------------------------------------------------------------------------------------
# Enumerations, record mapping and CAN IDs


def test_command_ids_are_the_seeds_enum() -> None:
    # The vendor document's enum (docs/protocols.md §4.3, §4.9): 0..5, 18..27 are commands (16
    # of them), 11..13 telemetry.
    assert sorted(records.Command) == [*range(0, 6), *range(18, 28)]
    assert sorted(records.Telemetry) == [11, 12, 13]
    assert [int(g) for g in records.Gear] == [0, 1, 2, 3, 4]


def test_command_records_is_one_to_one() -> None:
    assert set(records.COMMAND_RECORDS) == set(records.Command)
    assert len(set(records.COMMAND_RECORDS.values())) == len(records.Command)
    for command, (cls, has_crc, has_gear) in records.COMMAND_RECORDS.items():
        record = RECORD[command](0.0, records.Gear.NONE)
        assert type(record) is cls
        assert has_crc == (command in WITH_CRC)
        assert has_gear == (command in GEARED)


@given(st.integers(0, 255), st.integers(0, 255))
def test_can_id_and_parse_id_invert(esc_id: int, command: int) -> None:
    arbitration_id = records.can_id(esc_id, command)
    assert arbitration_id == esc_id * 256 + command
    assert records.parse_id(arbitration_id) == (esc_id, command)


@pytest.mark.parametrize(("esc_id", "command"), [(-1, 0), (256, 0), (0, -1), (0, 256)])
def test_can_id_out_of_range(esc_id: int, command: int) -> None:
    with pytest.raises(ValueRangeError, match="outside"):
        records.can_id(esc_id, command)


@pytest.mark.parametrize("arbitration_id", [-1, 0x10000, 0x1FFFFFFF, 0x004E8500])
def test_parse_id_refuses_ids_above_16_bits(arbitration_id: int) -> None:
    with pytest.raises(ValueRangeError, match="FT's ID range"):
        records.parse_id(arbitration_id)


# ---------------------------------------------------------------------------------------------
# Round trips


def command_raw(command: records.Command) -> st.SearchStrategy[int]:
    lowest, highest = raw_bounds(command)
    edges = [lowest, lowest + 1, -1, 0, 1, highest - 1, highest]
    return st.one_of(st.sampled_from(edges), st.integers(lowest, highest))


@pytest.mark.parametrize("command", list(records.Command), ids=lambda c: c.name)
@given(data=st.data())
def test_command_round_trip_exact(command: records.Command, data: st.DataObject) -> None:
    """Values on the wire grid survive encode → decode unchanged, at every gear."""
    raw = data.draw(command_raw(command), label="raw")
    gear = (
        data.draw(st.sampled_from(records.Gear), label="gear")
        if command in GEARED
        else records.Gear.NONE
    )
    esc_id = data.draw(st.integers(0, 255), label="esc_id")
    value = raw / SCALE[command] if SCALE[command] != 1 else raw
    frame = records.FtFrame(esc_id, RECORD[command](value, gear))

    msg = codec.encode(frame)
    assert msg.arbitration_id == (esc_id << 8) | command
    assert bytes(msg.data) == expected_command_bytes(command, raw, gear)
    assert codec.decode(msg) == frame
    # The hot path produces the same frame as the record path.
    hot = codec.encode_command(esc_id, command, value, gear)
    assert (hot.arbitration_id, hot.data, hot.is_extended_id) == (
        msg.arbitration_id,
        msg.data,
        True,
    )


def command_float(command: records.Command) -> st.SearchStrategy[float]:
    lowest, highest = raw_bounds(command)
    scale = SCALE[command]
    return st.floats(lowest / scale, highest / scale)


@pytest.mark.parametrize("command", list(records.Command), ids=lambda c: c.name)
@given(data=st.data())
def test_command_round_trip_within_half_lsb(command: records.Command, data: st.DataObject) -> None:
    value = data.draw(command_float(command), label="value")
    gear = (
        data.draw(st.sampled_from(records.Gear), label="gear")
        if command in GEARED
        else records.Gear.NONE
    )
    decoded = codec.decode(codec.encode_command(17, command, value, gear))
    assert decoded is not None
    assert decoded.esc_id == 17
    assert not isinstance(
        decoded.message, records.RealtimeData0 | records.RealtimeData1 | records.RealtimeData2
    )
    # Half an LSB, plus a millionth of one for the float products' own rounding.
    lsb = 1 / SCALE[command]
    assert abs(value_of(decoded.message) - value) <= 0.500001 * lsb


def test_values_round_to_nearest_not_truncate() -> None:
    # 0.57 * 100000 == 56999.99999999999; the seed's C casts would send 56999.
    msg = codec.encode_command(1, C.SET_CURRENT_PERCENT_GEAR, 0.57)
    assert struct.unpack(">i", msg.data[:4])[0] == 57000
    msg = codec.encode_command(1, C.SET_DUTY_GEAR, -0.0000004)
    assert struct.unpack(">i", msg.data[:4])[0] == 0


@given(
    st.integers(0, 255),
    st.one_of(st.sampled_from([I24_MIN, -1, 0, I24_MAX]), st.integers(I24_MIN, I24_MAX)),
    st.one_of(st.sampled_from([I24_MIN, -1, 0, I24_MAX]), st.integers(I24_MIN, I24_MAX)),
)
def test_realtime_data_0_and_1_round_trip(esc_id: int, first: int, second: int) -> None:
    payload = with_crc(i24(first) + i24(second))
    for frame, command in [
        (
            records.FtFrame(esc_id, records.RealtimeData0(first / 1000, second / 1000)),
            records.Telemetry.REALTIME_DATA_0,
        ),
        (
            records.FtFrame(esc_id, records.RealtimeData1(first, second / 1000)),
            records.Telemetry.REALTIME_DATA_1,
        ),
    ]:
        msg = codec.encode(frame)
        assert msg.arbitration_id == (esc_id << 8) | command
        assert bytes(msg.data) == payload
        assert codec.decode(msg) == frame


i16s = st.one_of(st.sampled_from([I16_MIN, -1, 0, I16_MAX]), st.integers(I16_MIN, I16_MAX))


@given(st.integers(0, 255), i16s, i16s, i16s)
def test_realtime_data_2_round_trip(esc_id: int, mosfet: int, motor: int, volts: int) -> None:
    frame = records.FtFrame(esc_id, records.RealtimeData2(mosfet / 100, motor / 100, volts / 100))
    msg = codec.encode(frame)
    assert msg.arbitration_id == (esc_id << 8) | records.Telemetry.REALTIME_DATA_2
    assert bytes(msg.data) == with_crc(struct.pack(">hhh", mosfet, motor, volts))
    assert codec.decode(msg) == frame


@pytest.mark.parametrize(
    ("payload", "expected"),
    [
        ("ff ff ff 80 00 00", records.RealtimeData0(-0.001, -8388.608)),
        ("ff ff fe 80 00 01", records.RealtimeData0(-0.002, -8388.607)),
        ("00 7f ff ff 80 00", records.RealtimeData0(32.767, -32.768)),
    ],
)
def test_i24_sign_extension(payload: str, expected: records.RealtimeData0) -> None:
    data = with_crc(bytes.fromhex(payload))
    assert codec.decode(message(0x050B, data)) == records.FtFrame(5, expected)


def test_i24_sign_extension_erpm_and_i16_temperatures() -> None:
    data = with_crc(bytes.fromhex("ff 85 ee ff fc 18"))  # -31250 erpm, duty -1.000
    assert codec.decode(message(0x010C, data)) == records.FtFrame(
        1, records.RealtimeData1(-31250, -1.0)
    )
    data = with_crc(struct.pack(">hhh", -4000, -1, 0))
    assert codec.decode(message(0x010D, data)) == records.FtFrame(
        1, records.RealtimeData2(-40.0, -0.01, 0.0)
    )


def test_id_current_accepts_the_c_examples_dlc_7() -> None:
    data = with_crc(struct.pack(">iB", -150_000, 0))
    assert codec.decode(message(0x0214, data)) == records.FtFrame(2, records.SetIdCurrent(-1.5))
    flipped = bytes([data[0] ^ 0x01]) + data[1:]
    with pytest.raises(CrcError):
        codec.decode(message(0x0214, flipped))


# ---------------------------------------------------------------------------------------------
# Malformed frames


@pytest.mark.parametrize(
    ("flags", "what"),
    [
        ({"is_extended_id": False}, "11-bit"),
        ({"is_remote_frame": True}, "remote"),
        ({"is_error_frame": True}, "error frame"),
    ],
)
def test_not_extended_data_frame(flags: dict[str, bool], what: str) -> None:
    with pytest.raises(NotExtendedIdError, match=what):
        codec.decode(message(0x100, b"", **flags))


@pytest.mark.parametrize("command", [*records.Command, *records.Telemetry], ids=lambda c: c.name)
def test_wrong_dlc(command: int) -> None:
    for length in set(range(9)) - VALID_DLCS[command]:
        with pytest.raises(DlcError, match=rf"{length} data bytes, expected"):
            codec.decode(message(0x0300 | command, bytes(length)))


def crc_frames() -> st.SearchStrategy[can.Message]:
    """Valid encoded frames of every CRC-carrying type, with random contents."""
    commands = st.sampled_from(sorted(WITH_CRC)).flatmap(
        lambda c: st.builds(codec.encode_command, st.integers(0, 255), st.just(c), command_float(c))
    )
    i24_values = st.integers(I24_MIN, I24_MAX).map(lambda raw: raw / 1000)
    telemetry = st.one_of(
        st.builds(records.RealtimeData0, i24_values, i24_values),
        st.builds(records.RealtimeData1, st.integers(I24_MIN, I24_MAX), i24_values),
        st.builds(records.RealtimeData2, *[i16s.map(lambda raw: raw / 100)] * 3),
    ).map(lambda record: codec.encode(records.FtFrame(9, record)))
    return st.one_of(commands, telemetry)


@given(crc_frames(), st.data())
def test_single_bit_flip_is_a_crc_error(msg: can.Message, data: st.DataObject) -> None:
    assert codec.decode(msg) is not None
    bit = data.draw(st.integers(0, 8 * len(msg.data) - 1), label="bit")
    corrupted = bytearray(msg.data)
    corrupted[bit // 8] ^= 1 << (bit % 8)
    with pytest.raises(CrcError, match=r"CRC 0x[0-9A-F]{4} in frame, expected 0x[0-9A-F]{4}"):
        codec.decode(message(msg.arbitration_id, bytes(corrupted)))


def test_gear_byte_above_4_is_a_frame_error() -> None:
    with pytest.raises(FrameError, match=r"gear byte 5, expected 0\.\.4"):
        codec.decode(message(0x0115, struct.pack(">iB", 0, 5)))
    with pytest.raises(FrameError, match="gear byte 255"):
        codec.decode(message(0x0100, with_crc(struct.pack(">iB", 0, 255))))


@given(st.integers(0x10000, 0x1FFFFFFF), st.binary(max_size=8))
@example(0x004E8500, bytes.fromhex("e8c35d0000 7d01c0"))  # a CKESC RawCommand_12b
@example(0x0001010B, with_crc(bytes(6)))  # telemetry with bit 16 set
def test_ids_above_16_bits_are_not_ours(arbitration_id: int, data: bytes) -> None:
    assert codec.decode(message(arbitration_id, data)) is None


UNKNOWN_COMMANDS = sorted(set(range(256)) - set(records.Command) - set(records.Telemetry))


@given(st.integers(0, 255), st.sampled_from(UNKNOWN_COMMANDS), st.binary(max_size=8))
def test_unknown_command_bytes_are_not_ours(esc_id: int, command: int, data: bytes) -> None:
    assert codec.decode(message((esc_id << 8) | command, data)) is None


# ---------------------------------------------------------------------------------------------
# Values that must not be encoded


@pytest.mark.parametrize("command", list(records.Command), ids=lambda c: c.name)
@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
def test_non_finite_values_are_refused(command: records.Command, value: float) -> None:
    with pytest.raises(ValueRangeError, match=rf"={value}"):
        codec.encode_command(1, command, value)
    if SCALE[command] == 1:
        return  # SetErpm holds an int, which cannot be NaN or infinite
    with pytest.raises(ValueRangeError, match=rf"={value}"):
        codec.encode(records.FtFrame(1, RECORD[command](value, records.Gear.NONE)))


@pytest.mark.parametrize("command", list(records.Command), ids=lambda c: c.name)
def test_range_boundaries(command: records.Command) -> None:
    """The ends of the range encode exactly; one LSB beyond them does not."""
    lowest, highest = raw_bounds(command)
    scale = SCALE[command]
    for raw in (lowest, highest):
        msg = codec.encode_command(1, command, raw / scale)
        assert struct.unpack(">i", msg.data[:4])[0] == raw
    for raw in (lowest - 1, highest + 1):
        with pytest.raises(ValueRangeError, match="allowed range") as caught:
            codec.encode_command(1, command, raw / scale)
        assert VALUE_FIELD[type(RECORD[command](0.0, records.Gear.NONE))] in str(caught.value)


@pytest.mark.parametrize(
    ("record", "pattern"),
    [
        (records.SetDuty(1.000001), r"duty=1\.000001 outside the allowed range -1\.\.1"),
        (records.SetDuty(-1.000001, crc=False), r"duty=-1\.000001 outside"),
        (records.SetDuty(1.0000004), r"duty=1\.0000004 outside"),  # checked before rounding
        (records.SetCurrentPercent(1.00001, None), r"fraction=1\.00001 outside"),
        (records.SetCurrentBrakePercent(-1.5), r"fraction=-1\.5 outside the allowed range -1\.\.1"),
        (records.SetPosition(180.00001), r"angle_deg=180\.00001 deg outside .* -180\.\.180 deg"),
        (records.SetPosition(-181.0, crc=False), r"angle_deg=-181\.0 deg outside"),
        (
            records.SetCurrent(30000.0),
            r"current_a=30000\.0 A scales \(x100000\) to 3000000000, which does not fit i32",
        ),
        (records.SetCurrentBrake(-21474.83649), r"allowed range -21474\.83648\.\.21474\.83647 A"),
        (records.SetIdCurrent(1e300), r"current_a=1e\+300 A"),
        (records.SetErpm(2**31), r"erpm=2147483648 erpm .* -2147483648\.\.2147483647 erpm"),
        (records.SetCurrentPercent(0.5, None, crc=False), r"has no FT command"),
        (
            records.SetCurrent(1.0, records.Gear(4), True),
            None,
        ),  # the valid control for the gear cases below
    ],
)
def test_out_of_range_records(record: records.FtCommand, pattern: str | None) -> None:
    if pattern is None:
        codec.encode(records.FtFrame(1, record))
        return
    with pytest.raises(ValueRangeError, match=pattern):
        codec.encode(records.FtFrame(1, record))


@pytest.mark.parametrize("gear", [-1, 5, 255])
def test_gear_outside_0_to_4_is_refused(gear: int) -> None:
    for command in sorted(GEARED):
        with pytest.raises(ValueRangeError, match=rf"gear={gear} outside 0\.\.4"):
            codec.encode_command(1, command, 0.0, gear)  # type: ignore[arg-type]


@pytest.mark.parametrize("command", sorted(set(records.Command) - GEARED), ids=lambda c: c.name)
def test_gear_given_to_a_command_without_gear_byte(command: records.Command) -> None:
    with pytest.raises(ValueRangeError, match="has no gear byte"):
        codec.encode_command(1, command, 0.0, records.Gear.LOW)


@pytest.mark.parametrize("esc_id", [-1, 256])
def test_esc_id_outside_0_to_255(esc_id: int) -> None:
    with pytest.raises(ValueRangeError, match=rf"esc_id={esc_id} outside 0\.\.255"):
        codec.encode_command(esc_id, C.SET_DUTY_GEAR, 0.0)
    with pytest.raises(ValueRangeError, match="esc_id"):
        codec.encode(records.FtFrame(esc_id, records.RealtimeData0(0.0, 0.0)))


def test_telemetry_id_is_not_a_command() -> None:
    with pytest.raises(ValueRangeError, match="not an FT command"):
        codec.encode_command(1, records.Telemetry.REALTIME_DATA_0, 0.0)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("record", "pattern"),
    [
        (records.RealtimeData0(8388.608, 0.0), r"motor_current_a=8388\.608 does not fit i24"),
        (
            records.RealtimeData0(0.0, -8388.609),
            r"battery_current_a=-8388\.609 .* -8388\.608\.\.8388\.607",
        ),
        (records.RealtimeData1(2**23, 0.0), r"erpm=8388608 does not fit i24"),
        (records.RealtimeData1(0, math.nan), r"duty=nan does not fit i24"),
        (records.RealtimeData2(327.68, 0.0, 0.0), r"mosfet_temp_c=327\.68 does not fit i16"),
        (records.RealtimeData2(0.0, -327.69, 0.0), r"motor_temp_c=-327\.69 .* -327\.68\.\.327\.67"),
        (records.RealtimeData2(0.0, 0.0, math.inf), r"battery_voltage_v=inf does not fit i16"),
    ],
)
def test_telemetry_out_of_range(
    record: records.RealtimeData0 | records.RealtimeData1 | records.RealtimeData2, pattern: str
) -> None:
    with pytest.raises(ValueRangeError, match=pattern):
        codec.encode(records.FtFrame(1, record))
