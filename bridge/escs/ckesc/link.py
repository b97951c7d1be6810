"""The CKESC set-up client's wire (:class:`ServiceLink`): requests encoded and sent, answers
matched by service type, transfer ID and node, broadcasts collected, the bus read and written
with its failures as :class:`~bridge.errors.LinkError`; and the conditions a refusal names."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Collection, Iterable
from typing import Final, TypeVar

import can

from bridge.errors import (
    CodecError,
    LinkError,
    NoAnswerError,
    RefusedError,
    ValueRangeError,
    WrongNodeError,
)
from bridge.escs import uavcan_v0
from bridge.escs.ckesc import codec, records
from bridge.escs.ckesc.results import SERVICE_NAMES

_DRAIN_LIMIT: Final = 100_000
"""At most this many queued frames are dropped before a request (a flooded bus never ends)."""

SET_ID_HELP: Final = (
    "an ESC takes Set ID only within 120 s of its power-up and only while no other ESC is "
    "on the bus: connect this ESC alone, switch its power off and on, and run set-id within "
    "2 minutes"
)
_CONDITIONS: Final[dict[int, str]] = {
    records.SERVICE_SET_ID: SET_ID_HELP,
    records.SERVICE_SET_BAUD: "an ESC takes Set Baud only within 120 s of its power-up: switch "
    "its power off and on and set the bit rate within 2 minutes",
    records.SERVICE_SET_LED: "an ESC takes Set LED only while its reports are on "
    "(MSGControl resume)",
    records.SERVICE_SET_ROTATION: "an ESC takes Set Rotation only with the motor stopped and its "
    "reports on (MSGControl resume)",
    records.SERVICE_SET_FREQ: "intervals must be 20..500 ms, even",
    records.SERVICE_THROTTLE_SELECT: "an ESC takes Throttle Select only at zero throttle",
    records.SERVICE_EXPAND_SET: "an ESC takes Expand Set only with the motor stopped, and may "
    "not support every part",
}
NO_ANSWER_HELP: Final = (
    "is the ESC powered and wired (CAN H/L, 120 ohm at both ends), and does the bus run at the "
    "ESC's bit rate (500 kbit/s from the factory)?"
)

_TEMP_RECORDS: Final = 4
"""READ_TEMP_RECORD: the ESC sends MCU, MOS, capacitor and motor records."""


R = TypeVar("R")


def check_node(node_id: object) -> int:
    if isinstance(node_id, int) and 1 <= node_id <= uavcan_v0.MAX_NODE_ID:
        return node_id
    raise ValueRangeError(
        f"node = {node_id!r} is not in 1..{uavcan_v0.MAX_NODE_ID} (0 is the host, "
        f"{uavcan_v0.MAX_NODE_ID + 1} and {uavcan_v0.MAX_NODE_ID + 2} are reserved)"
    )


def _service_label(service_type: int) -> str:
    return f"{SERVICE_NAMES.get(service_type, 'service')} ({service_type})"


def nodes_text(nodes: Iterable[int]) -> str:
    return ", ".join(map(str, sorted(nodes)))


log = logging.getLogger(__name__)


class ServiceLink:
    """The requests and answers under :class:`~bridge.escs.ckesc.setup.CkescClient`, which
    sets these attributes."""

    bus: can.BusABC
    timeout_s: float
    host_node: int
    _tids: uavcan_v0.TransferIds

    # -- the wire ---------------------------------------------------------------------------

    def _service_frame(
        self, node_id: int, message: records.CkescMessage
    ) -> tuple[can.Message, int]:
        """``message`` to ``node_id``, encoded (checked) with the next transfer ID of its type."""
        check_node(node_id)
        transfer_id = self._tids.next(codec.type_id_of(message))
        frame = codec.CkescFrame(
            codec.default_priority(message), self.host_node, node_id, transfer_id, message
        )
        return codec.encode(frame), transfer_id

    def _broadcast(self, message: records.CkescMessage) -> can.Message:
        """A host broadcast (from node 0, as the codec requires), encoded."""
        transfer_id = self._tids.next(codec.type_id_of(message))
        frame = codec.CkescFrame(
            codec.default_priority(message), records.HOST_NODE_ID, None, transfer_id, message
        )
        return codec.encode(frame)

    def _ask(
        self,
        msg: can.Message,
        transfer_id: int,
        node_id: int,
        sources: Collection[int],
        response_type: type[R] | tuple[type[R], ...],
    ) -> R:
        """Send the request ``msg`` to ``node_id`` and wait for its response from one of
        ``sources``."""
        service_type = msg.arbitration_id >> 16 & 0xFF
        label = _service_label(service_type)
        # A response's CAN ID but for its priority and source.
        wanted = service_type << 16 | self.host_node << 8 | 0x80
        self._drain()
        self._send(msg, f"{label} request to node {node_id}")
        deadline = time.monotonic() + self.timeout_s
        others: set[int] = set()
        problems: list[str] = []
        while (left := deadline - time.monotonic()) > 0:
            reply = self._recv(left)
            if reply is None:
                break
            can_id = reply.arbitration_id
            if not reply.is_extended_id or can_id & 0x00FFFF80 != wanted:
                continue
            source = can_id & 0x7F
            try:
                frame = codec.decode(reply)
            except CodecError as exc:
                problems.append(f"a malformed answer from node {source} ({exc})")
                continue
            if frame is None or frame.transfer_id != transfer_id:
                continue  # an answer to an earlier request
            if source not in sources:
                others.add(source)
            elif isinstance(frame.message, response_type):
                return frame.message
            else:
                problems.append(
                    f"node {source} answered with {type(frame.message).__name__} instead"
                )
        text = f"node {node_id} did not answer {label} within {self.timeout_s:g} s"
        if problems:
            text += "; " + "; ".join(problems)
        if others:
            raise WrongNodeError(
                f"{text}; node(s) {nodes_text(others)} answered it instead: a wrong node ID, or "
                "two ESCs on one ID?"
            )
        raise NoAnswerError(f"{text}; {NO_ANSWER_HELP}")

    def _refused(self, service_type: int, node_id: int, asked: str, kept: str) -> None:
        condition = _CONDITIONS.get(service_type, "")
        raise RefusedError(
            f"node {node_id} refused {_service_label(service_type)}: asked {asked}, in effect "
            f"{kept}" + (f"; {condition}" if condition else "")
        )

    def _temp_records(self, node_id: int) -> tuple[records.MsgExp12, ...]:
        frames = self._collect(
            self.timeout_s,
            lambda frame: (
                isinstance(frame.message, records.MsgExp12) and frame.source_node == node_id
            ),
            until=_TEMP_RECORDS,
        )
        found = tuple(
            frame.message for frame in frames if isinstance(frame.message, records.MsgExp12)
        )
        if not found:
            raise NoAnswerError(
                f"node {node_id} sent no temperature record (MSG_EXP12) within "
                f"{self.timeout_s:g} s of Expand Set READ_TEMP_RECORD"
            )
        return found

    def _collect(
        self,
        window_s: float,
        accept: Callable[[codec.CkescFrame], bool],
        until: int | None = None,
    ) -> list[codec.CkescFrame]:
        """The ESC frames (source node not 0) ``accept`` takes, read for ``window_s`` (or
        until there are ``until`` of them)."""
        deadline = time.monotonic() + window_s
        out: list[codec.CkescFrame] = []
        while (left := deadline - time.monotonic()) > 0:
            msg = self._recv(left)
            if msg is None:
                break
            try:
                frame = codec.decode(msg)
            except CodecError:
                continue
            if frame is not None and frame.source_node != records.HOST_NODE_ID and accept(frame):
                out.append(frame)
                if until is not None and len(out) >= until:
                    break
        return out

    def _drain(self) -> None:
        for _ in range(_DRAIN_LIMIT):
            if self._recv(0.0) is None:
                return

    def _send(self, msg: can.Message, what: str) -> None:
        try:
            self.bus.send(msg, timeout=self.timeout_s)
        except (can.CanError, OSError) as exc:
            raise LinkError(f"cannot send {what} on the CAN bus: {exc}") from exc
        log.debug("sent %s: %08X %s", what, msg.arbitration_id, msg.data.hex(" "))

    def _recv(self, timeout_s: float) -> can.Message | None:
        try:
            msg: can.Message | None = self.bus.recv(timeout_s)
        except (can.CanError, OSError) as exc:
            raise LinkError(f"cannot read the CAN bus: {exc}") from exc
        return msg
