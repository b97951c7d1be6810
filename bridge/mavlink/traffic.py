"""What a recording keeps of the MAVLink traffic as records: the autopilot's motor outputs and
HEARTBEATs, and every STATUSTEXT.

:class:`TrafficReader` takes the frames as the link records them (each whole, as on the wire,
received or sent) and returns a record for the few it keeps, read with the control loop's own
scanner and motor-output decoders (:mod:`bridge.mavlink.frames`, :mod:`bridge.mavlink.actuators`):
the recording shows the outputs as the loop reads them. Motor outputs and HEARTBEATs count only
from the obeyed autopilot (its system and component ID), as the loop obeys only it; a
STATUSTEXT counts from anyone (the bridge's own among them). Every other frame is skipped by
its ID, undecoded.

:func:`autopilot_stamp_unix_ns` puts an autopilot's own stamp (µs since its boot) on the wall
clock, given its boot clock now (:mod:`bridge.mavlink.boot_time`).

Pure: no pymavlink at run time, no I/O, clock or logging.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from types import ModuleType
from typing import Final

from bridge.mavlink.actuators import HEARTBEAT_ID, MAV_MODE_FLAG_SAFETY_ARMED, decoder_for
from bridge.mavlink.frames import MAGIC_V1, FrameScanner
from bridge.mixing.definition import INPUT_NAMES

__all__ = [
    "STATUSTEXT_ID",
    "AutopilotHeartbeat",
    "MotorOutputs",
    "StatusText",
    "TrafficReader",
    "autopilot_stamp_unix_ns",
]

STATUSTEXT_ID: Final = 253
_STATUSTEXT_LEN: Final = 50  # char[50], after the one-byte severity
# HEARTBEAT: custom_mode u32, type, autopilot, base_mode, system_status, mavlink_version u8.
_HEARTBEAT: Final = struct.Struct("<IBBBBB")
MAX_STAMP_AGE_US: Final = 10_000_000
"""An autopilot stamp this much older than its clock now (or newer than :data:`MAX_STAMP_LEAD_US`)
is not put on the wall clock: from before a reboot, or on another clock than its boot's."""
MAX_STAMP_LEAD_US: Final = 1_000_000


@dataclass(frozen=True, slots=True)
class MotorOutputs:
    """One motor-output message from the autopilot, as the control loop reads it."""

    source: str
    """The message's name (``[mavlink] source``'s), e.g. SERVO_OUTPUT_RAW."""
    channels: dict[str, float]
    """The present input channels by name (``ch1``.., ``roll``..), as received (PWM µs, or
    -1..1)."""
    time_usec: int | None
    """The message's own stamp (the autopilot's µs since boot; 32 bits for SERVO_OUTPUT_RAW);
    None when it carries 0."""
    time_bits: int
    """Width of ``time_usec`` on the wire."""
    armed: bool | None
    """The message's own arming flag (HIL_ACTUATOR_CONTROLS); None for others."""


@dataclass(frozen=True, slots=True)
class AutopilotHeartbeat:
    """The obeyed autopilot's HEARTBEAT."""

    autopilot: int
    """MAV_AUTOPILOT (3 ArduPilot, 12 PX4)."""
    vehicle_type: int
    """MAV_TYPE."""
    base_mode: int
    custom_mode: int
    system_status: int
    armed: bool
    """``base_mode`` has MAV_MODE_FLAG_SAFETY_ARMED."""


@dataclass(frozen=True, slots=True)
class StatusText:
    """A STATUSTEXT, from anyone (the bridge's own, the autopilot's, a ground station's)."""

    severity: int
    """MAV_SEVERITY: 0 emergency .. 7 debug."""
    text: str
    system: int
    component: int


Record = MotorOutputs | AutopilotHeartbeat | StatusText


def _message_id(frame: bytes) -> int:
    if frame[0] == MAGIC_V1:
        return frame[5] if len(frame) > 5 else -1
    return int.from_bytes(frame[7:10], "little") if len(frame) >= 10 else -1


class TrafficReader:
    """Reads the frames a recording keeps as records; one per recording, fed in order (the
    SERVO_OUTPUT_RAW decoder carries channels from one port's message to the next)."""

    def __init__(
        self,
        dialect: ModuleType,
        source: str,
        autopilot: tuple[int, int],
        own: tuple[int, int],
    ) -> None:
        """``dialect``: the link's (:func:`bridge.mavlink.load_dialect`), for the messages'
        CRC_EXTRA; ``source``: ``[mavlink] source``; ``autopilot`` and ``own``: the obeyed
        autopilot's and the bridge's (system, component).

        Raises:
            ConfigError: ``source`` names no motor-output message.
        """
        self._scanner = FrameScanner.for_dialect(dialect, pass_unknown=False)
        self._decoder = decoder_for(source, *own)
        self._autopilot = autopilot
        self._wanted = frozenset({HEARTBEAT_ID, STATUSTEXT_ID} | self._decoder.msg_ids)
        self.bad_frames = 0
        """Frames of a kept ID that did not read back (cannot happen for the link's own)."""

    def read(self, frame: bytes) -> Record | None:
        """The record ``frame`` makes, or None for a frame the recording does not keep."""
        if not frame or _message_id(frame) not in self._wanted:
            return None
        found = self._scanner.feed(frame, whole=True)
        if len(found) != 1:
            self.bad_frames += 1
            return None
        (parsed,) = found
        sender = (parsed.sys_id, parsed.comp_id)
        if parsed.msg_id == STATUSTEXT_ID:
            raw = parsed.payload[1 : 1 + _STATUSTEXT_LEN].split(b"\0", 1)[0]
            return StatusText(parsed.payload[0], raw.decode("ascii", "replace"), *sender)
        if sender != self._autopilot:
            return None
        if parsed.msg_id == HEARTBEAT_ID:
            custom_mode, kind, autopilot, base_mode, status, _ = _HEARTBEAT.unpack_from(
                parsed.payload
            )
            self._decoder.identify(autopilot)
            return AutopilotHeartbeat(
                autopilot,
                kind,
                base_mode,
                custom_mode,
                status,
                bool(base_mode & MAV_MODE_FLAG_SAFETY_ARMED),
            )
        decoded = self._decoder.decode(parsed)
        if decoded is None:
            return None
        channels = {
            name: value
            for name, value in zip(INPUT_NAMES, decoded.values, strict=False)
            if value == value  # NaN: channel absent
        }
        return MotorOutputs(
            self._decoder.name,
            channels,
            decoded.time_us,
            self._decoder.time_bits,
            decoded.armed,
        )


def autopilot_stamp_unix_ns(
    time_usec: int, time_bits: int, boot_usec_now: int, unix_ns_now: int
) -> int | None:
    """The wall time (ns since the Unix epoch) of the autopilot's stamp ``time_usec`` (µs since
    its boot, ``time_bits`` wide on the wire), given that its boot clock reads ``boot_usec_now``
    at ``unix_ns_now``. None when the stamp is more than :data:`MAX_STAMP_AGE_US` older than
    that (or :data:`MAX_STAMP_LEAD_US` newer): it was not made on this boot's clock."""
    age_us = boot_usec_now - time_usec
    if time_bits < 64:  # the stamp wraps: the nearest instant with these low bits
        span = 1 << time_bits
        age_us %= span
        if age_us >= span // 2:
            age_us -= span
    if not -MAX_STAMP_LEAD_US <= age_us <= MAX_STAMP_AGE_US:
        return None
    return unix_ns_now - age_us * 1000
