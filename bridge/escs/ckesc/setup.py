"""Setting up CKESC ESCs over any python-can bus: request, answer, check. No printing.

:class:`CkescClient` is the engine of ``esc-bridge esc``: it sends one request at a time from
the host and reads the bus until the matching answer arrives or its timeout passes, then checks
the answer. The wire is docs/protocols.md §3.5, §3.6 and every frame goes through the production
codec (:mod:`bridge.escs.ckesc.codec`), so values outside the protocol's range raise
:class:`~bridge.errors.ValueRangeError` before anything is sent.

A service response matches a request when it has the request's service type, is addressed to
the host, carries the request's transfer ID and comes from the addressed node. Broadcast
requests (GET_ESC_ID, MSGControl) are answered by every ESC (node_id % 32) x 2 ms later, so
the client waits out that window (64 ms) plus its timeout and keeps every answer.

Errors (see :mod:`bridge.errors`): :class:`~bridge.errors.NoAnswerError` (nothing in time; a
:class:`~bridge.errors.WrongNodeError` when another node answered instead),
:class:`~bridge.errors.RefusedError` (the ESC answered with values other than those asked),
:class:`~bridge.errors.SetupError` (a step that cannot be done as the bus stands),
:class:`~bridge.errors.LinkError` (the bus failed), :class:`~bridge.errors.ValueRangeError`.

Decisions where the spec is silent
----------------------------------
- **Refused.** An ESC that refuses a setting answers with the values in effect (the simulated
  ESC does; the seed says nothing): an answer that differs from the request is a refusal, and
  the error names what was asked, what is in effect and the condition the seed puts on it.
- **Set ID** reaches every ESC on the bus (its destination is ignored), so :meth:`set_id`
  asks GET_ESC_ID first and sends nothing unless exactly one ESC answers. Its response may
  come from the old or the new node ID (the simulated ESC answers from the new one).
- **Expand Set** has no response. :meth:`~CkescClient.expand` first asks the ESC for its
  information (so a missing ESC is an error, not silence), sends the command, then checks what
  Get Major Configuration shows of it (direction, LED colour, CAN or PWM+CAN interface);
  READ_TEMP_RECORD returns the four MSG_EXP12 records the ESC sends in answer.
- **MSGControl and CANTest are broadcasts**: every ESC on the bus acts on them. A ``node``
  only names the ESC whose acknowledgement (or CANTest reports) is required. CANTest "leave" is
  sent however the test ends. Lost frames are the counter's span minus the reports received.
- Frames already queued when a request goes out are dropped first (old answers, telemetry).
  A frame with the expected CAN ID that does not decode is remembered and named if no good
  answer follows; any other frame is skipped.
- Broadcast requests come from node 0, as the codec requires; service requests come from
  ``host_node`` (0 unless told) and their responses must be addressed to it.
"""

from __future__ import annotations

import math
from collections import Counter
from typing import Final, cast

import can

from bridge.errors import (
    LinkError,
    NoAnswerError,
    SetupError,
    ValueRangeError,
)
from bridge.escs import uavcan_v0
from bridge.escs.ckesc import codec, records
from bridge.escs.ckesc.keys import CkescKeys
from bridge.escs.ckesc.link import (
    NO_ANSWER_HELP,
    SET_ID_HELP,
    R,
    ServiceLink,
    check_node,
    nodes_text,
)
from bridge.escs.ckesc.results import (
    CanTestResult,
    ExpandResult,
    MaintenanceResponse,
    ReportsResult,
    ScannedEsc,
    SelfTestResult,
    SetIdResult,
    value_name,
)
from bridge.escs.family import EscSetup

__all__ = [
    "ANSWER_WINDOW_S",
    "DEFAULT_TIMEOUT_S",
    "LEARN_WINDOW_S",
    "SET_ID_WINDOW_S",
    "CkescClient",
    "learn_node_ids",
]

DEFAULT_TIMEOUT_S: Final = 0.5
"""How long a request waits for its answer."""
ANSWER_WINDOW_S: Final = 0.064
"""GET_ESC_ID answers and MSGControl acks come (node_id % 32) x 2 ms late: within 64 ms."""
LEARN_WINDOW_S: Final = 0.1
"""How long :func:`learn_node_ids` listens for the answers (all of them by 62 ms)."""
SET_ID_WINDOW_S: Final = 120
"""An ESC takes Set ID and Set Baud only this long after power-up (seed 4.3.2)."""
COUNTER_MODULUS: Final = 1 << 32
"""The CANTest counter is a u32 that wraps."""
_MAINTENANCE_RESPONSES: Final[dict[int, type[MaintenanceResponse]]] = {
    0: records.Maintenance0Response,
    1: records.Maintenance1Response,
    2: records.Maintenance2Response,
}

# What Get Major Configuration shows of an Expand Set: command -> part -> (field, value).
_EXPAND_EFFECTS: Final[dict[int, dict[int, tuple[str, object]]]] = {
    records.ExpandSetCommand.DIRECTION: {
        1: ("direction_reversed", False),
        2: ("direction_reversed", True),
    },
    records.ExpandSetCommand.LED: {
        0: ("led_color", records.LedColor(0)),
        1: ("led_color", records.LedColor.RED),
        2: ("led_color", records.LedColor.GREEN),
        3: ("led_color", records.LedColor.BLUE),
    },
    records.ExpandSetCommand.THROTTLE_INTERFACE: {
        2: ("throttle_source", records.ThrottleSource.PWM_AND_CAN),
        3: ("throttle_source", records.ThrottleSource.CAN),
    },
}


class CkescClient(ServiceLink):
    """Requests to CKESC ESCs on ``bus`` from the host, each answer awaited for ``timeout_s``.

    The bus stays the caller's (the client never shuts it down); use one client per bus, so
    that the transfer IDs count on.

    Raises:
        ValueError: ``timeout_s`` is not a number of seconds > 0.
        ValueRangeError: ``host_node`` outside 0..0x7D.
    """

    def __init__(
        self,
        bus: can.BusABC,
        *,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        host_node: int = records.HOST_NODE_ID,
    ) -> None:
        if not (0 < timeout_s < math.inf):
            raise ValueError(f"timeout_s={timeout_s!r}: expected a number of seconds > 0")
        if not (isinstance(host_node, int) and 0 <= host_node <= uavcan_v0.MAX_NODE_ID):
            raise ValueRangeError(f"host_node = {host_node!r} is not in 0..{uavcan_v0.MAX_NODE_ID}")
        self.bus = bus
        self.timeout_s = timeout_s
        self.host_node = host_node
        self._tids = uavcan_v0.TransferIds()

    # -- discovery --------------------------------------------------------------------------

    def find_escs(self, window_s: float | None = None) -> list[records.GetEscIdAnswer]:
        """Every GET_ESC_ID answer, in arrival order (an ID shared by two ESCs comes twice),
        read for ``window_s`` (default: :data:`ANSWER_WINDOW_S` and the timeout).

        Raises:
            LinkError: the bus failed.
        """
        request = self._broadcast(records.GetEscIdRequest())
        self._drain()
        self._send(request, "GET_ESC_ID")
        frames = self._collect(
            ANSWER_WINDOW_S + self.timeout_s if window_s is None else window_s,
            lambda frame: isinstance(frame.message, records.GetEscIdAnswer),
        )
        return [
            frame.message for frame in frames if isinstance(frame.message, records.GetEscIdAnswer)
        ]

    def scan(self) -> list[ScannedEsc]:
        """Every ESC on the bus (GET_ESC_ID) with its information and major configuration,
        sorted by node ID; an ESC that does not answer those keeps a ``problem``. An empty list
        when no ESC answered.

        Raises:
            LinkError: the bus failed.
        """
        answers = self.find_escs()
        count = Counter(answer.node_id for answer in answers)
        escs = []
        for answer in sorted(answers, key=lambda a: (a.node_id, a.throttle_channel)):
            node, channel = answer.node_id, answer.throttle_channel
            if count[node] > 1:
                problem = f"{count[node]} ESCs answer as node {node}: not asked for details"
                escs.append(ScannedEsc(node, channel, problem=problem))
                continue
            info: records.EscInfoResponse | None = None
            config: records.MajorConfigResponse | None = None
            try:
                info = self.info(node)
                config = self.major_config(node)
            except NoAnswerError as exc:
                escs.append(ScannedEsc(node, channel, info, config, problem=str(exc)))
                continue
            escs.append(ScannedEsc(node, channel, info, config))
        return escs

    # -- the services -----------------------------------------------------------------------

    def request(
        self,
        node_id: int,
        message: records.CkescMessage,
        response_type: type[R] | tuple[type[R], ...],
    ) -> R:
        """Send the service request ``message`` to ``node_id``; its checked response.

        Raises:
            ValueRangeError: a value outside the protocol's range (nothing was sent).
            NoAnswerError: no response within the timeout (WrongNodeError: from another node).
            LinkError: the bus failed.
        """
        msg, transfer_id = self._service_frame(node_id, message)
        return self._ask(msg, transfer_id, node_id, (node_id,), response_type)

    def set_id(self, node_id: int, throttle_channel: int) -> SetIdResult:
        """Give the only ESC on the bus ``node_id`` and ``throttle_channel`` (saved in flash).

        Raises:
            ValueRangeError: node_id outside 1..0x7D or channel outside 1..20 (nothing sent).
            NoAnswerError: no ESC answers GET_ESC_ID, or the ESC does not answer Set ID.
            SetupError: several ESCs answer GET_ESC_ID (Set ID is then not sent).
            RefusedError: the ESC answers with other values (outside its 120 s window).
            LinkError: the bus failed.
        """
        request = records.SetIdRequest(node_id, throttle_channel)
        # The values are checked before the scan puts anything on the bus.
        codec.encode(codec.CkescFrame(0, self.host_node, records.FACTORY_NODE_ID, 0, request))
        answers = self.find_escs()
        if not answers:
            window = ANSWER_WINDOW_S + self.timeout_s
            raise NoAnswerError(
                f"no ESC answered GET_ESC_ID within {window:.3g} s, so Set ID was not sent; "
                f"{NO_ANSWER_HELP} Note: {SET_ID_HELP}"
            )
        if len(answers) > 1:
            listed = nodes_text(answer.node_id for answer in answers)
            raise SetupError(
                f"{len(answers)} ESCs answered GET_ESC_ID (nodes {listed}): Set ID reaches "
                "every ESC on the bus, so it was not sent; connect only the ESC to set up"
            )
        old = answers[0]
        msg, transfer_id = self._service_frame(old.node_id, request)
        try:
            response = self._ask(
                msg, transfer_id, old.node_id, {old.node_id, node_id}, records.SetIdResponse
            )
        except NoAnswerError as exc:
            raise type(exc)(f"{exc}; {SET_ID_HELP}") from None
        got = (response.node_id, response.throttle_channel)
        if got != (node_id, throttle_channel):
            self._refused(
                records.SERVICE_SET_ID,
                old.node_id,
                f"node {node_id} channel {throttle_channel}",
                f"node {got[0]} channel {got[1]}",
            )
        return SetIdResult(old.node_id, old.throttle_channel, node_id, throttle_channel)

    def set_baud(self, node_id: int, bitrate: int) -> int:
        """Set the ESC's CAN bit rate (bit/s, one of :data:`~bridge.escs.ckesc.BAUD_RATES_BPS`),
        in effect from its next power-up; the bit rate set.

        Raises:
            ValueRangeError: a bit rate the ESC does not have (nothing sent).
            RefusedError: the ESC keeps another (outside its 120 s window).
            NoAnswerError, LinkError: as :meth:`request`.
        """
        rates = records.BAUD_RATES_BPS
        if bitrate not in rates:
            raise ValueRangeError(
                f"bitrate = {bitrate!r} is not one of {', '.join(map(str, rates))}"
            )
        response = self.request(
            node_id, records.SetBaudRequest(rates.index(bitrate)), records.SetBaudResponse
        )
        if response.baud_code != rates.index(bitrate):
            kept = (
                f"{rates[response.baud_code]} bit/s"
                if response.baud_code < len(rates)
                else f"code {response.baud_code}"
            )
            self._refused(records.SERVICE_SET_BAUD, node_id, f"{bitrate} bit/s", kept)
        return bitrate

    def set_led(
        self, node_id: int, color: records.LedColor, blink_hz: int = 0, *, save: bool = False
    ) -> records.SetLed:
        """Set the LED (colour bits, blink 0/1/2/5 Hz), saved as the default with ``save``.

        Raises:
            ValueRangeError: colour outside 0..7 or another blink rate (nothing sent).
            RefusedError: the ESC shows another (its reports are paused).
            NoAnswerError, LinkError: as :meth:`request`.
        """
        asked = records.SetLedRequest(save, color, blink_hz)
        response = self.request(node_id, asked, records.SetLedResponse)
        if (response.color, response.blink_hz) != (asked.color, asked.blink_hz):
            self._refused(
                records.SERVICE_SET_LED,
                node_id,
                f"{value_name(asked.color)} blink {asked.blink_hz} Hz",
                f"{value_name(response.color)} blink {response.blink_hz} Hz",
            )
        return response

    def rotation(
        self, node_id: int, rotation: records.Rotation | None = None
    ) -> records.Rotation | int:
        """Set the motor direction (saved in flash), or with None ask for it; the direction.

        Raises:
            RefusedError: the ESC keeps the other (motor running or reports paused).
            ValueRangeError, NoAnswerError, LinkError: as :meth:`request`.
        """
        asked = records.Rotation.QUERY if rotation is None else rotation
        response = self.request(
            node_id, records.SetRotationRequest(asked), records.SetRotationResponse
        )
        if rotation is not None and response.rotation != rotation:
            self._refused(
                records.SERVICE_SET_ROTATION,
                node_id,
                value_name(rotation),
                value_name(response.rotation),
            )
        return response.rotation

    def report_intervals(
        self,
        node_id: int,
        msg1_ms: int | None = None,
        msg2_ms: int | None = None,
        msg3_ms: int | None = None,
    ) -> records.SetFreq:
        """Read the MSG1/2/3 report intervals, or write those given (20..500 ms, even; the
        others are read first and kept); the intervals in use.

        Raises:
            ValueRangeError: an interval outside 20..500 ms or odd (nothing sent).
            RefusedError: the ESC keeps other intervals.
            NoAnswerError, LinkError: as :meth:`request`.
        """
        given = (msg1_ms, msg2_ms, msg3_ms)
        read = records.SetFreqRequest(False, 0, 0, 0)
        if all(ms is None for ms in given):
            return self.request(node_id, read, records.SetFreqResponse)
        # Check the values given before anything is sent (20 ms stands in for the others).
        m1, m2, m3 = (20 if ms is None else ms for ms in given)
        self._service_frame(node_id, records.SetFreqRequest(True, m1, m2, m3))
        if any(ms is None for ms in given):
            now = self.request(node_id, read, records.SetFreqResponse)
            m1 = now.msg1_interval_ms if msg1_ms is None else msg1_ms
            m2 = now.msg2_interval_ms if msg2_ms is None else msg2_ms
            m3 = now.msg3_interval_ms if msg3_ms is None else msg3_ms
        response = self.request(
            node_id, records.SetFreqRequest(True, m1, m2, m3), records.SetFreqResponse
        )
        got = (response.msg1_interval_ms, response.msg2_interval_ms, response.msg3_interval_ms)
        if got != (m1, m2, m3):
            self._refused(
                records.SERVICE_SET_FREQ,
                node_id,
                f"intervals {m1}/{m2}/{m3} ms",
                "{}/{}/{} ms".format(*got),
            )
        return response

    def throttle_source(
        self, node_id: int, source: records.ThrottleSource | None = None
    ) -> records.ThrottleSource | int:
        """Set where the ESC takes its throttle from (saved in flash), or with None read it
        (Get Major Configuration); the source in use.

        Raises:
            RefusedError: the ESC keeps the other (throttle not zero).
            ValueRangeError, NoAnswerError, LinkError: as :meth:`request`.
        """
        if source is None:
            return self.major_config(node_id).throttle_source
        response = self.request(
            node_id, records.ThrottleSelectRequest(source), records.ThrottleSelectResponse
        )
        if response.source != source:
            self._refused(
                records.SERVICE_THROTTLE_SELECT,
                node_id,
                value_name(source),
                value_name(response.source),
            )
        return response.source

    def self_test(self, node_id: int) -> SelfTestResult:
        """The power-on self-test's result; for a failure, the fault code as well.

        Raises:
            ValueRangeError, NoAnswerError, LinkError: as :meth:`request`.
        """
        response = self.request(node_id, records.SelfTestRequest(), records.SelfTestResponse)
        if response.passed:
            return SelfTestResult(node_id, True)
        try:
            counters = self.maintenance(node_id, 2)
        except NoAnswerError:
            return SelfTestResult(node_id, False)
        fault = (
            counters.self_test_fault if isinstance(counters, records.Maintenance2Response) else None
        )
        return SelfTestResult(node_id, False, fault)

    def info(self, node_id: int) -> records.EscInfoResponse:
        """ESC Information (240): cells, current rating, versions, firmware date.

        Raises:
            ValueRangeError, NoAnswerError, LinkError: as :meth:`request`.
        """
        return self.request(node_id, records.EscInfoRequest(), records.EscInfoResponse)

    def maintenance(self, node_id: int, option: int) -> MaintenanceResponse:
        """Maintenance Information (241), option 0 (lifetime), 1 (this run) or 2 (counters).

        Raises:
            ValueRangeError: option outside 0..2 (nothing sent).
            NoAnswerError, LinkError: as :meth:`request`; an answer for another option counts
                as none.
        """
        message = records.MaintenanceRequest(option)
        msg, transfer_id = self._service_frame(node_id, message)
        expected = _MAINTENANCE_RESPONSES[option]
        response = self._ask(msg, transfer_id, node_id, (node_id,), expected)
        return cast(MaintenanceResponse, response)

    def major_config(self, node_id: int) -> records.MajorConfigResponse:
        """Get Major Configuration (242): direction, throttle source and channel, LED, intervals.

        Raises:
            ValueRangeError, NoAnswerError, LinkError: as :meth:`request`.
        """
        return self.request(node_id, records.MajorConfigRequest(), records.MajorConfigResponse)

    def expand(self, node_id: int, command: records.ExpandSetCommand, part: int) -> ExpandResult:
        """Send one Expand Set command (no response: the motor beeps) and check what can be
        checked (see the module docstring).

        Raises:
            ValueRangeError: an unknown command or a part outside its table (nothing sent).
            NoAnswerError: the ESC does not answer ESC Information (Expand Set is then not
                sent), or sends no temperature record for READ_TEMP_RECORD.
            RefusedError: Get Major Configuration does not show the new setting.
            LinkError: the bus failed.
        """
        msg, _ = self._service_frame(node_id, records.ExpandSetRequest(command, part))
        command = records.ExpandSetCommand(command)
        try:
            self.info(node_id)
        except NoAnswerError as exc:
            raise type(exc)(f"{exc}; Expand Set (which has no answer) was not sent") from None
        self._drain()
        self._send(msg, f"Expand Set {command.name} to node {node_id}")
        if command == records.ExpandSetCommand.READ_TEMP_RECORD:
            temp_records = self._temp_records(node_id)
            return ExpandResult(node_id, command, part, True, temp_records)
        effect = _EXPAND_EFFECTS.get(command, {}).get(part)
        if effect is None:
            return ExpandResult(node_id, command, part, None)
        field, value = effect
        shown = getattr(self.major_config(node_id), field)
        if shown != value:
            what = field.replace("_", " ")
            self._refused(
                records.SERVICE_EXPAND_SET,
                node_id,
                f"{value_name(command)} {part} ({what} {value_name(value)})",
                f"{what} {value_name(shown)} (Get Major Configuration)",
            )
        return ExpandResult(node_id, command, part, True)

    # -- broadcasts -------------------------------------------------------------------------

    def reports(
        self, command: records.MsgControlCommand, node_id: int | None = None
    ) -> ReportsResult:
        """MSGControl to every ESC: PAUSE, RESUME_MSG or RESUME_EXP; the nodes that acked.

        Raises:
            ValueRangeError: another command, or node_id outside 1..0x7D (nothing sent).
            NoAnswerError: no ESC acked (with ``node_id``: that one did not).
            LinkError: the bus failed.
        """
        if node_id is not None:
            check_node(node_id)
        request = self._broadcast(records.MsgControlRequest(command))
        what = f"MSGControl {records.MsgControlCommand(command).name}"
        self._drain()
        self._send(request, what)
        window = ANSWER_WINDOW_S + self.timeout_s
        frames = self._collect(
            window,
            lambda frame: (
                isinstance(frame.message, records.MsgControlAck)
                and frame.message.command == records.MsgControlCommand.ACK
            ),
        )
        acked = tuple(sorted({frame.source_node for frame in frames}))
        others = f"; acknowledged by node(s) {nodes_text(acked)}" if acked else ""
        if node_id is not None and node_id not in acked:
            raise NoAnswerError(
                f"node {node_id} did not acknowledge {what} within {window:g} s{others}; "
                + NO_ANSWER_HELP
            )
        if not acked:
            raise NoAnswerError(f"no ESC acknowledged {what} within {window:g} s; {NO_ANSWER_HELP}")
        return ReportsResult(records.MsgControlCommand(command), acked)

    def can_test(self, duration_s: float, node_id: int | None = None) -> list[CanTestResult]:
        """Put every ESC in CANTest mode for ``duration_s``, count each one's reports against
        their counter, then end the mode (always); per node, sorted (only ``node_id`` if given).

        Raises:
            ValueRangeError: duration not > 0 s, or node_id outside 1..0x7D (nothing sent).
            NoAnswerError: no reports (with ``node_id``: none from that node).
            LinkError: the bus failed.
        """
        if not (isinstance(duration_s, int | float) and 0 < duration_s < math.inf):
            raise ValueRangeError(f"duration = {duration_s!r} s is not a time > 0")
        if node_id is not None:
            check_node(node_id)
        enter = self._broadcast(records.CanTestRequest(records.CanTestOption.ENTER))
        leave = self._broadcast(records.CanTestRequest(records.CanTestOption.LEAVE))
        self._drain()
        self._send(enter, "CANTest enter")
        try:
            frames = self._collect(
                duration_s, lambda frame: isinstance(frame.message, records.CanTestReport)
            )
        finally:
            self._send(leave, "CANTest leave")
        counts: dict[int, list[int]] = {}
        for frame in frames:
            if isinstance(frame.message, records.CanTestReport):
                counts.setdefault(frame.source_node, []).append(frame.message.count)
        results = [
            CanTestResult(node, len(seen), seen[0], seen[-1], duration_s)
            for node, seen in sorted(counts.items())
            if node_id is None or node == node_id
        ]
        if not results:
            whose = "no ESC" if node_id is None else f"node {node_id}"
            heard = f" (reports came from node(s) {nodes_text(counts)})" if counts else ""
            raise NoAnswerError(
                f"{whose} sent CANTest reports within {duration_s:g} s{heard}; {NO_ANSWER_HELP}"
            )
        return results


def learn_node_ids(
    bus: can.BusABC, setup: EscSetup[CkescKeys], window_s: float = LEARN_WINDOW_S
) -> dict[int, int]:
    """Ask every CKESC on ``bus`` for its node ID (GET_ESC_ID) and map motors to node IDs:
    ``{i: node_id}`` for each answering ESC that follows output i's throttle channel
    (``setup.channels``).

    Raises:
        LinkError: two ESCs answer with the same throttle channel (they would spin together),
            or the bus failed.
    """
    channels = setup.channels or setup.keys.ckesc_channels
    found: dict[int, int] = {}
    for answer in CkescClient(bus, timeout_s=window_s).find_escs(window_s):
        if answer.throttle_channel not in channels:
            continue
        other = found.get(answer.throttle_channel)
        if other is not None and other != answer.node_id:
            raise LinkError(
                f"CKESC nodes {other} and {answer.node_id} both follow throttle channel "
                f"{answer.throttle_channel}; give each ESC its own channel (Set ID)"
            )
        found[answer.throttle_channel] = answer.node_id
    return {i: found[channel] for i, channel in enumerate(channels) if channel in found}
