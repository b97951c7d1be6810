"""The link's heartbeat thread: the bridge's own HEARTBEAT, and the autopilot's streams watched
and negotiated.

Once per ``heartbeat_hz`` period it sends the bridge's HEARTBEAT (MAV_TYPE_ONBOARD_CONTROLLER)
to every connection. Once a second it notices a stopped output stream, measures the arrival
rates of the autopilot's outputs and HEARTBEATs, and asks the autopilot for the rates it should
send them at (MAV_CMD_SET_MESSAGE_INTERVAL on the autopilot's connection only; the negotiation
itself is :class:`bridge.mavlink.streams.StreamRequest`'s). The output rate is logged when it
first settles or moves, and loudly when it is too slow for the control loop to arm on.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from types import ModuleType
from typing import Any, Final

from bridge.config import MavlinkConfig
from bridge.mavlink.stats import LinkStats
from bridge.mavlink.streams import StreamRequest, result_name

__all__ = ["Heartbeat"]

log = logging.getLogger(__name__)

_REQUEST_PERIOD_NS: Final = 1_000_000_000  # check the streams (and ask) this often
_HEARD_NS: Final = 3_000_000_000  # the autopilot is there: a HEARTBEAT within this (3 missed)
_RATE_WINDOW_NS: Final = 1_000_000_000  # the arrival rate is measured over about this long
_RATE_LOG_CHANGE: Final = 0.2  # log the arrival rate again when it moves by this fraction


class Heartbeat:
    """The bridge's HEARTBEAT and the autopilot's stream rates, for one link.

    ``mav`` and ``dialect``: the link's codec (to build messages) and dialect. ``output_name``:
    the motor-output message obeyed. ``stats``: the link's counters, whose ``outputs``,
    ``output_rate_hz``, ``last_output_ns`` and ``last_heartbeat_ns`` this keeps.
    ``needed_rate_hz``: the slowest output stream the control loop arms on (0: no limit).
    ``send_all`` sends a message to every connection; ``send_autopilot`` to the autopilot's
    only. The reader thread calls the ``on_*`` and ``note_*`` methods, :meth:`run` is the
    heartbeat thread.
    """

    def __init__(
        self,
        config: MavlinkConfig,
        mav: Any,
        dialect: ModuleType,
        output_name: str,
        stats: LinkStats,
        needed_rate_hz: float,
        send_all: Callable[[Any], None],
        send_autopilot: Callable[[Any], None],
    ) -> None:
        self._config = config
        self._mav = mav
        self._dialect = dialect
        self._autopilot = (config.autopilot_system_id, config.autopilot_component_id)
        self._output_name = output_name
        self._output_msg_id: int = getattr(dialect, f"MAVLINK_MSG_ID_{output_name}")
        self._stats = stats
        self._needed_rate_hz = needed_rate_hz
        self._send_all = send_all
        self._send_autopilot = send_autopilot
        # Arrival-rate window, owned by the autopilot's reader thread.
        self._window_start_ns: int | None = None  # the note the rate window starts at
        self._window_count = 0  # outputs noted after it
        self._outputs_noted = 0  # the last total given to note_outputs
        self._logged_rate_hz = 0.0
        self._slow_logged = False
        # The rates asked of the autopilot (MAV_CMD_SET_MESSAGE_INTERVAL): its outputs, and
        # its HEARTBEAT, which carries the arming state. One request goes out per check, so
        # a COMMAND_ACK (which does not say for which message) answers the newest request.
        autopilot = f"autopilot {self._autopilot[0]}/{self._autopilot[1]}"
        self._output_request = StreamRequest(output_name, autopilot, config.stream_rate_hz)
        self._heartbeat_request = StreamRequest(
            "HEARTBEAT", autopilot, config.autopilot_heartbeat_hz, gave_up_level=logging.WARNING
        )
        self._pending_request: StreamRequest | None = None
        self._asked_hz: dict[str, float] = {}  # the rate last asked, per message: log changes
        self._heartbeats = 0  # the autopilot's HEARTBEATs, for their arriving rate
        self._heartbeats_checked = (0, 0)  # (count, monotonic ns) at the previous check
        self._autopilot_type: int | None = None

    @property
    def autopilot_type(self) -> int | None:
        """MAV_AUTOPILOT from the obeyed autopilot's latest HEARTBEAT; None before the first."""
        return self._autopilot_type

    def on_heartbeat(self, autopilot_type: int, now: int) -> None:
        """A HEARTBEAT from the obeyed autopilot, received at ``now`` (monotonic ns)."""
        self._stats.last_heartbeat_ns = now
        self._heartbeats += 1
        self._autopilot_type = autopilot_type

    def on_ack(self, msg: Any) -> None:
        """A COMMAND_ACK on the autopilot's connection: the answer to a stream request when it
        comes from the autopilot, is for MAV_CMD_SET_MESSAGE_INTERVAL and names us (or no one:
        MAVLink 1 has no target fields)."""
        if (msg.get_srcSystem(), msg.get_srcComponent()) != self._autopilot:
            return
        if msg.command != self._dialect.MAV_CMD_SET_MESSAGE_INTERVAL:
            return
        target = (getattr(msg, "target_system", 0), getattr(msg, "target_component", 0))
        if target[0] and target != (self._mav.srcSystem, self._config.component_id):
            return  # the answer to another component's request (a GCS's, forwarded)
        request = self._pending_request
        if request is None:
            log.info("autopilot answered %s to no request of ours", result_name(msg.result))
            return
        request.on_ack(msg.result)

    def note_outputs(self, total: int, now_ns: int) -> None:
        """Output messages counted by whoever reads them: ``total`` since start, as of
        ``now_ns``."""
        new = total - self._outputs_noted
        self._outputs_noted = total
        if new > 0:
            self.note_output(now_ns, new)

    def note_output(self, now: int, count: int = 1) -> None:
        """Count outputs and update the arrival-rate estimate."""
        stats = self._stats
        stats.outputs += count
        # The rate is the outputs noted after the window's first note over the time since it:
        # an output noted at the first note arrived before it. (Counted in batches, as the
        # control loop reports them, a count paired with the wrong span was off by a whole
        # batch: a 10 Hz stream read as 11 Hz when one report came late.)
        start = self._window_start_ns
        if start is None or now - stats.last_output_ns > _RATE_WINDOW_NS:
            self._window_start_ns, self._window_count = now, 0
        else:
            self._window_count += count
            elapsed = now - start
            if elapsed >= _RATE_WINDOW_NS:
                rate = self._window_count * 1e9 / elapsed
                stats.output_rate_hz = rate
                self._window_start_ns, self._window_count = now, 0
                self._log_rate(rate)
        stats.last_output_ns = now

    def _log_rate(self, rate_hz: float) -> None:
        """Say the arriving rate when it first settles or moves, and loudly when it is too
        slow for the control loop to arm on."""
        logged = self._logged_rate_hz
        if logged == 0 or abs(rate_hz - logged) > _RATE_LOG_CHANGE * logged:
            self._logged_rate_hz = rate_hz
            asked = self._output_request.asked_hz
            log.info(
                "%s from %d/%d arriving at %.0f Hz (%s)",
                self._output_name,
                *self._autopilot,
                rate_hz,
                f"asked for {asked:.0f} Hz" if asked else "not asked for a rate",
            )
        slow = rate_hz < self._needed_rate_hz
        if slow and not self._slow_logged:
            log.warning(
                "%s from %d/%d arrives at %.0f Hz, too slow for input_timeout_ms (it needs "
                "%.0f Hz or more): the motors will not arm on it; %s "
                "(docs/troubleshooting.md)",
                self._output_name,
                *self._autopilot,
                rate_hz,
                self._needed_rate_hz,
                "the autopilot did not take the rate asked for: set the stream's rate in the "
                "autopilot (ArduPilot SRn_ parameters, PX4 MAV_n_RATE), or a slower stream needs "
                "a larger [output] input_timeout_ms"
                if self._output_request.asked_hz
                else "[mavlink] stream_rate_hz is 0: give it a rate to ask the autopilot for, or "
                "set the stream's rate in the autopilot",
            )
        self._slow_logged = slow

    def run(self, stop: threading.Event) -> None:
        """The heartbeat thread's body, until ``stop`` is set."""
        beat_period_ns = round(1e9 / self._config.heartbeat_hz)
        next_beat = next_check = time.monotonic_ns()
        while True:
            now = time.monotonic_ns()
            if now >= next_beat:
                self._send_all(
                    self._mav.heartbeat_encode(
                        self._dialect.MAV_TYPE_ONBOARD_CONTROLLER,
                        self._dialect.MAV_AUTOPILOT_INVALID,
                        0,
                        0,
                        self._dialect.MAV_STATE_ACTIVE,
                    )
                )
                next_beat = max(next_beat + beat_period_ns, now)
            if now >= next_check:
                self._check_stream(now)
                next_check = max(next_check + _REQUEST_PERIOD_NS, now)
            if stop.wait(max(0, min(next_beat, next_check) - time.monotonic_ns()) / 1e9):
                return

    def _check_stream(self, now: int) -> None:
        """Once a second: notice a stopped stream, and negotiate the rates of the autopilot's
        outputs and HEARTBEAT (:class:`~bridge.mavlink.streams.StreamRequest`)."""
        stats = self._stats
        last = stats.last_output_ns
        if not (last and now - last <= _REQUEST_PERIOD_NS):
            if stats.output_rate_hz > 0:
                log.warning(
                    "no %s from %d/%d for %.1f s",
                    self._output_name,
                    *self._autopilot,
                    (now - last) / 1e9,
                )
            stats.output_rate_hz = 0.0
            self._logged_rate_hz = 0.0
        counted, since_ns = self._heartbeats_checked
        heartbeats = self._heartbeats
        self._heartbeats_checked = (heartbeats, now)
        heartbeat_hz = (heartbeats - counted) * 1e9 / (now - since_ns) if since_ns else 0.0
        heard = stats.last_heartbeat_ns != 0 and now - stats.last_heartbeat_ns <= _HEARD_NS
        streams = [
            (self._output_request, self._output_msg_id, stats.output_rate_hz),
            (self._heartbeat_request, self._dialect.MAVLINK_MSG_ID_HEARTBEAT, heartbeat_hz),
        ]
        if self._pending_request is self._output_request:
            streams.reverse()  # take turns, so that neither starves the other
        for request, _, arriving_hz in streams:
            request.observe(arriving_hz)
        for request, msg_id, arriving_hz in streams:
            rate_hz = request.due(arriving_hz, heard)
            if rate_hz is not None:
                self._ask_rate(request, msg_id, rate_hz)
                return  # one request per check: the next ACK is its answer

    def _ask_rate(self, request: StreamRequest, msg_id: int, rate_hz: float) -> None:
        """Send MAV_CMD_SET_MESSAGE_INTERVAL for ``msg_id`` at ``rate_hz`` to the autopilot."""
        log.log(
            logging.DEBUG if self._asked_hz.get(request.name) == rate_hz else logging.INFO,
            "asking %d/%d for %s at %.0f Hz (MAV_CMD_SET_MESSAGE_INTERVAL)",
            *self._autopilot,
            request.name,
            rate_hz,
        )
        self._asked_hz[request.name] = rate_hz
        self._pending_request = request
        # To the autopilot only: a GCS on an output has no use for it.
        self._send_autopilot(
            self._mav.command_long_encode(
                *self._autopilot,
                self._dialect.MAV_CMD_SET_MESSAGE_INTERVAL,
                0,
                float(msg_id),
                float(round(1e6 / rate_hz)),  # interval in µs
                0,
                0,
                0,
                0,
                0,  # param7 0: the flight stack's default target (us, the requester)
            )
        )
