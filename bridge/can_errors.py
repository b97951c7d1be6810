"""SocketCAN error frames, read: what a CAN controller says about the bus, per linux/can/error.h.

A CAN controller's driver tells of the bus's faults by error frames: a frame whose ID carries
``CAN_ERR_FLAG`` and, in place of an ID, a mask of error classes (bus-off, controller problems,
protocol violations, no acknowledgement, ...), with details in its eight data bytes. Every
socket that asks (``CAN_RAW_ERR_FILTER``; python-can asks for all of them by default) receives
them beside the bus's frames. :func:`decode_error_frame` reads one into an :class:`ErrorFrame`,
and :class:`ControllerErrors` folds them into the controller's state as the kernel keeps it
(the ``state`` of ``ip -details link show``) and a count of each fault.

Pure: no I/O, no clock, no logging; the CAN reader feeds it (:mod:`bridge.telemetry.reader`).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Final

__all__ = ["ControllerErrors", "ControllerState", "ErrorFrame", "decode_error_frame"]

# -- linux/can/error.h ------------------------------------------------------------------------
# The error classes, in the frame's ID (with CAN_ERR_FLAG).
CAN_ERR_TX_TIMEOUT: Final = 0x001  # TX timeout (by the driver)
CAN_ERR_LOSTARB: Final = 0x002  # lost arbitration: data[0] the bit
CAN_ERR_CRTL: Final = 0x004  # controller problems: data[1]
CAN_ERR_PROT: Final = 0x008  # protocol violations: data[2] the type, data[3] the location
CAN_ERR_TRX: Final = 0x010  # transceiver status: data[4]
CAN_ERR_ACK: Final = 0x020  # no ACK on transmission
CAN_ERR_BUSOFF: Final = 0x040
CAN_ERR_BUSERROR: Final = 0x080
CAN_ERR_RESTARTED: Final = 0x100  # the controller restarted (restart-ms, or by hand)
CAN_ERR_CNT: Final = 0x200  # data[6] the TX error counter, data[7] the RX error counter
CAN_ERR_MASK: Final = 0x1FFFFFFF

# data[1], with CAN_ERR_CRTL.
CAN_ERR_CRTL_RX_OVERFLOW: Final = 0x01
CAN_ERR_CRTL_TX_OVERFLOW: Final = 0x02
CAN_ERR_CRTL_RX_WARNING: Final = 0x04
CAN_ERR_CRTL_TX_WARNING: Final = 0x08
CAN_ERR_CRTL_RX_PASSIVE: Final = 0x10
CAN_ERR_CRTL_TX_PASSIVE: Final = 0x20
CAN_ERR_CRTL_ACTIVE: Final = 0x40

_CLASS_NAMES: Final = (
    (CAN_ERR_TX_TIMEOUT, "transmit timeout"),
    (CAN_ERR_LOSTARB, "lost arbitration"),
    (CAN_ERR_CRTL, "controller"),
    (CAN_ERR_PROT, "protocol violation"),
    (CAN_ERR_TRX, "transceiver"),
    (CAN_ERR_ACK, "no acknowledgement"),
    (CAN_ERR_BUSOFF, "bus-off"),
    (CAN_ERR_BUSERROR, "bus error"),
    (CAN_ERR_RESTARTED, "controller restarted"),
)
_CONTROLLER_NAMES: Final = (
    (CAN_ERR_CRTL_RX_OVERFLOW, "receive overflow"),
    (CAN_ERR_CRTL_TX_OVERFLOW, "transmit overflow"),
    (CAN_ERR_CRTL_RX_WARNING, "receive errors at warning level"),
    (CAN_ERR_CRTL_TX_WARNING, "transmit errors at warning level"),
    (CAN_ERR_CRTL_RX_PASSIVE, "receive error-passive"),
    (CAN_ERR_CRTL_TX_PASSIVE, "transmit error-passive"),
    (CAN_ERR_CRTL_ACTIVE, "back to error-active"),
)
_PROTOCOL_TYPES: Final = (  # data[2]
    (0x01, "bit"),
    (0x02, "form"),
    (0x04, "stuffing"),
    (0x08, "cannot send dominant bit"),
    (0x10, "cannot send recessive bit"),
    (0x20, "overload"),
    (0x40, "active error announcement"),
    (0x80, "while transmitting"),
)
_PROTOCOL_LOCATIONS: Final = {  # data[3]
    0x03: "start of frame",
    0x02: "ID bits 28-21",
    0x06: "ID bits 20-18",
    0x04: "substitute RTR",
    0x05: "ID extension",
    0x07: "ID bits 17-13",
    0x0F: "ID bits 12-5",
    0x0E: "ID bits 4-0",
    0x0C: "RTR",
    0x0D: "reserved bit 1",
    0x09: "reserved bit 0",
    0x0B: "data length code",
    0x0A: "data",
    0x08: "CRC sequence",
    0x18: "CRC delimiter",
    0x19: "ACK slot",
    0x1B: "ACK delimiter",
    0x1A: "end of frame",
    0x12: "intermission",
}
_TRANSCEIVER: Final = {  # data[4]: CAN H in the low nibble, CAN L in the high one
    0x04: "CAN H not wired",
    0x05: "CAN H shorted to battery",
    0x06: "CAN H shorted to VCC",
    0x07: "CAN H shorted to ground",
    0x40: "CAN L not wired",
    0x50: "CAN L shorted to battery",
    0x60: "CAN L shorted to VCC",
    0x70: "CAN L shorted to ground",
    0x80: "CAN L shorted to CAN H",
}


class ControllerState(enum.IntEnum):
    """A CAN controller's fault confinement state (ISO 11898-1), worst last."""

    ERROR_ACTIVE = 0
    """Fewer than 96 errors counted: all is well."""
    ERROR_WARNING = 1
    """An error counter reached 96: the bus has errors, the controller still takes part."""
    ERROR_PASSIVE = 2
    """An error counter passed 127: it may no longer signal errors; a transmit with no
    acknowledgement (no other node powered) stays here, retrying."""
    BUS_OFF = 3
    """The transmit error counter passed 255: the controller left the bus until restarted."""

    @property
    def text(self) -> str:
        """As iproute2 prints it: ``ERROR-ACTIVE``, ``ERROR-WARNING``, ``ERROR-PASSIVE``,
        ``BUS-OFF``."""
        return self.name.replace("_", "-")


@dataclass(frozen=True)
class ErrorFrame:
    """One error frame, read."""

    classes: int
    """The error-class mask (the frame's ID without ``CAN_ERR_FLAG``)."""
    state: ControllerState | None
    """The controller state the frame announces; None when it announces none."""
    restarted: bool
    """The controller was restarted (after a bus-off): its state is error-active again, and
    whatever it held to send was dropped."""
    receive_overflow: bool
    """The controller's own receive buffer overflowed: frames were lost before the kernel had
    them."""
    problems: tuple[str, ...]
    """Every fault the frame names, in words, for the log."""
    tx_errors: int | None = None
    """The transmit error counter, when the frame carries it."""
    rx_errors: int | None = None
    """The receive error counter, when the frame carries it."""

    def describe(self) -> str:
        """One line: the faults, then the error counters if given."""
        text = "; ".join(self.problems) or "no error class set"
        if self.tx_errors is not None and self.rx_errors is not None:
            text += f" (transmit errors {self.tx_errors}, receive errors {self.rx_errors})"
        return text


def decode_error_frame(classes: int, data: bytes | bytearray) -> ErrorFrame:
    """Read an error frame: ``classes`` is its ID (``CAN_ERR_FLAG`` and any frame-format flags
    are masked off), ``data`` its data bytes (fewer than eight are read as zeros, as a driver
    leaves the bytes it does not fill).

    The state follows the kernel's own ``can_change_state``: a bus-off frame announces bus-off;
    a controller frame announces the worst of the states its data byte names (a driver sets the
    bits of the side, transmit or receive, that changed); a restart announces error-active.
    """
    classes &= CAN_ERR_MASK
    data = bytes(data[:8]).ljust(8, b"\0")
    problems: list[str] = []
    state: ControllerState | None = None
    for bit, name in _CLASS_NAMES:
        if not classes & bit:
            continue
        if bit == CAN_ERR_LOSTARB:
            name += f" at bit {data[0]}" if data[0] else ""
        elif bit == CAN_ERR_CRTL:
            named = _bits(data[1], _CONTROLLER_NAMES)
            name += f": {', '.join(named)}" if named else " problem"
        elif bit == CAN_ERR_PROT:
            kinds = _bits(data[2], _PROTOCOL_TYPES)
            where = _PROTOCOL_LOCATIONS.get(data[3])
            name += f": {', '.join(kinds)}" if kinds else ""
            name += f" at {where}" if where else ""
        elif bit == CAN_ERR_TRX:
            name += f": {_TRANSCEIVER.get(data[4], f'status {data[4]:#04x}')}" if data[4] else ""
        problems.append(name)
    if classes & CAN_ERR_CRTL:
        state = _controller_state(data[1])
    if classes & CAN_ERR_RESTARTED:
        state = ControllerState.ERROR_ACTIVE
    if classes & CAN_ERR_BUSOFF:
        state = ControllerState.BUS_OFF
    counted = bool(classes & CAN_ERR_CNT)
    return ErrorFrame(
        classes,
        state,
        restarted=bool(classes & CAN_ERR_RESTARTED),
        receive_overflow=bool(classes & CAN_ERR_CRTL and data[1] & CAN_ERR_CRTL_RX_OVERFLOW),
        problems=tuple(problems),
        tx_errors=data[6] if counted else None,
        rx_errors=data[7] if counted else None,
    )


def _bits(value: int, names: tuple[tuple[int, str], ...]) -> list[str]:
    return [name for bit, name in names if value & bit]


def _controller_state(flags: int) -> ControllerState | None:
    if flags & (CAN_ERR_CRTL_TX_PASSIVE | CAN_ERR_CRTL_RX_PASSIVE):
        return ControllerState.ERROR_PASSIVE
    if flags & (CAN_ERR_CRTL_TX_WARNING | CAN_ERR_CRTL_RX_WARNING):
        return ControllerState.ERROR_WARNING
    if flags & CAN_ERR_CRTL_ACTIVE:
        return ControllerState.ERROR_ACTIVE
    return None  # an overflow alone, or unspecified: no state change


@dataclass
class ControllerErrors:
    """The controller's state and fault counts, folded from its error frames (one writer)."""

    state: ControllerState = ControllerState.ERROR_ACTIVE
    """As the last error frame that announced one left it."""
    frames: int = 0
    """Error frames read."""
    entered: list[int] = field(default_factory=lambda: [0] * len(ControllerState))
    """How many times each state was entered, by :class:`ControllerState`: a bus-off and its
    restart between two looks are both seen."""
    restarts: int = 0
    receive_overflows: int = 0
    no_ack: int = 0
    """Error frames saying a frame we sent went unacknowledged (no other node on the bus)."""
    bus_errors: int = 0
    """Error frames for protocol violations, lost arbitration, transceiver faults, bus errors."""
    last: ErrorFrame | None = None

    def note(self, frame: ErrorFrame) -> None:
        """Fold one error frame in."""
        self.frames += 1
        self.last = frame
        if frame.restarted:
            self.restarts += 1
        if frame.receive_overflow:
            self.receive_overflows += 1
        if frame.classes & CAN_ERR_ACK:
            self.no_ack += 1
        if frame.classes & (CAN_ERR_PROT | CAN_ERR_LOSTARB | CAN_ERR_TRX | CAN_ERR_BUSERROR):
            self.bus_errors += 1
        if frame.state is not None:
            self._enter(frame.state)

    def note_frame_received(self) -> None:
        """A frame other than an error frame arrived: a controller that receives is not
        bus-off (a restart's own error frame may have been lost with a full queue)."""
        if self.state == ControllerState.BUS_OFF:
            self._enter(ControllerState.ERROR_ACTIVE)

    def _enter(self, state: ControllerState) -> None:
        if state != self.state:
            self.entered[state] += 1
            self.state = state
