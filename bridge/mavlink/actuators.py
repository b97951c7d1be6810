"""Decoders of the autopilot's control messages into the bridge's input vector, for the
real-time loop: a :class:`~bridge.mavlink.frames.Frame` in, an :class:`ActuatorInput` out.

Pure: no pymavlink, I/O, clock or logging. Each payload is read with one precompiled
:class:`struct.Struct` in MAVLink wire order (fields sorted by type size, largest first, in
definition order among equals; extension fields last, in definition order), over the payload
zero-extended to the message's full length, so a truncated MAVLink 2 payload and a MAVLink 1
frame without the extensions read the missing fields as 0. tests/mavlink/test_actuators.py
checks every layout against pymavlink's dialect.

The input vector has :data:`INPUT_VECTOR_LEN` floats in the order of
``bridge.mixing.definition.INPUT_NAMES`` (``ch1..ch32, roll, pitch, yaw, thrust``); NaN means
absent. :class:`bridge.mavlink.link.MavlinkLink` decodes with these same decoders:

======================================  ===================================================
 source (``[mavlink] source``)           message and rule
======================================  ===================================================
 ``servo_output_raw``                    SERVO_OUTPUT_RAW port 0 -> ch1..16, port 1 ->
                                         ch17..32, other ports refused; a raw value of 0 is
                                         no output (absent); a port that missed a whole
                                         round of the other port is absent, not held (see
                                         :class:`ServoOutputRawDecoder`). uint32 time_usec.
 ``actuator_output_status``              ACTUATOR_OUTPUT_STATUS actuator[i] -> ch(i+1) where
                                         bit i of ``active`` is set; from PX4 (its HEARTBEAT
                                         says MAV_AUTOPILOT_PX4) ``active`` is the number of
                                         outputs: ch1..ch(active)
 ``hil_actuator_controls``               HIL_ACTUATOR_CONTROLS controls[0..15] -> ch1..16;
                                         ``mode`` & MAV_MODE_FLAG_SAFETY_ARMED -> ``armed``
 ``actuator_control_target``             ACTUATOR_CONTROL_TARGET group 0 and
                                         SET_ACTUATOR_CONTROL_TARGET group 0 addressed to us
                                         (target system 0 or ours, component 0 or ours):
                                         controls[0..3] -> roll, pitch, yaw, thrust
======================================  ===================================================

A float that is not finite is absent: an autopilot's inf is no command, it would saturate the
output. The decoders do not look at the sender: the caller obeys only the autopilot's system
and component id, as :class:`bridge.mavlink.link.MavlinkLink` does.

Cost: decode runs for every output message (up to 1000 Hz), so it builds one list per result
and nothing else: no dicts, no attribute look-ups by name.
"""

from __future__ import annotations

import struct
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Final, get_args

from bridge.config import MavlinkSource
from bridge.errors import ConfigError
from bridge.mavlink.frames import Frame
from bridge.mixing.definition import AXIS_NAMES, CHANNEL_COUNT, INPUT_NAMES

__all__ = [
    "ACTUATOR_CONTROL_TARGET_ID",
    "ACTUATOR_OUTPUT_STATUS_ID",
    "HEARTBEAT_ID",
    "HIL_ACTUATOR_CONTROLS_ID",
    "INPUT_VECTOR_LEN",
    "MAV_MODE_FLAG_SAFETY_ARMED",
    "SERVO_OUTPUT_RAW_ID",
    "SET_ACTUATOR_CONTROL_TARGET_ID",
    "ActuatorControlTargetDecoder",
    "ActuatorDecoder",
    "ActuatorInput",
    "ActuatorOutputStatusDecoder",
    "HilActuatorControlsDecoder",
    "ServoOutputRawDecoder",
    "decoder_for",
    "heartbeat_armed",
    "heartbeat_autopilot",
]

INPUT_VECTOR_LEN: Final = len(INPUT_NAMES)
"""36: ``ch1..ch32``, then ``roll, pitch, yaw, thrust``."""

HEARTBEAT_ID: Final = 0
SERVO_OUTPUT_RAW_ID: Final = 36
HIL_ACTUATOR_CONTROLS_ID: Final = 93
SET_ACTUATOR_CONTROL_TARGET_ID: Final = 139
ACTUATOR_CONTROL_TARGET_ID: Final = 140
ACTUATOR_OUTPUT_STATUS_ID: Final = 375
MAV_MODE_FLAG_SAFETY_ARMED: Final = 128
MAV_AUTOPILOT_PX4: Final = 12

# Wire layouts. HEARTBEAT: custom_mode u32, type, autopilot, base_mode, system_status,
# mavlink_version (u8 each): base_mode is byte 6.
_HEARTBEAT_AUTOPILOT_AT: Final = 5
_HEARTBEAT_BASE_MODE_AT: Final = 6
# SERVO_OUTPUT_RAW: time_usec u32, servo1..8_raw u16, port u8; extensions servo9..16_raw u16.
_SERVO: Final = struct.Struct("<I8HB8H")
_SERVO_PORT_AT: Final = 9  # index of port in the unpacked tuple
# ACTUATOR_OUTPUT_STATUS: time_usec u64, active u32, actuator float[32].
_OUTPUT_STATUS: Final = struct.Struct("<QI32f")
# HIL_ACTUATOR_CONTROLS: time_usec u64, flags u64, controls float[16], mode u8.
_HIL: Final = struct.Struct("<QQ16fB")
_HIL_MODE_AT: Final = 18
# ACTUATOR_CONTROL_TARGET: time_usec u64, controls float[8], group_mlx u8.
_CONTROL_TARGET: Final = struct.Struct("<Q8fB")
_CONTROL_GROUP_AT: Final = 9
# SET_ACTUATOR_CONTROL_TARGET: time_usec u64, controls float[8], group_mlx, target_system,
# target_component u8.
_SET_CONTROL_TARGET: Final = struct.Struct("<Q8fBBB")

_NAN: Final = float("nan")
_INF: Final = float("inf")
_PORT_CHANNELS: Final = 16  # SERVO_OUTPUT_RAW carries 16 channels per port
_HIL_CHANNELS: Final = 16
_AXIS_AT: Final = INPUT_NAMES.index(AXIS_NAMES[0])  # roll, pitch, yaw, thrust follow in order
_ABSENT_AXES: Final = [_NAN] * len(AXIS_NAMES)
_ABSENT_AFTER_HIL: Final = [_NAN] * (INPUT_VECTOR_LEN - _HIL_CHANNELS)


@dataclass(slots=True)
class ActuatorInput:
    """One decoded output message."""

    values: list[float]
    """:data:`INPUT_VECTOR_LEN` floats (NaN = absent); the receiver's to keep."""
    time_us: int | None
    """The message's own ``time_usec`` (the autopilot's clock, µs since its boot); None when
    the message carries 0."""
    armed: bool | None = None
    """HIL_ACTUATOR_CONTROLS: its ``mode`` has MAV_MODE_FLAG_SAFETY_ARMED; None for others."""


def _full(payload: bytes, size: int) -> bytes:
    """``payload`` zero-extended to ``size``. The scanner does that for every id it knows; this
    covers a scanner built without these ids, which passes a truncated payload as sent."""
    return payload if len(payload) >= size else payload.ljust(size, b"\0")


def heartbeat_armed(frame: Frame) -> bool | None:
    """For a HEARTBEAT: its ``base_mode`` has MAV_MODE_FLAG_SAFETY_ARMED. None for any other
    message. The sender is not checked (the caller obeys only the autopilot)."""
    if frame.msg_id != HEARTBEAT_ID:
        return None
    payload = frame.payload
    if len(payload) <= _HEARTBEAT_BASE_MODE_AT:
        return False  # truncated to before base_mode: it was 0
    return bool(payload[_HEARTBEAT_BASE_MODE_AT] & MAV_MODE_FLAG_SAFETY_ARMED)


def heartbeat_autopilot(frame: Frame) -> int | None:
    """For a HEARTBEAT: its ``autopilot`` (MAV_AUTOPILOT: 3 ArduPilot, 12 PX4). None for any
    other message."""
    if frame.msg_id != HEARTBEAT_ID:
        return None
    payload = frame.payload
    return payload[_HEARTBEAT_AUTOPILOT_AT] if len(payload) > _HEARTBEAT_AUTOPILOT_AT else 0


class ActuatorDecoder(ABC):
    """Decodes one ``[mavlink] source``'s messages; built by :func:`decoder_for`."""

    name: str
    """The message's name, e.g. ``"SERVO_OUTPUT_RAW"`` (the first, when there are two)."""
    msg_ids: frozenset[int]
    """The message ids :meth:`decode` reads; it returns None for any other."""
    time_bits = 64
    """Width of the messages' ``time_usec``: 32 for SERVO_OUTPUT_RAW (wraps every 71.6 min)."""

    @abstractmethod
    def decode(self, frame: Frame) -> ActuatorInput | None:
        """The input vector of ``frame``, or None when it is no usable output (another
        message, SERVO_OUTPUT_RAW port 2.., control group 1.., addressed elsewhere)."""

    def reset(self) -> None:
        """Forget what earlier messages left (the link was reopened)."""
        return  # most decoders keep nothing from one message to the next

    def identify(self, autopilot: int) -> None:
        """The sender's flight stack (MAV_AUTOPILOT, from its HEARTBEAT), for a message that
        stacks fill differently."""
        return  # most messages mean the same from every stack


class ServoOutputRawDecoder(ActuatorDecoder):
    """SERVO_OUTPUT_RAW, ports 0 (ch1..16) and 1 (ch17..32).

    Channels of both ports are carried from message to message, but a port that missed a whole
    round of the other one becomes absent: ArduPilot stops sending a port once all its channels
    are off, so its last values must not be held. MAVLink 1 carries servo1..8 only (9..16 read
    as 0, absent).
    """

    name = "SERVO_OUTPUT_RAW"
    msg_ids = frozenset((SERVO_OUTPUT_RAW_ID,))
    time_bits = 32

    def __init__(self) -> None:
        self._channels: list[float] = [_NAN] * CHANNEL_COUNT
        # Per port: whether the other port arrived since this one last did.
        self._other_seen = [True, True]

    def reset(self) -> None:
        self._channels = [_NAN] * CHANNEL_COUNT
        self._other_seen = [True, True]

    def decode(self, frame: Frame) -> ActuatorInput | None:
        if frame.msg_id != SERVO_OUTPUT_RAW_ID:
            return None
        fields = _SERVO.unpack_from(_full(frame.payload, _SERVO.size))
        port: int = fields[_SERVO_PORT_AT]
        if port > 1:
            return None  # ports 2.. would be channels 33..: more than the mixer takes
        channels = self._channels
        other = 1 - port
        seen = self._other_seen
        if not seen[port]:
            start = other * _PORT_CHANNELS
            for i in range(start, start + _PORT_CHANNELS):
                channels[i] = _NAN
        seen[port] = False
        seen[other] = True
        at = port * _PORT_CHANNELS
        # fields: time_usec, servo1..8, port, servo9..16; 0 = no output on that channel.
        for raw in fields[1:_SERVO_PORT_AT]:
            channels[at] = float(raw) if raw else _NAN
            at += 1
        for raw in fields[_SERVO_PORT_AT + 1 :]:
            channels[at] = float(raw) if raw else _NAN
            at += 1
        time_us: int = fields[0]
        return ActuatorInput(channels + _ABSENT_AXES, time_us or None)


class ActuatorOutputStatusDecoder(ActuatorDecoder):
    """ACTUATOR_OUTPUT_STATUS: actuator[i] -> ch(i+1) where bit i of ``active`` is set.

    The message definition makes ``active`` a bitmask, but PX4, the stack that sends this
    message, puts the number of outputs there (``active = noutputs`` in its
    ACTUATOR_OUTPUT_STATUS stream: 16 for channels 1..16). Read as bits, that count would drop
    motors (16 is bit 4 alone: channel 5 only), so once the sender's HEARTBEAT names PX4 the
    count is what it means.
    """

    name = "ACTUATOR_OUTPUT_STATUS"
    msg_ids = frozenset((ACTUATOR_OUTPUT_STATUS_ID,))

    def __init__(self) -> None:
        self._active_is_count = False

    def identify(self, autopilot: int) -> None:
        self._active_is_count = autopilot == MAV_AUTOPILOT_PX4

    def decode(self, frame: Frame) -> ActuatorInput | None:
        if frame.msg_id != ACTUATOR_OUTPUT_STATUS_ID:
            return None
        fields = _OUTPUT_STATUS.unpack_from(_full(frame.payload, _OUTPUT_STATUS.size))
        active: int = fields[1]
        if self._active_is_count:
            active = (1 << min(active, CHANNEL_COUNT)) - 1
        values = [_NAN] * INPUT_VECTOR_LEN
        slot = 0
        while active:
            if active & 1:
                value: float = fields[2 + slot]
                if -_INF < value < _INF:  # False for inf and NaN
                    values[slot] = value
            active >>= 1
            slot += 1
        time_us: int = fields[0]
        return ActuatorInput(values, time_us or None)


class HilActuatorControlsDecoder(ActuatorDecoder):
    """HIL_ACTUATOR_CONTROLS: controls[0..15] -> ch1..16, and the arming state of ``mode``."""

    name = "HIL_ACTUATOR_CONTROLS"
    msg_ids = frozenset((HIL_ACTUATOR_CONTROLS_ID,))

    def decode(self, frame: Frame) -> ActuatorInput | None:
        if frame.msg_id != HIL_ACTUATOR_CONTROLS_ID:
            return None
        fields = _HIL.unpack_from(_full(frame.payload, _HIL.size))
        values = [v if -_INF < v < _INF else _NAN for v in fields[2:_HIL_MODE_AT]]
        values += _ABSENT_AFTER_HIL
        time_us: int = fields[0]
        armed = bool(fields[_HIL_MODE_AT] & MAV_MODE_FLAG_SAFETY_ARMED)
        return ActuatorInput(values, time_us or None, armed)


class ActuatorControlTargetDecoder(ActuatorDecoder):
    """ACTUATOR_CONTROL_TARGET and SET_ACTUATOR_CONTROL_TARGET, control group 0 (the flight
    controls; others are gimbal, payload, ...): controls[0..3] -> roll, pitch, yaw, thrust.
    SET_ACTUATOR_CONTROL_TARGET only when addressed to us (system 0 or ours, component 0 or
    ours)."""

    name = "ACTUATOR_CONTROL_TARGET"
    msg_ids = frozenset((ACTUATOR_CONTROL_TARGET_ID, SET_ACTUATOR_CONTROL_TARGET_ID))

    def __init__(self, own_system_id: int, own_component_id: int) -> None:
        self._system_id = own_system_id
        self._component_id = own_component_id

    def decode(self, frame: Frame) -> ActuatorInput | None:
        msg_id = frame.msg_id
        if msg_id == ACTUATOR_CONTROL_TARGET_ID:
            fields = _CONTROL_TARGET.unpack_from(_full(frame.payload, _CONTROL_TARGET.size))
        elif msg_id == SET_ACTUATOR_CONTROL_TARGET_ID:
            fields = _SET_CONTROL_TARGET.unpack_from(_full(frame.payload, _SET_CONTROL_TARGET.size))
            system, component = fields[10], fields[11]
            if (system and system != self._system_id) or (
                component and component != self._component_id
            ):
                return None  # a command addressed to another system or component
        else:
            return None
        if fields[_CONTROL_GROUP_AT]:
            return None
        values = [_NAN] * INPUT_VECTOR_LEN
        for axis in range(len(AXIS_NAMES)):
            value: float = fields[1 + axis]
            if -_INF < value < _INF:  # False for inf and NaN
                values[_AXIS_AT + axis] = value
        time_us: int = fields[0]
        return ActuatorInput(values, time_us or None)


_SOURCES: Final = get_args(MavlinkSource)


def decoder_for(source: str, own_system_id: int, own_component_id: int) -> ActuatorDecoder:
    """A fresh decoder for a ``[mavlink] source`` name (:data:`bridge.config.MavlinkSource`).
    ``own_system_id`` and ``own_component_id`` are the bridge's (its system id is the
    vehicle's): SET_ACTUATOR_CONTROL_TARGET is obeyed only when addressed to them or broadcast.

    Raises:
        ConfigError: ``source`` is not a MavlinkSource name.
    """
    if source == "servo_output_raw":
        return ServoOutputRawDecoder()
    if source == "actuator_output_status":
        return ActuatorOutputStatusDecoder()
    if source == "hil_actuator_controls":
        return HilActuatorControlsDecoder()
    if source == "actuator_control_target":
        return ActuatorControlTargetDecoder(own_system_id, own_component_id)
    raise ConfigError(f"MAVLink source {source!r}: expected one of {', '.join(_SOURCES)}")
