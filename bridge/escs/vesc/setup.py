"""Finding the VESCs on a bus: a PING to each controller ID, the PONGs back, and the status
frames each sends meanwhile (docs/protocols.md §6.6). For ``esc-bridge esc vesc-scan``.

A PING to 255 is answered by every VESC with 255 as its ID, so it tells how many answered but
not who: the scan pings each ID in turn. The status frames a VESC sends are off by default, and
the scan says which VESCs have them off, with the VESC Tool setting that turns them on.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Final

import can

from bridge.errors import FrameError, LinkError, NoAnswerError, ValueRangeError
from bridge.escs.vesc.codec import decode, encode
from bridge.escs.vesc.records import (
    BROADCAST_ID,
    STATUS_PACKETS,
    HwType,
    Packet,
    Ping,
    Pong,
    VescFrame,
)

DEFAULT_HOST_ID: Final = 254
"""The ID the scan pings from, where the PONGs go: any ID works (a VESC with it ignores PONGs),
254 is one a UUID-derived VESC ID (0..127) never takes."""
DEFAULT_LISTEN_S: Final = 0.5
"""How long the scan listens after its last PING: PONGs come within milliseconds, and a VESC
sends at least two sets of status frames at the slowest default rate (Can Status Rate 2, 5 Hz)."""
SEND_TIMEOUT_S: Final = 0.1
STATUS_ON_HINT: Final = (
    "turn them on in VESC Tool: App Settings > General > Can Messages Rate 1: Status 1 to 5, "
    "Can Status Rate 1: 50 Hz (firmware 5.x: Can Status Message Mode CAN_STATUS_1_2_3_4_5)"
)
"""What docs/escs.md asks of every VESC the bridge drives."""


@dataclass(frozen=True)
class FoundVesc:
    """One controller ID that answered the scan."""

    controller_id: int
    hw_type: int
    """:class:`~bridge.escs.vesc.records.HwType`'s value (0 VESC)."""
    answers: int
    """PONGs for this ID: more than one means VESCs that share it."""
    status: frozenset[int] = field(default_factory=frozenset)
    """The status packets (9 STATUS, 14 STATUS_2, ...) it sent while the scan listened."""

    @property
    def hw_name(self) -> str:
        return HwType(self.hw_type).name if self.hw_type in set(HwType) else str(self.hw_type)


def scan(
    bus: can.BusABC,
    *,
    host_id: int = DEFAULT_HOST_ID,
    ids: Iterable[int] = range(BROADCAST_ID),
    listen_s: float = DEFAULT_LISTEN_S,
) -> list[FoundVesc]:
    """PING every ID of ``ids`` from ``host_id``, listen ``listen_s`` after the last one, and
    return the IDs that answered, lowest first, with the status frames each sent meanwhile.

    Raises:
        ValueRangeError: ``host_id`` or an ID outside 0..254.
        LinkError: a PING could not be sent.
        NoAnswerError: no VESC answered.
    """
    pinged = sorted(set(ids))
    for checked in (host_id, *pinged):
        if not 0 <= checked < BROADCAST_ID:
            raise ValueRangeError(f"VESC ID {checked} outside 0..{BROADCAST_ID - 1}")
    pongs: dict[int, list[int]] = {}
    status: dict[int, set[int]] = {}
    for controller_id in pinged:
        try:
            bus.send(encode(VescFrame(controller_id, Ping(host_id))), timeout=SEND_TIMEOUT_S)
        except (can.CanError, OSError) as exc:
            raise LinkError(f"PING to VESC {controller_id} not sent: {exc}") from exc
        _take(bus, 0.0, host_id, pongs, status)
    deadline = time.monotonic() + listen_s
    while (left := deadline - time.monotonic()) > 0:
        _take(bus, left, host_id, pongs, status)
    if not pongs:
        raise NoAnswerError(
            f"no VESC answered a PING to IDs {pinged[0]}..{pinged[-1]}: are the VESCs powered "
            "and wired, the bus at their bit rate (VESC Tool: CAN Baud Rate, 500k from the "
            "factory), and their CAN mode VESC (the default)?"
        )
    return [
        FoundVesc(
            controller_id,
            hw_types[0],
            len(hw_types),
            frozenset(status.get(controller_id, ())),
        )
        for controller_id, hw_types in sorted(pongs.items())
    ]


def _take(
    bus: can.BusABC,
    timeout_s: float,
    host_id: int,
    pongs: dict[int, list[int]],
    status: dict[int, set[int]],
) -> None:
    """Read one frame (waiting up to ``timeout_s``): a PONG to us, or a VESC's status frame."""
    try:
        msg = bus.recv(timeout_s)
    except (can.CanError, OSError) as exc:
        raise LinkError(f"reading the bus failed: {exc}") from exc
    if msg is None:
        return
    try:
        frame = decode(msg)
    except FrameError:
        return  # another device's frame, or a malformed one: not an answer
    if frame is None:
        return
    packet = msg.arbitration_id >> 8
    message = frame.message
    if isinstance(message, Pong) and frame.controller_id == host_id:
        pongs.setdefault(message.controller_id, []).append(message.hw_type)
    elif packet in STATUS_PACKETS:
        status.setdefault(frame.controller_id, set()).add(packet)


def scan_warnings(found: Iterable[FoundVesc]) -> list[str]:
    """What is wrong with a bus of VESCs, one line each: a shared ID, status frames off, some of
    STATUS 1-5 missing."""
    wanted = {Packet.STATUS, Packet.STATUS_2, Packet.STATUS_3, Packet.STATUS_4, Packet.STATUS_5}
    warnings = []
    for vesc in found:
        where = f"VESC {vesc.controller_id}"
        if vesc.answers > 1:
            warnings.append(
                f"{where}: {vesc.answers} answers to one PING: VESCs that share an ID; give each "
                "its own (VESC Tool: App Settings > General > VESC ID)"
            )
        if vesc.hw_type != HwType.VESC:
            continue
        missing = sorted(wanted - vesc.status)
        if len(missing) == len(wanted):
            warnings.append(f"{where}: sends no status frames: {STATUS_ON_HINT}")
        elif missing:
            names = ", ".join(Packet(p).name for p in missing)
            warnings.append(f"{where}: sends no {names}: {STATUS_ON_HINT}")
    return warnings
