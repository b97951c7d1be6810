"""Control-message decoders against pymavlink: its encoder makes the frames (MAVLink 2 with
truncated payloads, and MAVLink 1 from the v1.0 dialect, which carries no extension fields);
the expected vectors are built from the field values by name, so every wire layout is checked
against the dialect. The scenarios follow tests/mavlink/test_link.py's for the old decoders.
"""

from __future__ import annotations

import math
import struct
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v10 import ardupilotmega as mavlink1

from bridge.errors import ConfigError
from bridge.mavlink import actuators, load_dialect
from bridge.mavlink.actuators import (
    HEARTBEAT_ID,
    INPUT_VECTOR_LEN,
    ActuatorInput,
    decoder_for,
    heartbeat_armed,
)
from bridge.mavlink.frames import Frame, FrameScanner
from bridge.mixing.definition import INPUT_NAMES

DIALECT: Any = load_dialect()
ARMED = DIALECT.MAV_MODE_FLAG_SAFETY_ARMED
HIL_ENABLED = DIALECT.MAV_MODE_FLAG_HIL_ENABLED
OURS = (1, 191)  # the bridge: the vehicle's system id, its own component id

u16 = st.integers(0, 0xFFFF)
u32 = st.integers(0, 0xFFFFFFFF)
u64 = st.integers(0, 0xFFFFFFFFFFFFFFFF)
u8 = st.integers(0, 0xFF)
# Zeros often (MAVLink 2 truncates trailing zero bytes), non-finite values, anything else.
floats = st.one_of(
    st.just(0.0),
    st.sampled_from([math.inf, -math.inf, math.nan, 1.0, -1.0]),
    st.floats(-1e6, 1e6, width=32),
)


def frame_of(msg: Any, mavlink1_codec: bool = False) -> Frame:
    """``msg`` packed by pymavlink and found again by the scanner."""
    dialect = mavlink1 if mavlink1_codec else DIALECT
    mav: Any = dialect.MAVLink(None, srcSystem=1, srcComponent=1)
    (frame,) = FrameScanner.for_dialect(DIALECT).feed(msg.pack(mav))
    assert frame.version == (1 if mavlink1_codec else 2)
    return frame


def f32(value: float) -> float:
    """What a float field holds after the wire: single precision; not finite = absent."""
    stored: float = struct.unpack("<f", struct.pack("<f", value))[0]
    return stored if math.isfinite(stored) else math.nan


def assert_vector(values: list[float], expected: dict[str, float]) -> None:
    """The named inputs hold these values (NaN included); every other one is NaN."""
    assert len(values) == INPUT_VECTOR_LEN == 36
    assert all(type(v) is float for v in values)
    for name, value in zip(INPUT_NAMES, values, strict=True):
        want = expected.get(name, math.nan)
        if math.isnan(want):
            assert math.isnan(value), f"{name} = {value}, expected NaN"
        else:
            assert value == want, name


def decode(source: str, frame: Frame) -> ActuatorInput:
    result = decoder_for(source, *OURS).decode(frame)
    assert result is not None
    return result


# -- layouts against the dialect: every field, v1 and v2, truncated, extensions -----------------


def test_message_ids_and_flags_are_the_dialects() -> None:
    for name in (
        "HEARTBEAT",
        "SERVO_OUTPUT_RAW",
        "ACTUATOR_OUTPUT_STATUS",
        "HIL_ACTUATOR_CONTROLS",
        "ACTUATOR_CONTROL_TARGET",
        "SET_ACTUATOR_CONTROL_TARGET",
    ):
        assert getattr(actuators, f"{name}_ID") == getattr(DIALECT, f"MAVLINK_MSG_ID_{name}")
    assert actuators.MAV_MODE_FLAG_SAFETY_ARMED == ARMED
    assert HEARTBEAT_ID == 0


@given(u32, st.integers(0, 3), st.lists(u16, min_size=16, max_size=16), st.booleans())
def test_servo_output_raw_layout(time_us: int, port: int, raw: list[int], v1: bool) -> None:
    codec = mavlink1 if v1 else DIALECT
    # MAVLink 1 has no extension fields: servo9..16 never leave the sender.
    args = raw[:8] if v1 else raw
    frame = frame_of(codec.MAVLink_servo_output_raw_message(time_us, port, *args), v1)

    result = decoder_for("servo_output_raw", *OURS).decode(frame)

    if port > 1:
        assert result is None
        return
    assert result is not None
    sent = raw[:8] if v1 else raw
    base = 16 * port
    assert_vector(
        result.values, {f"ch{base + i + 1}": float(v) for i, v in enumerate(sent) if v != 0}
    )
    assert (result.time_us, result.armed) == (time_us or None, None)


@given(u64, u32, st.lists(floats, min_size=32, max_size=32))
def test_actuator_output_status_layout(time_us: int, active: int, actuator: list[float]) -> None:
    frame = frame_of(DIALECT.MAVLink_actuator_output_status_message(time_us, active, actuator))

    result = decode("actuator_output_status", frame)

    assert_vector(
        result.values,
        {f"ch{i + 1}": f32(v) for i, v in enumerate(actuator) if active >> i & 1},
    )
    assert (result.time_us, result.armed) == (time_us or None, None)


@given(u64, st.lists(floats, min_size=16, max_size=16), u8, u64, st.booleans())
def test_hil_actuator_controls_layout(
    time_us: int, controls: list[float], mode: int, flags: int, v1: bool
) -> None:
    codec = mavlink1 if v1 else DIALECT
    frame = frame_of(
        codec.MAVLink_hil_actuator_controls_message(time_us, controls, mode, flags), v1
    )

    result = decode("hil_actuator_controls", frame)

    assert_vector(result.values, {f"ch{i + 1}": f32(v) for i, v in enumerate(controls)})
    assert result.armed == bool(mode & ARMED)
    assert result.time_us == (time_us or None)


@given(u64, st.integers(0, 3), st.lists(floats, min_size=8, max_size=8), st.booleans())
def test_actuator_control_target_layout(
    time_us: int, group: int, controls: list[float], v1: bool
) -> None:
    codec = mavlink1 if v1 else DIALECT
    frame = frame_of(codec.MAVLink_actuator_control_target_message(time_us, group, controls), v1)

    result = decoder_for("actuator_control_target", *OURS).decode(frame)

    if group != 0:
        assert result is None  # group 0 is the flight controls; others gimbal, payload, ...
        return
    assert result is not None
    axes = ("roll", "pitch", "yaw", "thrust")
    assert_vector(result.values, {name: f32(v) for name, v in zip(axes, controls, strict=False)})
    assert (result.time_us, result.armed) == (time_us or None, None)


@given(u64, st.integers(0, 1), u8, u8, st.lists(floats, min_size=8, max_size=8), st.booleans())
def test_set_actuator_control_target_layout(
    time_us: int, group: int, system: int, component: int, controls: list[float], v1: bool
) -> None:
    codec = mavlink1 if v1 else DIALECT
    msg = codec.MAVLink_set_actuator_control_target_message(
        time_us, group, system, component, controls
    )
    frame = frame_of(msg, v1)

    result = decoder_for("actuator_control_target", *OURS).decode(frame)

    addressed = system in (0, OURS[0]) and component in (0, OURS[1])
    if group != 0 or not addressed:
        assert result is None
        return
    assert result is not None
    axes = ("roll", "pitch", "yaw", "thrust")
    assert_vector(result.values, {name: f32(v) for name, v in zip(axes, controls, strict=False)})
    assert result.time_us == (time_us or None)


@given(u8, u8, u8, u32, u8, st.booleans())
@settings(max_examples=50)
def test_heartbeat_armed_reads_base_mode(
    kind: int, autopilot: int, base_mode: int, custom_mode: int, status: int, v1: bool
) -> None:
    codec = mavlink1 if v1 else DIALECT
    frame = frame_of(
        codec.MAVLink_heartbeat_message(kind, autopilot, base_mode, custom_mode, status, 3), v1
    )
    assert frame.msg_id == HEARTBEAT_ID
    assert heartbeat_armed(frame) is bool(base_mode & ARMED)


# -- the old decoders' scenarios ----------------------------------------------------------------


def servo(port: int, pwm: list[int], time_us: int = 1) -> Frame:
    values = (list(pwm) + [0] * 16)[:16]
    return frame_of(DIALECT.MAVLink_servo_output_raw_message(time_us, port, *values))


def test_servo_output_raw_ports_fill_channels_and_a_missed_port_is_absent() -> None:
    decoder = decoder_for("servo_output_raw", *OURS)
    port0 = {f"ch{i}": 1000.0 + i for i in range(1, 17) if i != 2}  # ch2 = 0: no output
    port1 = {"ch17": 1700.0, "ch32": 1800.0}

    def vector(frame: Frame) -> list[float]:
        result = decoder.decode(frame)
        assert result is not None
        return result.values

    assert_vector(vector(servo(0, [1001, 0, *range(1003, 1017)])), port0)
    assert_vector(vector(servo(1, [1700] + [0] * 14 + [1800])), port0 | port1)
    # Port 1 arrived since the last port 0, so it is still carried...
    first = vector(servo(0, [1500]))
    assert_vector(first, {"ch1": 1500.0} | port1)
    # ...but once it misses a round of port 0 it is absent, not frozen at its last values.
    assert_vector(vector(servo(0, [1600])), {"ch1": 1600.0})
    assert_vector(first, {"ch1": 1500.0} | port1)  # a result is never changed afterwards
    # Port 2 is refused and changes nothing.
    assert decoder.decode(servo(2, [1234])) is None
    assert_vector(vector(servo(1, [1900])), {"ch1": 1600.0, "ch17": 1900.0})

    decoder.reset()  # a reopened link: nothing carried over
    assert_vector(vector(servo(1, [1901])), {"ch17": 1901.0})


def test_servo_output_raw_over_mavlink1_carries_eight_channels() -> None:
    msg = mavlink1.MAVLink_servo_output_raw_message(77, 0, *range(1101, 1109))
    result = decode("servo_output_raw", frame_of(msg, mavlink1_codec=True))
    assert_vector(result.values, {f"ch{i}": 1100.0 + i for i in range(1, 9)})
    assert result.time_us == 77


def test_actuator_output_status_uses_the_active_mask() -> None:
    actuator = [0.25 * i for i in range(32)]
    actuator[5] = math.inf  # active but not a number: absent, never full scale
    active = 1 << 0 | 1 << 2 | 1 << 5 | 1 << 31
    msg = DIALECT.MAVLink_actuator_output_status_message(0, active, actuator)

    result = decode("actuator_output_status", frame_of(msg))

    assert_vector(result.values, {"ch1": 0.0, "ch3": 0.5, "ch32": 7.75})
    assert result.time_us is None  # 0: the message carried no time


@pytest.mark.parametrize(
    ("autopilot", "active", "expected"),
    [
        # PX4 (its ACTUATOR_OUTPUT_STATUS stream sets active = noutputs): a count.
        ("MAV_AUTOPILOT_PX4", 16, {f"ch{i}": 1000.0 + i for i in range(1, 17)}),
        ("MAV_AUTOPILOT_PX4", 4, {f"ch{i}": 1000.0 + i for i in range(1, 5)}),
        ("MAV_AUTOPILOT_PX4", 0, {}),
        ("MAV_AUTOPILOT_PX4", 40, {f"ch{i}": 1000.0 + i for i in range(1, 33)}),
        # Any other stack, or none heard yet: bits, as the message definition says.
        ("MAV_AUTOPILOT_ARDUPILOTMEGA", 16, {"ch5": 1005.0}),
        (None, 16, {"ch5": 1005.0}),
    ],
)
def test_actuator_output_status_active_is_a_count_from_px4(
    autopilot: str | None, active: int, expected: dict[str, float]
) -> None:
    decoder = decoder_for("actuator_output_status", *OURS)
    if autopilot is not None:
        heartbeat = frame_of(
            DIALECT.MAVLink_heartbeat_message(2, getattr(DIALECT, autopilot), 0, 0, 4, 3)
        )
        decoder.identify(actuators.heartbeat_autopilot(heartbeat) or 0)
    actuator = [1000.0 + i for i in range(1, 33)]
    result = decoder.decode(
        frame_of(DIALECT.MAVLink_actuator_output_status_message(9, active, actuator))
    )
    assert result is not None
    assert_vector(result.values, expected)


def test_heartbeat_autopilot_reads_the_stack() -> None:
    px4 = DIALECT.MAVLink_heartbeat_message(2, DIALECT.MAV_AUTOPILOT_PX4, 0, 0, 4, 3)
    assert actuators.heartbeat_autopilot(frame_of(px4)) == 12
    servo = DIALECT.MAVLink_servo_output_raw_message(1, 0, *[1000] * 8)
    assert actuators.heartbeat_autopilot(frame_of(servo)) is None


def test_hil_actuator_controls_carry_the_arming_state() -> None:
    controls = [0.5, -0.25, 0.125, 1.0] + [0.0] * 12
    armed = decode(
        "hil_actuator_controls",
        frame_of(
            DIALECT.MAVLink_hil_actuator_controls_message(5, controls, HIL_ENABLED | ARMED, 0)
        ),
    )
    disarmed = decode(
        "hil_actuator_controls",
        frame_of(DIALECT.MAVLink_hil_actuator_controls_message(6, controls, HIL_ENABLED, 0)),
    )
    assert (armed.armed, disarmed.armed) == (True, False)
    assert_vector(armed.values, {f"ch{i + 1}": v for i, v in enumerate(controls)})


def test_actuator_control_target_group_0_and_addressing() -> None:
    decoder = decoder_for("actuator_control_target", 1, 191)
    controls = [0.5, -0.25, 0.125, 0.75, 1.0, 1.0, 1.0, 1.0]
    axes = {"roll": 0.5, "pitch": -0.25, "yaw": 0.125, "thrust": 0.75}
    target = DIALECT.MAVLink_actuator_control_target_message
    set_target = DIALECT.MAVLink_set_actuator_control_target_message

    assert decoder.decode(frame_of(target(0, 1, controls))) is None  # group 1: not ours
    assert decoder.decode(frame_of(set_target(0, 0, 1, 1, controls))) is None  # to 1/1
    assert decoder.decode(frame_of(set_target(0, 0, 2, 191, controls))) is None  # system 2
    for msg in (
        target(0, 0, controls),
        set_target(0, 0, 1, 191, controls),  # to us
        set_target(0, 0, 0, 0, controls),  # broadcast
        set_target(0, 0, 1, 0, controls),  # every component of our system
    ):
        result = decoder.decode(frame_of(msg))
        assert result is not None
        assert_vector(result.values, axes)


def test_decoders_refuse_other_messages_and_name_theirs() -> None:
    beat = frame_of(DIALECT.MAVLink_heartbeat_message(2, 3, ARMED, 0, 4, 3))
    status = frame_of(DIALECT.MAVLink_actuator_output_status_message(1, 1, [1.0] * 32))
    expected = {
        "servo_output_raw": ("SERVO_OUTPUT_RAW", {36}),
        "actuator_output_status": ("ACTUATOR_OUTPUT_STATUS", {375}),
        "hil_actuator_controls": ("HIL_ACTUATOR_CONTROLS", {93}),
        "actuator_control_target": ("ACTUATOR_CONTROL_TARGET", {139, 140}),
    }
    for source, (name, ids) in expected.items():
        decoder = decoder_for(source, *OURS)
        assert (decoder.name, decoder.msg_ids) == (name, frozenset(ids))
        assert decoder.decode(beat) is None
        if source != "actuator_output_status":
            assert decoder.decode(status) is None
    assert heartbeat_armed(beat) is True
    assert heartbeat_armed(status) is None


def test_an_unknown_source_is_a_config_error_naming_the_choices() -> None:
    with pytest.raises(ConfigError, match=r"'servo_raw'.*servo_output_raw, actuator_output_status"):
        decoder_for("servo_raw", *OURS)


def test_truncated_payloads_of_ids_the_scanner_does_not_know_decode_the_same() -> None:
    # A scanner that knows none of these ids passes their payloads as sent: truncated.
    bare = FrameScanner({}, {})
    controls = [0.5, -0.25, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    cases = [
        ("servo_output_raw", DIALECT.MAVLink_servo_output_raw_message(9, 0, 1500, *[0] * 15)),
        (
            "actuator_output_status",
            DIALECT.MAVLink_actuator_output_status_message(9, 1, [0.0] * 32),
        ),
        (
            "hil_actuator_controls",
            DIALECT.MAVLink_hil_actuator_controls_message(9, [0.0] * 16, 0, 0),
        ),
        (
            "actuator_control_target",
            DIALECT.MAVLink_actuator_control_target_message(9, 0, controls),
        ),
        (
            "actuator_control_target",
            DIALECT.MAVLink_set_actuator_control_target_message(9, 0, 0, 0, controls),
        ),
    ]
    mav: Any = DIALECT.MAVLink(None, srcSystem=1, srcComponent=1)
    for source, msg in cases:
        raw = msg.pack(mav)
        (short,) = bare.feed(raw)
        (full,) = FrameScanner.for_dialect(DIALECT).feed(raw)
        assert len(short.payload) < len(full.payload), msg.get_type()
        expected = decode(source, full)
        got = decode(source, short)
        assert got.time_us == expected.time_us == 9
        assert_vector(got.values, dict(zip(INPUT_NAMES, expected.values, strict=True)))
    idle = DIALECT.MAVLink_heartbeat_message(0, 0, 0, 0, 0, 0).pack(mav)
    (beat,) = bare.feed(idle)
    assert len(beat.payload) == 1
    assert heartbeat_armed(beat) is False


@pytest.mark.parametrize(
    ("source", "bits"),
    [
        ("servo_output_raw", 32),  # a uint32 time_usec: wraps every 71.6 min
        ("actuator_output_status", 64),
        ("hil_actuator_controls", 64),
        ("actuator_control_target", 64),
    ],
)
def test_each_decoder_says_how_wide_its_time_is(source: str, bits: int) -> None:
    assert decoder_for(source, *OURS).time_bits == bits
