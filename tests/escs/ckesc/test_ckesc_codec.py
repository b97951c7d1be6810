"""CKESC codec: docs/protocols.md §3.9 vectors, dronecan cross-checks, round trips, malformed
frames (the UAVCAN v0 CAN ID, tail byte and transfer IDs are tested in
tests/escs/test_uavcan_v0.py).

The ``SPEC`` table below is written from docs/protocols.md §3.2, §3.6 and the seed,
independently of the module's own table, so the tests check the module's type IDs, DLCs,
priorities, directions and field ranges against the spec rather than against themselves.
"""

from __future__ import annotations

import math
import typing
from collections.abc import Callable, Mapping
from dataclasses import dataclass, fields, replace
from typing import Any

import can
import dronecan
import pytest
from dronecan.transport import Transfer
from hypothesis import given
from hypothesis import strategies as st

from bridge.errors import (
    DlcError,
    FrameError,
    NotExtendedIdError,
    TailByteError,
    UnknownTypeError,
    ValueRangeError,
)
from bridge.escs.ckesc import codec, messages, records, services
from bridge.escs.uavcan_v0 import message_id, parse_id, service_id

# --------------------------------------------------------------------------------------------
# The spec, as test data


@dataclass(frozen=True)
class Int:
    """An int field accepting lo..hi in steps of ``step``."""

    lo: int
    hi: int
    step: int = 1

    def strategy(self) -> st.SearchStrategy[Any]:
        return st.integers(0, (self.hi - self.lo) // self.step).map(
            lambda k: self.lo + k * self.step
        )

    def bounds(self) -> tuple[Any, Any]:
        return self.lo, self.hi

    def bad(self) -> tuple[Any, ...]:
        off_step = (self.lo + 1,) if self.step > 1 else ()
        return (self.lo - self.step, self.hi + self.step, *off_step)


@dataclass(frozen=True)
class Choice:
    """A field accepting only ``values``; ``bad_values`` are values the encoder must refuse."""

    values: tuple[Any, ...]
    bad_values: tuple[Any, ...]

    def strategy(self) -> st.SearchStrategy[Any]:
        return st.sampled_from(self.values)

    def bounds(self) -> tuple[Any, Any]:
        return self.values[0], self.values[-1]

    def bad(self) -> tuple[Any, ...]:
        return self.bad_values


@dataclass(frozen=True)
class Centi:
    """Volts or amps, 0..655.35 in 0.01 steps (a u16 count of 0.01 on the wire)."""

    def strategy(self) -> st.SearchStrategy[Any]:
        return st.integers(0, 0xFFFF).map(lambda raw: raw / 100)

    def bounds(self) -> tuple[Any, Any]:
        return 0.0, 655.35

    def bad(self) -> tuple[Any, ...]:
        return -0.01, 655.36, math.nan, math.inf


@dataclass(frozen=True)
class Raw6:
    """Six raw bytes (MSG_EXP2..6)."""

    def strategy(self) -> st.SearchStrategy[Any]:
        return st.binary(min_size=6, max_size=6)

    def bounds(self) -> tuple[Any, Any]:
        return bytes(6), b"\xff" * 6

    def bad(self) -> tuple[Any, ...]:
        return bytes(5), bytes(7)


@dataclass(frozen=True)
class Throttles:
    """A tuple of ``count`` throttles, 0..hi each."""

    count: int
    hi: int

    def strategy(self) -> st.SearchStrategy[Any]:
        return st.tuples(*[st.integers(0, self.hi)] * self.count)

    def bounds(self) -> tuple[Any, Any]:
        return (0,) * self.count, (self.hi,) * self.count

    def bad(self) -> tuple[Any, ...]:
        zeros = (0,) * (self.count - 1)
        return (self.hi + 1, *zeros), (*zeros, -1), zeros, (*zeros, 0, 0)


Field = Int | Choice | Centi | Raw6 | Throttles
Variant = Mapping[str, Field]

U8, U16, U32 = Int(0, 0xFF), Int(0, 0xFFFF), Int(0, 0xFFFF_FFFF)
BOOL = Choice((False, True), (2, -1))
ESC_NODE = Int(1, 0x7D)
CHANNEL = Int(1, 20)
INTERVAL_MS = Int(0, 510, 2)
INTERVAL_WRITE_MS = Int(20, 500, 2)
LED_RGB = Int(0, 7)
NIBBLE = Int(0, 15)


@dataclass(frozen=True)
class Spec:
    """One record type: its frame type, who sends it, DLC with tail, priority, field variants."""

    type_id: int
    sender: str  # "host" / "esc" for message frames, "request" / "response" for services
    dlc: int
    priority: int
    variants: tuple[Variant, ...]

    @property
    def service(self) -> bool:
        return self.sender in ("request", "response")


def spec(type_id: int, sender: str, dlc: int, priority: int, *variants: Variant) -> Spec:
    return Spec(type_id, sender, dlc, priority, variants or ({},))


H, M, L, LO = 0, 16, 24, 31  # HIGHEST, MEDIUM, LOW, LOWEST
DEBUG: Variant = {"data": Raw6()}
SET_ID: Variant = {"node_id": ESC_NODE, "throttle_channel": CHANNEL}
SET_LED: Variant = {"save": BOOL, "color": LED_RGB, "blink_hz": Choice((0, 1, 2, 5), (3, 4, 6))}
ROTATION: Variant = {"rotation": Choice((0x00, 0x01, 0xFF), (0x02, 0xFE))}
THROTTLE_SOURCE: Variant = {"source": Choice((0, 1), (2,))}
FREQ_WRITE: Variant = {
    "write": Choice((True,), (2,)),
    "msg1_interval_ms": INTERVAL_WRITE_MS,
    "msg2_interval_ms": INTERVAL_WRITE_MS,
    "msg3_interval_ms": INTERVAL_WRITE_MS,
}
FREQ_READ: Variant = {
    "write": Choice((False,), (2,)),
    "msg1_interval_ms": INTERVAL_MS,
    "msg2_interval_ms": INTERVAL_MS,
    "msg3_interval_ms": INTERVAL_MS,
}
# Seed 4.4.25: each Expand Set command with the parts it takes.
EXPAND_SET_PARTS: dict[int, tuple[int, ...]] = {
    0xFFF0: (1, 2),
    0xFFF1: (0, 1, 2, 3),
    0xFFF2: (1, 2, 3, 4, 5, 6),
    0xFFF4: (0, 1),
    0xFFF5: (1, 2, 3, 4),
    0xFFF6: (1, 2, 3, 4),
    0xFFF7: (1, 2, 3, 4),
    0xFFF8: (0, 1, 2, 3),
    0xFFF9: tuple(range(16)),
    0xFFFA: tuple(range(16)),
    0xFFFB: (1,),
    0xFFFC: tuple(range(7)),
    0xFFFE: (0x00, 0x10, 0x11),
}
EXPAND_SET_VARIANTS: tuple[Variant, ...] = tuple(
    {
        "command": Choice((command,), (0xFFF3, 0xFFFD, 0xFFFF, 0)),
        "part": Choice(parts, tuple(sorted({-1, 256} | (set(range(18)) - set(parts))))[:4]),
    }
    for command, parts in EXPAND_SET_PARTS.items()
)

SPEC: dict[type, Spec] = {
    records.CanTestRequest: spec(
        20000, "host", 6, LO, {"option": Choice((0xAA, 0x55), (0, 1)), "count": U32}
    ),
    records.CanTestReport: spec(20000, "esc", 6, LO, {"count": U32, "option": U8}),
    records.MsgControlRequest: spec(
        20010,
        "host",
        6,
        M,
        {"command": Choice((0x5555_5555, 0xAAAA_AAAA, 0xEEEE_EEEE), (0, 1)), "option": U8},
    ),
    records.MsgControlAck: spec(20010, "esc", 6, M, {"command": U32, "option": U8}),
    records.GetEscIdRequest: spec(20013, "host", 2, M, {"option": U8}),
    records.GetEscIdAnswer: spec(20013, "esc", 3, M, SET_ID),
    records.Msg1: spec(
        20050, "esc", 7, LO, {"speed_rpm": U16, "throttle": Int(0, 2000), "status": U16}
    ),
    records.Msg2: spec(
        20051, "esc", 6, LO, {"voltage_v": Centi(), "current_a": Centi(), "mos_temp_c": U8}
    ),
    records.Msg3: spec(
        20052,
        "esc",
        8,
        LO,
        {"mos_temp_c": U8, "capacitor_temp_c": U8, "motor_temp_c": U8, "mcu_temp_c": U8},
    ),
    records.MsgExp1: spec(
        20053, "esc", 7, LO, {"speed_rpm": U16, "voltage_v": Centi(), "current_a": Centi()}
    ),
    records.MsgExp2: spec(20054, "esc", 7, LO, DEBUG),
    records.MsgExp3: spec(20055, "esc", 7, LO, DEBUG),
    records.MsgExp4: spec(20056, "esc", 7, LO, DEBUG),
    records.MsgExp5: spec(20057, "esc", 7, LO, DEBUG),
    records.MsgExp6: spec(20058, "esc", 7, LO, DEBUG),
    records.MsgExp7: spec(
        20059,
        "esc",
        7,
        LO,
        {
            name: NIBBLE
            for name in (
                "motor_direction",
                "led",
                "throttle_interface",
                "active_freewheeling",
                "timing",
                "timing_2",
                "load_type",
                "prop_lock",
                "startup_acceleration",
                "signal_loss_rate",
            )
        },
    ),
    records.MsgExp8: spec(
        20060, "esc", 7, LO, {"power_on_count": U16, "start_count": U16, "stop_count": U16}
    ),
    records.MsgExp9: spec(20061, "esc", 7, LO, {"total_run_time_s": U32, "self_test_fault": U16}),
    records.MsgExp10: spec(20062, "esc", 7, LO, {"run_time_s": U32, "fault_code_2": U16}),
    records.MsgExp11: spec(
        20063,
        "esc",
        7,
        LO,
        {"mos_temp_c": U8, "mcu_temp_c": U8, "capacitor_temp_c": U8, "motor_temp_c": U8},
    ),
    records.MsgExp12: spec(
        20064,
        "esc",
        8,
        LO,
        {
            "kind": Choice((1, 2, 3, 4), (0, 5)),
            "max_temp_c": U8,
            "run_count": U16,
            "run_time_s": U32,
        },
    ),
    records.RawCommand14b: spec(20100, "host", 8, H, {"throttles": Throttles(4, 2000)}),
    records.RawCommand12b: spec(
        20101, "host", 8, H, {"group": Int(1, 5), "throttles": Throttles(4, 2000)}
    ),
    records.RawCommand10b: spec(20102, "host", 8, H, {"throttles": Throttles(6, 1000)}),
    records.SetIdRequest: spec(210, "request", 3, M, SET_ID),
    records.SetIdResponse: spec(210, "response", 3, M, SET_ID),
    records.SetBaudRequest: spec(211, "request", 2, M, {"baud_code": Int(0, 6)}),
    records.SetBaudResponse: spec(211, "response", 2, M, {"baud_code": Int(0, 6)}),
    records.SetLedRequest: spec(212, "request", 4, L, SET_LED),
    records.SetLedResponse: spec(212, "response", 4, L, SET_LED),
    records.SetRotationRequest: spec(213, "request", 2, L, ROTATION),
    records.SetRotationResponse: spec(213, "response", 2, L, ROTATION),
    records.SetFreqRequest: spec(214, "request", 5, M, FREQ_WRITE, FREQ_READ),
    records.SetFreqResponse: spec(
        214,
        "response",
        5,
        M,
        {**FREQ_READ, "write": BOOL},
    ),
    records.ThrottleSelectRequest: spec(215, "request", 2, M, THROTTLE_SOURCE),
    records.ThrottleSelectResponse: spec(215, "response", 2, M, THROTTLE_SOURCE),
    records.SelfTestRequest: spec(216, "request", 1, LO),
    records.SelfTestResponse: spec(216, "response", 2, LO, {"passed": BOOL}),
    records.ExpandSetRequest: spec(222, "request", 4, M, *EXPAND_SET_VARIANTS),
    records.EscInfoRequest: spec(240, "request", 2, M, {"option": U8}),
    records.EscInfoResponse: spec(
        240,
        "response",
        8,
        M,
        {
            "max_cells": U8,
            "max_current_a": Int(0, 2550, 10),
            "hardware_version": U8,
            "protocol_version": U8,
            "firmware_year": U8,
            "firmware_month": U8,
            "firmware_day": U8,
        },
    ),
    records.MaintenanceRequest: spec(241, "request", 2, M, {"option": Int(0, 2)}),
    records.Maintenance0Response: spec(
        241,
        "response",
        8,
        M,
        {"total_run_time_s": U32, "max_mos_temp_c": U8, "max_capacitor_temp_c": U8},
    ),
    records.Maintenance1Response: spec(
        241, "response", 8, M, {"run_time_s": U32, "run_count": U16}
    ),
    records.Maintenance2Response: spec(
        241, "response", 8, M, {"power_on_count": U16, "stop_count": U16, "self_test_fault": U16}
    ),
    records.MajorConfigRequest: spec(242, "request", 2, M, {"option": U8}),
    records.MajorConfigResponse: spec(
        242,
        "response",
        8,
        M,
        {
            "direction_reversed": BOOL,
            "throttle_source": Choice((0, 1), (2,)),
            "throttle_channel": Int(0, 63),
            "led_blink_hz": Int(0, 31),
            "led_color": LED_RGB,
            "msg1_interval_ms": INTERVAL_MS,
            "msg2_interval_ms": INTERVAL_MS,
            "msg3_interval_ms": INTERVAL_MS,
        },
    ),
}

WITHOUT_TRANSFER_ID = (records.RawCommand10b, records.MsgExp12)
RECORD_TYPES = sorted(SPEC, key=lambda record: (SPEC[record].type_id, record.__name__))
VARIANTS = [
    pytest.param(record, variant, id=f"{record.__name__}-{index}")
    for record in RECORD_TYPES
    for index, variant in enumerate(SPEC[record].variants)
]
BAD_FIELDS = [
    pytest.param(record, variant, name, value, id=f"{record.__name__}-{index}-{name}={value!r}")
    for record in RECORD_TYPES
    for index, variant in enumerate(SPEC[record].variants)
    for name, field in variant.items()
    for value in field.bad()
]


def frame_for(
    record: records.CkescMessage, transfer_id: int | None = 0, node: int = 3
) -> codec.CkescFrame:
    """A valid frame around ``record``: sender and receiver as its direction requires."""
    spec_ = SPEC[type(record)]
    if type(record) in WITHOUT_TRANSFER_ID:
        transfer_id = None
    source, destination = {
        "host": (0, None),
        "esc": (node, None),
        "request": (0, node),
        "response": (node, 0),
    }[spec_.sender]
    return codec.CkescFrame(spec_.priority, source, destination, transfer_id, record)


def boundary_record(record: type, variant: Variant, end: int) -> records.CkescMessage:
    """The record with every field at its low (``end`` 0) or high (1) limit."""
    built: records.CkescMessage = record(
        **{name: field.bounds()[end] for name, field in variant.items()}
    )
    return built


@st.composite
def frames(draw: st.DrawFn, record: type, variant: Variant) -> codec.CkescFrame:
    built = draw(st.builds(record, **{name: f.strategy() for name, f in variant.items()}))
    base = frame_for(built, draw(st.integers(0, 31)), draw(st.integers(1, 0x7D)))
    priority = draw(st.integers(0, 31))
    if SPEC[record].service:
        # Services decode the same whoever talks to whom.
        source, destination = draw(st.integers(0, 0x7D)), draw(st.integers(0, 0x7D))
        return replace(base, priority=priority, source_node=source, destination_node=destination)
    return replace(base, priority=priority)


def message(can_id: int, data: bytes | str, **flags: bool) -> can.Message:
    payload = bytes.fromhex(data) if isinstance(data, str) else data
    return can.Message(arbitration_id=can_id, data=payload, is_extended_id=True, **flags)


def valid_data(record: type) -> tuple[int, bytes]:
    """CAN ID and data of a valid frame of ``record``'s type."""
    encoded = codec.encode(frame_for(boundary_record(record, SPEC[record].variants[0], 0)))
    return encoded.arbitration_id, bytes(encoded.data)


# --------------------------------------------------------------------------------------------
# docs/protocols.md §3.9


VECTORS = [
    pytest.param(
        codec.CkescFrame(0, 0, None, 0, records.RawCommand12b(1, (1000, 1500, 0, 2000))),
        0x004E8500,
        "e8 c3 5d 00 00 7d 01 c0",
        id="12b",
    ),
    pytest.param(
        codec.CkescFrame(0, 0, None, 0, records.RawCommand14b((1000, 1000, 1000, 1000))),
        0x004E8400,
        "e8 0f a0 3e 80 fa 03 c0",
        id="14b",
    ),
    pytest.param(
        codec.CkescFrame(0, 0, None, None, records.RawCommand10b((100, 200, 300, 400, 500, 1000))),
        0x004E8600,
        "64 20 c3 12 64 f4 a1 0f",
        id="10b",
    ),
    # Another Set LED than §3.9's: the data follow §3.6 (option, colour, blink, tail).
    pytest.param(
        codec.CkescFrame(
            24, 0, 5, 0, records.SetLedRequest(save=True, color=records.LedColor.RED, blink_hz=2)
        ),
        0x18D48580,
        "01 04 02 c0",
        id="set-led",
    ),
    pytest.param(
        codec.CkescFrame(31, 3, None, 7, records.Msg1(12000, 1500, records.Msg1Status.RUNNING)),
        0x1F4E5203,
        "e0 2e dc 05 00 01 c7",
        id="msg1",
    ),
    pytest.param(
        codec.CkescFrame(31, 3, None, 2, records.Msg2(25.20, 12.34, 45)),
        0x1F4E5303,
        "d8 09 d2 04 2d c2",
        id="msg2",
    ),
]


@pytest.mark.parametrize(("frame", "can_id", "data"), VECTORS)
def test_vector_encodes(frame: codec.CkescFrame, can_id: int, data: str) -> None:
    encoded = codec.encode(frame)
    assert (encoded.arbitration_id, encoded.data.hex(" ")) == (can_id, data)
    assert encoded.is_extended_id
    assert not encoded.is_remote_frame


@pytest.mark.parametrize(("frame", "can_id", "data"), VECTORS)
def test_vector_decodes(frame: codec.CkescFrame, can_id: int, data: str) -> None:
    assert codec.decode(message(can_id, data)) == frame
    assert codec.decode(message(can_id, data), esc_nodes={3, 5}) == frame


def test_vectors_through_the_throttle_encoders() -> None:
    cases = [
        (codec.encode_raw_12b(1, [1000, 1500, 0, 2000], 0), 0x004E8500, "e8 c3 5d 00 00 7d 01 c0"),
        (codec.encode_raw_14b([1000] * 4, 0), 0x004E8400, "e8 0f a0 3e 80 fa 03 c0"),
        (
            codec.encode_raw_10b([100, 200, 300, 400, 500, 1000]),
            0x004E8600,
            "64 20 c3 12 64 f4 a1 0f",
        ),
    ]
    for encoded, can_id, data in cases:
        assert (encoded.arbitration_id, encoded.data.hex(" "), encoded.is_extended_id) == (
            can_id,
            data,
            True,
        )


def test_msg1_status_bits_are_the_seeds() -> None:
    expected = {
        "DIRECTION_CCW": 15,
        "THROTTLE_SOURCE_PWM": 14,
        "COMMS_FAULT": 13,
        "UNDER_VOLTAGE": 12,
        "OVER_VOLTAGE": 11,
        "OVER_CURRENT": 10,
        "OVER_TEMPERATURE": 9,
        "RUNNING": 8,
        "SELF_TEST_COM_INPUT_LOW": 7,
        "SELF_TEST_PHASE_C_OUTPUT_LOW": 6,
        "SELF_TEST_PHASE_B_OUTPUT_LOW": 5,
        "SELF_TEST_PHASE_A_OUTPUT_LOW": 4,
        "SELF_TEST_COM_INPUT_HIGH": 3,
        "SELF_TEST_PHASE_C_OUTPUT_HIGH": 2,
        "SELF_TEST_PHASE_B_OUTPUT_HIGH": 1,
        "SELF_TEST_PHASE_A_OUTPUT_HIGH": 0,
    }
    assert {name: records.Msg1Status[name].value.bit_length() - 1 for name in expected} == expected
    assert records.Msg1Status.SELF_TEST_ERRORS.value == 0xFF
    status = codec.decode(message(0x1F4E5203, "00 00 00 00 11 90 c0"))
    assert status is not None and isinstance(status.message, records.Msg1)
    assert (
        status.message.status
        == records.Msg1Status.DIRECTION_CCW | records.Msg1Status.UNDER_VOLTAGE | 0x11
    )
    assert isinstance(status.message.status, records.Msg1Status)


# --------------------------------------------------------------------------------------------
# Cross-checks against dronecan's own serializer (the CAN ID's: tests/escs/test_uavcan_v0.py)


@given(st.lists(st.integers(0, 2000), min_size=4, max_size=4), st.integers(0, 31))
def test_14b_bit_order_matches_dronecan(throttles: list[int], transfer_id: int) -> None:
    command = dronecan.uavcan.equipment.esc.RawCommand(cmd=throttles)
    transfer = Transfer(transfer_id=transfer_id, source_node_id=1, payload=command)
    (expected,) = transfer.to_frames()
    ours = codec.encode_raw_14b(throttles, transfer_id, source_node=1)
    assert bytes(ours.data[:7]) == bytes(expected.bytes[:7])
    assert bytes(ours.data) == bytes(expected.bytes)  # and the tail byte too
    decoded = codec.decode(ours)
    assert decoded is not None and decoded.message == records.RawCommand14b(tuple(throttles))  # type: ignore[arg-type]


# --------------------------------------------------------------------------------------------
# The module's frame table against the spec's


def test_spec_covers_every_record() -> None:
    table = {row.record for row in (*messages.MESSAGE_TYPES, *services.SERVICE_TYPES)}
    assert set(SPEC) == table
    # Every record type is of one of the layouts CkescMessage names.
    assert all(issubclass(record, typing.get_args(records.CkescMessage)) for record in table)
    for record, spec_ in SPEC.items():
        for variant in spec_.variants:
            assert list(variant) == [f.name for f in fields(record)], record


@pytest.mark.parametrize("record", RECORD_TYPES, ids=lambda record: record.__name__)
def test_type_id_priority_and_dlc(record: type) -> None:
    spec_ = SPEC[record]
    sample = boundary_record(record, spec_.variants[0], 0)
    assert codec.type_id_of(sample) == spec_.type_id
    assert codec.default_priority(sample) == spec_.priority
    encoded = codec.encode(frame_for(sample))
    assert len(encoded.data) == spec_.dlc
    assert parse_id(encoded.arbitration_id).type_id == spec_.type_id
    assert parse_id(encoded.arbitration_id).is_service == spec_.service


def test_not_a_record() -> None:
    with pytest.raises(TypeError, match="not a CKESC record"):
        codec.encode(codec.CkescFrame(0, 0, None, 0, "MSG1"))  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="not a CKESC record"):
        codec.default_priority(42)  # type: ignore[arg-type]


# --------------------------------------------------------------------------------------------
# Round trips


@pytest.mark.parametrize(("record", "variant"), VARIANTS)
@given(data=st.data())
def test_round_trip(record: type, variant: Variant, data: st.DataObject) -> None:
    frame = data.draw(frames(record, variant))
    assert codec.decode(codec.encode(frame)) == frame


@pytest.mark.parametrize(("record", "variant"), VARIANTS)
@pytest.mark.parametrize("end", [0, 1], ids=["low", "high"])
def test_round_trip_at_every_limit(record: type, variant: Variant, end: int) -> None:
    for transfer_id in (0, 31):
        for node in (1, 0x7D):
            frame = frame_for(boundary_record(record, variant, end), transfer_id, node)
            assert codec.decode(codec.encode(frame)) == frame
    extremes = replace(frame_for(boundary_record(record, variant, end)), priority=31)
    assert codec.decode(codec.encode(extremes)) == extremes


def esc(record: records.CkescMessage, type_id: int, data: str, node: int = 3) -> Any:
    """A known message frame from ESC ``node`` with transfer ID 1."""
    tid = None if isinstance(record, records.MsgExp12) else 1
    return pytest.param(
        codec.CkescFrame(SPEC[type(record)].priority, node, None, tid, record),
        message_id(SPEC[type(record)].priority, type_id, node),
        data,
        id=type(record).__name__,
    )


def host(record: records.CkescMessage, type_id: int, data: str) -> Any:
    """A known message frame from the host with transfer ID 1."""
    return pytest.param(
        codec.CkescFrame(SPEC[type(record)].priority, 0, None, 1, record),
        message_id(SPEC[type(record)].priority, type_id, 0),
        data,
        id=type(record).__name__,
    )


def svc(record: records.CkescMessage, data: str, node: int = 3) -> Any:
    """A known service frame between the host and ESC ``node``, transfer ID 1."""
    spec_ = SPEC[type(record)]
    request = spec_.sender == "request"
    source, destination = (0, node) if request else (node, 0)
    return pytest.param(
        codec.CkescFrame(spec_.priority, source, destination, 1, record),
        service_id(spec_.priority, spec_.type_id, request, destination, source),
        data,
        id=type(record).__name__,
    )


# One frame per record type, bytes written from the seed's frame tables (section 4.4.x), with
# distinct values per field so that a field in the wrong place shows.
# fmt: off
KNOWN_FRAMES = [
    host(records.CanTestRequest(records.CanTestOption.ENTER, 0x0403_0201), 20000,
         "aa 01 02 03 04 c1"),
    esc(records.CanTestReport(0x0A0B_0C0D), 20000, "00 0d 0c 0b 0a c1"),
    host(records.MsgControlRequest(records.MsgControlCommand.RESUME_EXP), 20010,
         "00 ee ee ee ee c1"),
    esc(records.MsgControlAck(), 20010, "00 00 00 00 00 c1"),
    host(records.GetEscIdRequest(), 20013, "00 c1"),
    esc(records.GetEscIdAnswer(3, 7), 20013, "03 07 c1"),
    esc(records.Msg1(0x0201, 0x0403, records.Msg1Status(0x0605)), 20050, "01 02 03 04 05 06 c1"),
    esc(records.Msg2(5.13, 10.27, 5), 20051, "01 02 03 04 05 c1"),
    esc(records.Msg3(10, 20, 30, 40), 20052, "0a 14 1e 28 00 00 00 c1"),
    esc(records.MsgExp1(0x0201, 10.27, 15.41), 20053, "01 02 03 04 05 06 c1"),
    esc(records.MsgExp2(bytes.fromhex("010203040506")), 20054, "01 02 03 04 05 06 c1"),
    esc(records.MsgExp3(bytes.fromhex("0a0b0c0d0e0f")), 20055, "0a 0b 0c 0d 0e 0f c1"),
    esc(records.MsgExp4(bytes.fromhex("ffeeddccbbaa")), 20056, "ff ee dd cc bb aa c1"),
    esc(records.MsgExp5(bytes(6)), 20057, "00 00 00 00 00 00 c1"),
    esc(records.MsgExp6(bytes.fromhex("600000000006")), 20058, "60 00 00 00 00 06 c1"),
    esc(records.MsgExp7(1, 2, 3, 1, 5, 6, 7, 3, 9, 10), 20059, "21 03 51 76 93 0a c1"),
    esc(records.MsgExp8(1, 2, 3), 20060, "01 00 02 00 03 00 c1"),
    esc(records.MsgExp9(0x0403_0201, records.SelfTestFault.PHASE_C_LOW), 20061,
        "01 02 03 04 23 00 c1"),
    esc(records.MsgExp10(0x0403_0201, 0x0605), 20062, "01 02 03 04 05 06 c1"),
    esc(records.MsgExp11(10, 20, 30, 40), 20063, "0a 14 1e 28 00 00 c1"),
    esc(records.MsgExp12(records.TempRecordKind.CAPACITOR, 95, 0x0201, 0x0605_0403), 20064,
        "5f 01 02 03 04 05 06 c3"),
    host(records.RawCommand14b((1, 2, 3, 4)), 20100, "01 00 08 00 30 01 00 c1"),
    host(records.RawCommand12b(5, (0x123, 0x456, 0x789, 0x7AB)), 20101, "23 61 45 89 b7 7a 05 c1"),
    svc(records.SetIdRequest(5, 2), "05 02 c1"),
    svc(records.SetIdResponse(5, 2), "05 02 c1", node=5),
    svc(records.SetBaudRequest(2), "02 c1"),
    svc(records.SetBaudResponse(6), "06 c1"),
    svc(records.SetLedResponse(False, records.LedColor.GREEN | records.LedColor.BLUE, 5),
        "00 03 05 c1"),
    svc(records.SetRotationRequest(records.Rotation.QUERY), "ff c1"),
    svc(records.SetRotationResponse(records.Rotation.REVERSED), "01 c1"),
    svc(records.SetFreqRequest(True, 20, 100, 500), "01 0a 32 fa c1"),
    svc(records.SetFreqResponse(False, 22, 24, 26), "00 0b 0c 0d c1"),
    svc(records.ThrottleSelectRequest(records.ThrottleSource.PWM_AND_CAN), "01 c1"),
    svc(records.ThrottleSelectResponse(records.ThrottleSource.CAN), "00 c1"),
    svc(records.SelfTestRequest(), "c1"),
    svc(records.SelfTestResponse(passed=False), "01 c1"),
    svc(records.ExpandSetRequest(records.ExpandSetCommand.BAUD, 3), "fc ff 03 c1"),
    svc(records.EscInfoRequest(), "00 c1"),
    svc(records.EscInfoResponse(12, 80, 2, 21, 24, 10, 11), "0c 08 02 15 18 0a 0b c1"),
    svc(records.MaintenanceRequest(1), "01 c1"),
    svc(records.Maintenance0Response(0x0403_0201, 5, 6), "01 02 03 04 05 06 00 c1"),
    svc(records.Maintenance1Response(0x0403_0201, 0x0605), "01 02 03 04 05 06 01 c1"),
    svc(records.Maintenance2Response(0x0201, 0x0403, records.SelfTestFault.COM_HIGH),
        "01 02 03 04 02 00 02 c1"),
    svc(records.MajorConfigRequest(), "00 c1"),
    svc(records.MajorConfigResponse(True, records.ThrottleSource.PWM_AND_CAN, 5, 2,
                                    records.LedColor.RED | records.LedColor.BLUE, 20, 100, 500),
        "c5 15 0a 32 fa 00 00 c1"),
]
# fmt: on


def test_known_frames_cover_every_record() -> None:
    frames = [param.values[0] for param in [*KNOWN_FRAMES, *VECTORS]]
    assert {type(frame.message) for frame in frames if isinstance(frame, codec.CkescFrame)} == set(
        SPEC
    )


@pytest.mark.parametrize(("frame", "can_id", "data"), KNOWN_FRAMES)
def test_known_frame_decodes(frame: codec.CkescFrame, can_id: int, data: str) -> None:
    assert codec.decode(message(can_id, data)) == frame


@pytest.mark.parametrize(("frame", "can_id", "data"), KNOWN_FRAMES)
def test_known_frame_encodes(frame: codec.CkescFrame, can_id: int, data: str) -> None:
    encoded = codec.encode(frame)
    assert (encoded.arbitration_id, encoded.data.hex(" ")) == (can_id, data)


def test_decoded_values_have_their_types() -> None:
    frame = codec.decode(message(0x1F4E5D03, "10 0e 00 00 12 00 c0"))
    assert frame is not None and frame.message == records.MsgExp9(
        3600, records.SelfTestFault.PHASE_B_HIGH
    )
    assert isinstance(frame.message.self_test_fault, records.SelfTestFault)
    unknown = codec.decode(message(0x1F4E5D03, "10 0e 00 00 99 00 c0"))
    assert unknown is not None and unknown.message == records.MsgExp9(3600, 0x99)
    assert type(unknown.message.self_test_fault) is int
    volts = codec.decode(message(0x1F4E5503, "00 00 d8 09 01 00 c0"))
    assert volts is not None and volts.message == records.MsgExp1(0, 25.2, 0.01)
    assert isinstance(volts.message.voltage_v, float)
    config = codec.decode(message(service_id(16, 242, False, 0, 3), "c5 15 0a 32 fa 00 00 c0"))
    assert config is not None and isinstance(config.message, records.MajorConfigResponse)
    assert isinstance(config.message.throttle_source, records.ThrottleSource)
    assert isinstance(config.message.led_color, records.LedColor)


def test_out_of_range_values_decode_as_sent() -> None:
    frame = codec.decode(message(0x004E8500, "ff ff ff ff ff ff 06 c0"))
    assert frame is not None and frame.message == records.RawCommand12b(6, (4095, 4095, 4095, 4095))
    with pytest.raises(ValueRangeError, match=r"RawCommand12b\.throttles\[0\] = 4095"):
        codec.encode(frame)


def test_exp7_nibbles_in_wire_order() -> None:
    frame = codec.decode(message(0x1F4E5B03, "12 f3 a1 cb 0d 0e c3"))
    assert frame is not None and frame.message == records.MsgExp7(
        motor_direction=2,
        led=1,
        throttle_interface=3,
        active_freewheeling=1,
        timing=10,
        timing_2=11,
        load_type=12,
        prop_lock=13,
        startup_acceleration=0,
        signal_loss_rate=14,
    )
    # Reserved nibbles (Set_1 and Set_5 high) are not kept: they go back out as zero.
    assert codec.encode(frame).data.hex(" ") == "12 03 a1 cb 0d 0e c3"


@pytest.mark.parametrize(
    ("option", "expected"),
    [
        (0, records.Maintenance0Response(0x0403_0201, 5, 6)),
        (1, records.Maintenance1Response(0x0403_0201, 0x0605)),
        (2, records.Maintenance2Response(0x0201, 0x0403, 0x0605)),
    ],
)
def test_maintenance_response_chosen_by_option_byte(
    option: int, expected: records.CkescMessage
) -> None:
    frame = codec.decode(
        message(service_id(16, 241, False, 0, 4), f"01 02 03 04 05 06 {option:02x} c0")
    )
    assert frame is not None and frame.message == expected


def test_exp12_kind_rides_in_the_tail() -> None:
    for kind in records.TempRecordKind:
        frame = codec.CkescFrame(31, 9, None, None, records.MsgExp12(kind, 90, 12, 3600))
        encoded = codec.encode(frame)
        assert encoded.data.hex(" ") == f"5a 0c 00 10 0e 00 00 c{kind.value}"
        assert codec.decode(encoded) == frame


@given(
    st.integers(1, 5),
    st.lists(st.integers(0, 2000), min_size=1, max_size=4),
    st.integers(0, 31),
    st.integers(0, 0x7D),
)
def test_raw_12b_encoder_matches_the_record_encoder(
    group: int, throttles: list[int], transfer_id: int, source: int
) -> None:
    padded = (*throttles, 0, 0, 0)[:4]
    record = records.RawCommand12b(group, padded)  # type: ignore[arg-type]
    frame = codec.CkescFrame(0, source, None, transfer_id, record)
    fast = codec.encode_raw_12b(group, throttles, transfer_id, source)
    slow = codec.encode(frame)
    assert (fast.arbitration_id, bytes(fast.data)) == (slow.arbitration_id, bytes(slow.data))
    assert codec.decode(fast) == frame


@given(st.lists(st.integers(0, 2000), min_size=1, max_size=4), st.integers(0, 31))
def test_raw_14b_pads_missing_channels_with_zero(throttles: list[int], transfer_id: int) -> None:
    padded = [*throttles, 0, 0, 0][:4]
    assert (
        codec.encode_raw_14b(throttles, transfer_id).data
        == codec.encode_raw_14b(padded, transfer_id).data
    )


@given(st.lists(st.integers(0, 1000), min_size=1, max_size=6), st.integers(0, 0x7D))
def test_raw_10b_encoder_matches_the_record_encoder(throttles: list[int], source: int) -> None:
    padded = (*throttles, 0, 0, 0, 0, 0)[:6]
    frame = codec.CkescFrame(0, source, None, None, records.RawCommand10b(padded))  # type: ignore[arg-type]
    fast = codec.encode_raw_10b(throttles, source)
    assert (fast.arbitration_id, bytes(fast.data)) == (
        codec.encode(frame).arbitration_id,
        bytes(codec.encode(frame).data),
    )
    assert codec.decode(fast) == frame


# --------------------------------------------------------------------------------------------
# node_id


def test_node_id_is_the_escs() -> None:
    assert codec.CkescFrame(31, 7, None, 0, records.Msg1(0, 0, records.Msg1Status(0))).node_id == 7
    assert codec.CkescFrame(24, 0, 9, 0, records.SetRotationRequest(0xFF)).node_id == 9
    assert codec.CkescFrame(24, 9, 0, 0, records.SetRotationResponse(1)).node_id == 9
    assert codec.CkescFrame(0, 0, None, 0, records.RawCommand14b((0, 0, 0, 0))).node_id == 0


# --------------------------------------------------------------------------------------------
# Encoding refuses out-of-range values


@pytest.mark.parametrize(("record", "variant", "name", "value"), BAD_FIELDS)
def test_encode_refuses_a_field_out_of_range(
    record: type, variant: Variant, name: str, value: object
) -> None:
    good = boundary_record(record, variant, 0)
    bad = replace(good, **{name: value})  # type: ignore[arg-type]
    with pytest.raises(ValueRangeError, match=rf"^{record.__name__}\.{name}\b.* = .+ is not "):
        codec.encode(frame_for(bad))


@pytest.mark.parametrize(
    ("frame", "pattern"),
    [
        (
            replace(frame_for(records.Msg1(0, 0, records.Msg1Status(0))), priority=32),
            r"priority = 32 is not in",
        ),
        (
            replace(frame_for(records.Msg1(0, 0, records.Msg1Status(0))), source_node=0x7E),
            r"source_node = 126",
        ),
        (
            replace(frame_for(records.Msg1(0, 0, records.Msg1Status(0))), transfer_id=32),
            r"transfer_id = 32",
        ),
        (
            replace(frame_for(records.Msg1(0, 0, records.Msg1Status(0))), transfer_id=None),
            r"transfer_id = None",
        ),
        (
            replace(frame_for(records.Msg1(0, 0, records.Msg1Status(0))), destination_node=5),
            r"destination_node",
        ),
        (
            replace(frame_for(records.SetBaudRequest(1)), destination_node=0x7E),
            r"destination_node = 126",
        ),
        (
            replace(frame_for(records.SetBaudRequest(1)), destination_node=None),
            r"destination_node = None",
        ),
        (
            replace(frame_for(records.RawCommand10b((0,) * 6)), transfer_id=0),
            r"RawCommand10b \(20102\) carries no transfer ID",
        ),
        (
            replace(
                frame_for(records.MsgExp12(records.TempRecordKind.MOS, 0, 0, 0)), transfer_id=0
            ),
            r"MsgExp12 \(20064\) carries no transfer ID",
        ),
        # decode() tells these apart by the source, so encode() insists on the right one.
        (
            replace(frame_for(records.CanTestRequest(0xAA)), source_node=5),
            r"CanTestRequest \(20000\) is sent by the host",
        ),
        (
            replace(frame_for(records.GetEscIdAnswer(5, 1)), source_node=0),
            r"GetEscIdAnswer \(20013\) is sent by an ESC",
        ),
        (
            replace(
                frame_for(records.MsgControlRequest(records.MsgControlCommand.PAUSE)), source_node=1
            ),
            r"MsgControlRequest \(20010\) is sent by the host",
        ),
        (
            frame_for(records.ExpandSetRequest(records.ExpandSetCommand.DIRECTION, 0)),
            r"part \(for DIRECTION\)",
        ),
    ],
)
def test_encode_refuses_a_bad_envelope(frame: codec.CkescFrame, pattern: str) -> None:
    with pytest.raises(ValueRangeError, match=pattern):
        codec.encode(frame)


@pytest.mark.parametrize(
    ("call", "pattern"),
    [
        (
            lambda: codec.encode_raw_12b(1, [0, 0, 2001, 0], 0),
            r"RawCommand12b throttles\[2\] = 2001",
        ),
        (
            lambda: codec.encode_raw_12b(1, [-1], 0),
            r"RawCommand12b throttles\[0\] = -1 is not in 0\.\.",
        ),
        (lambda: codec.encode_raw_12b(0, [0], 0), r"RawCommand12b group = 0 is not in 1\.\.5"),
        (lambda: codec.encode_raw_12b(6, [0], 0), r"RawCommand12b group = 6 is not in 1\.\.5"),
        (lambda: codec.encode_raw_12b(1, [], 0), r"RawCommand12b takes 1\.\.4 throttles, got 0"),
        (
            lambda: codec.encode_raw_12b(1, [0] * 5, 0),
            r"RawCommand12b takes 1\.\.4 throttles, got 5",
        ),
        (lambda: codec.encode_raw_12b(1, [0], 32), r"transfer_id = 32 is not in 0\.\.31"),
        (lambda: codec.encode_raw_12b(1, [0], 0, 0x7E), r"source_node = 126 is not in 0\.\.125"),
        (lambda: codec.encode_raw_14b([2001], 0), r"RawCommand14b throttles\[0\] = 2001"),
        (lambda: codec.encode_raw_14b([0] * 5, 0), r"RawCommand14b takes 1\.\.4 throttles, got 5"),
        (lambda: codec.encode_raw_14b([0], -1), r"transfer_id = -1 is not in 0\.\.31"),
        (lambda: codec.encode_raw_14b([0], 0, 0x7F), r"source_node = 127"),
        (
            lambda: codec.encode_raw_10b([0, 1001]),
            r"RawCommand10b throttles\[1\] = 1001 is not in 0\.\.",
        ),
        (lambda: codec.encode_raw_10b([0] * 7), r"RawCommand10b takes 1\.\.6 throttles, got 7"),
        (lambda: codec.encode_raw_10b([0], 0x7E), r"source_node = 126"),
    ],
)
def test_throttle_encoders_refuse_and_never_clamp(call: Callable[[], object], pattern: str) -> None:
    with pytest.raises(ValueRangeError, match=pattern):
        call()


# --------------------------------------------------------------------------------------------
# Decoding: malformed frames and frames that are not ours


@pytest.mark.parametrize(
    ("msg", "pattern"),
    [
        (can.Message(arbitration_id=0x123, data=bytes(8), is_extended_id=False), "11-bit ID 0x123"),
        (message(0x1F4E5203, b"", is_remote_frame=True), r"remote \(RTR\) frame"),
        (message(0x1F4E5203, bytes(7), is_error_frame=True), "error frame"),
    ],
)
def test_not_a_29_bit_data_frame(msg: can.Message, pattern: str) -> None:
    with pytest.raises(NotExtendedIdError, match=pattern):
        codec.decode(msg)


@pytest.mark.parametrize("record", RECORD_TYPES, ids=lambda record: record.__name__)
def test_wrong_dlc(record: type) -> None:
    can_id, data = valid_data(record)
    dlc = SPEC[record].dlc
    for length in sorted({0, dlc - 1, min(dlc + 1, 8)} - {dlc}):
        with pytest.raises(
            DlcError, match=rf"\({SPEC[record].type_id}\): DLC {length}, expected {dlc}"
        ):
            codec.decode(message(can_id, (data + bytes(8))[:length]))


@pytest.mark.parametrize(
    "record", [r for r in RECORD_TYPES if r not in WITHOUT_TRANSFER_ID], ids=lambda r: r.__name__
)
@pytest.mark.parametrize("tail", [0x00, 0x40, 0x80, 0xE0, 0x7F, 0xA3])
def test_bad_tail_byte(record: type, tail: int) -> None:
    can_id, data = valid_data(record)
    with pytest.raises(TailByteError, match=rf"\({SPEC[record].type_id}\): tail byte 0x{tail:02X}"):
        codec.decode(message(can_id, data[:-1] + bytes((tail,))))


@pytest.mark.parametrize("tail", [0xC0, 0xC5, 0xDF, 0xE1, 0x81, 0x41])
def test_exp12_tail_must_name_a_record(tail: int) -> None:
    with pytest.raises(TailByteError, match=rf"MsgExp12 \(20064\): tail byte 0x{tail:02X}"):
        codec.decode(message(0x1F4E6003, bytes(7) + bytes((tail,))))


@given(st.binary(min_size=8, max_size=8))
def test_10b_has_no_tail_byte(data: bytes) -> None:
    frame = codec.decode(message(0x004E8600, data))
    assert frame is not None and frame.transfer_id is None
    assert isinstance(frame.message, records.RawCommand10b)


def test_maintenance_response_with_an_unknown_option() -> None:
    with pytest.raises(FrameError, match=r"241\) response: option \(byte 6\) = 3"):
        codec.decode(message(service_id(16, 241, False, 0, 4), "00 00 00 00 00 00 03 c0"))


@pytest.mark.parametrize(
    ("can_id", "pattern"),
    [
        (message_id(31, 20001, 3), "message type 20001 is in CKESC's range"),
        (message_id(31, 20065, 3), "message type 20065"),
        (message_id(0, 20103, 0), "message type 20103"),
        (message_id(31, 20999, 3), "message type 20999"),
        (service_id(16, 200, True, 3, 0), "service type 200 request"),
        (service_id(16, 217, False, 0, 3), "service type 217 response"),
        (service_id(16, 222, False, 0, 3), "service type 222 response"),
        (service_id(16, 223, True, 3, 0), "service type 223 request"),
        (service_id(16, 224, True, 3, 0), "service type 224 request"),
        (service_id(16, 255, True, 3, 0), "service type 255 request"),
    ],
)
def test_unknown_type_in_ckesc_ranges(can_id: int, pattern: str) -> None:
    with pytest.raises(UnknownTypeError, match=pattern):
        codec.decode(message(can_id, bytes(8)))


@pytest.mark.parametrize(
    "can_id",
    [
        message_id(0, 1030, 1),  # uavcan.equipment.esc.RawCommand
        message_id(31, 1034, 3),  # uavcan.equipment.esc.Status
        message_id(31, 19999, 3),
        message_id(31, 21000, 3),
        service_id(30, 1, True, 3, 0),  # uavcan.protocol.GetNodeInfo
        service_id(30, 199, False, 0, 3),
    ],
)
def test_other_types_are_not_ours(can_id: int) -> None:
    assert codec.decode(message(can_id, bytes(8))) is None
    assert codec.decode(message(can_id, bytes(3)), esc_nodes={1, 3}) is None


def test_esc_nodes_keep_foreign_nodes_out() -> None:
    ours = {1, 2}
    msg1 = "e0 2e dc 05 00 01 c7"
    assert codec.decode(message(message_id(31, 20050, 1), msg1), ours) is not None
    assert codec.decode(message(message_id(31, 20050, 3), msg1), ours) is None
    assert (
        codec.decode(message(message_id(31, 20050, 3), msg1)) is not None
    )  # no esc_nodes: decoded
    # Another vendor's frame with the same type ID but another length: not ours, not an error.
    assert codec.decode(message(message_id(31, 20050, 3), bytes(8)), ours) is None
    answer = message(message_id(16, 20013, 3), "03 01 c0")
    assert codec.decode(answer, ours) is None
    assert codec.decode(message(message_id(16, 20010, 9), "00 00 00 00 00 c0"), ours) is None
    assert codec.decode(message(message_id(31, 20000, 9), "00 01 00 00 00 c0"), ours) is None
    assert codec.decode(message(message_id(31, 20064, 9), bytes(7) + b"\xc1"), ours) is None


def test_esc_nodes_keep_foreign_commands_out() -> None:
    ours = {1, 2}
    command = "e8 c3 5d 00 00 7d 01 c0"
    assert codec.decode(message(message_id(0, 20101, 0), command), ours) is not None
    assert codec.decode(message(message_id(0, 20101, 5), command), ours) is None
    assert codec.decode(message(message_id(0, 20101, 5), bytes(3)), ours) is None  # never raises
    assert codec.decode(message(message_id(0, 20101, 5), command)) is not None
    assert codec.decode(message(message_id(0, 20102, 5), bytes(8)), ours) is None
    assert codec.decode(message(message_id(16, 20010, 0), "00 55 55 55 55 c0"), ours) is not None


def test_esc_nodes_keep_foreign_services_out() -> None:
    ours = {1, 2}
    rotation = "ff c0"
    assert codec.decode(message(service_id(24, 213, True, 1, 0), rotation), ours) is not None
    assert codec.decode(message(service_id(24, 213, True, 3, 0), rotation), ours) is None
    assert (
        codec.decode(message(service_id(24, 213, True, 1, 4), rotation), ours) is None
    )  # not host
    assert codec.decode(message(service_id(24, 213, False, 0, 1), "01 c0"), ours) is not None
    assert codec.decode(message(service_id(24, 213, False, 0, 3), "01 c0"), ours) is None
    assert (
        codec.decode(message(service_id(24, 213, False, 4, 1), "01 c0"), ours) is None
    )  # not host
    # Set ID is pseudo-broadcast: the ESC ignores the destination, whichever it is.
    assert codec.decode(message(service_id(16, 210, True, 0x7D, 0), "05 01 c0"), ours) is not None
    assert codec.decode(message(service_id(16, 210, False, 0, 5), "05 01 c0"), ours) is not None


def test_request_and_answer_told_apart_by_source() -> None:
    request = codec.decode(message(message_id(16, 20013, 0), "00 c0"))
    answer = codec.decode(message(message_id(16, 20013, 4), "04 07 c3"))
    assert request == codec.CkescFrame(16, 0, None, 0, records.GetEscIdRequest())
    assert answer == codec.CkescFrame(16, 4, None, 3, records.GetEscIdAnswer(4, 7))
    with pytest.raises(DlcError, match=r"GetEscIdRequest \(20013\): DLC 3, expected 2"):
        codec.decode(message(message_id(16, 20013, 0), "04 07 c3"))
    ack = codec.decode(message(message_id(16, 20010, 4), "00 00 00 00 00 c5"))
    assert ack == codec.CkescFrame(16, 4, None, 5, records.MsgControlAck())
    report = codec.decode(message(message_id(31, 20000, 4), "00 2a 00 00 00 c5"))
    assert report == codec.CkescFrame(31, 4, None, 5, records.CanTestReport(42))


@given(
    st.one_of(
        st.integers(0, (1 << 29) - 1),
        st.builds(
            message_id,
            st.integers(0, 31),
            st.sampled_from([s.type_id for s in SPEC.values() if not s.service]),
            st.integers(0, 0x7D),
        ),
        st.builds(
            service_id,
            st.integers(0, 31),
            st.sampled_from([s.type_id for s in SPEC.values() if s.service]),
            st.booleans(),
            st.integers(0, 0x7D),
            st.integers(0, 0x7D),
        ),
    ),
    st.binary(max_size=8),
    st.none() | st.frozensets(st.integers(0, 0x7F)),
)
def test_any_frame_decodes_or_raises_a_frame_error(
    can_id: int, data: bytes, esc_nodes: frozenset[int] | None
) -> None:
    try:
        frame = codec.decode(message(can_id, data), esc_nodes)
    except FrameError:
        return
    if frame is None:
        return
    # Whatever decodes, and encodes (values may be out of range), comes back the same.
    try:
        encoded = codec.encode(frame)
    except ValueRangeError:
        return
    assert codec.decode(encoded) == frame
