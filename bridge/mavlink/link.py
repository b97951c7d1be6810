"""The MAVLink edge: the autopilot's motor outputs and arming state in; the bridge's HEARTBEAT,
STATUSTEXT and ESC telemetry out, to the autopilot and to any extra outputs (a GCS).

The only module besides the dialect and :mod:`bridge.mavlink.telemetry_out` that touches
pymavlink. A :class:`MavlinkLink` opens one connection to the autopilot plus one per
``[mavlink] outputs`` entry, and runs named daemon threads:

* one reader per connection. On the autopilot's connection it decodes the configured output
  message into a :data:`INPUT_VECTOR_LEN`-vector (``ch1..ch32, roll, pitch, yaw, thrust``, the
  order of ``bridge.mixer.INPUT_NAMES``; NaN = absent) and hands it, with the arming state from
  the autopilot's HEARTBEAT, to an :class:`InputSink`. On every connection it passes
  COMMAND_LONGs addressed to the bridge to the command handler and answers with COMMAND_ACK.
  When a TCP or serial connection drops it reopens it with jittered, capped exponential backoff.
* one writer per extra output: :meth:`MavlinkLink.send` only queues frames for an output, so a
  congested or dead output (a wedged UART, a stalled TCP client) delays nobody but itself.
* the heartbeat thread sends the bridge's own HEARTBEAT everywhere, negotiates the rates of
  the autopilot's output stream and of its HEARTBEAT (MAV_CMD_SET_MESSAGE_INTERVAL, autopilot
  link only; :mod:`bridge.mavlink.streams`), and notices when the stream stops.

Motor outputs and arming are obeyed only from the configured autopilot (system and component
ID) on the autopilot's connection; an output can never move a motor. The bridge is no router:
nothing is forwarded between connections. Everything that arrives is counted (:class:`LinkStats`
for the autopilot's connection, :class:`OutputStats` per output), and nothing that arrives can
stop a reader: junk, bad CRCs and refused signatures are counted and dropped. With a signing key
every connection signs what it sends and refuses unsigned input, outputs included.

Commands (COMMAND_LONG): addressed to the bridge means ``target_system`` is the vehicle's system
ID or 0 (broadcast) and ``target_component`` is ``component_id`` or 0, from any sender on any
connection. The registered handlers (:meth:`MavlinkLink.add_command_handler`) are asked in
the order they were added; each returns a MAV_RESULT, or ``None`` for "not mine", and the first
answer wins. The COMMAND_ACK goes back to the sender on the
connection the command came in on, only: the autopilot would otherwise forward a GCS's answers
back to it a second time. A command nobody claims is answered MAV_RESULT_UNSUPPORTED only when it
named the bridge exactly (system and component); broadcasts nobody claims get no answer.

Every frame is packed once: one sequence number and one signature serve all connections, so a
recording (``tlog``) holds exactly the bytes on the wire. A COMMAND_ACK or a stream request goes
to one connection only, and a message sent with ``to`` (the ESC telemetry of one connection's
message set) to those named, which the others see as a skipped sequence number.

Encoding and decoding use the project's MAVLink 2 dialect module, ardupilotmega plus ESC_INFO
and ESC_STATUS (:func:`bridge.mavlink.load_dialect`), directly rather than the one ``mavutil``
picks, because ``mavutil`` chooses MAVLink 1 or 2 from the ``MAVLINK20`` environment
variable and switches it process-wide when it first sees a MAVLink 2 frame. The MAVLink 2 parser
reads MAVLink 1 frames too. ``mavutil`` is used only to open the transports.

pymavlink is not thread-safe: packing updates the sequence number and the signing timestamp,
which the parsers update too (replay protection), and a UDP server connection's list of peers is
changed by reads while writes walk it. So one codec lock covers every pack and every parse (CPU
only, microseconds), each connection has a lock around its reads and writes, and a send lock keeps
frames in sequence order on the wire. No thread holds two of them except a sender (send lock,
then one of the others); callbacks run with none held.
"""

from __future__ import annotations

import functools
import hashlib
import hmac
import logging
import math
import random
import select
import struct
import threading
import time
from collections import deque
from collections.abc import Callable, Collection
from dataclasses import dataclass
from types import ModuleType, TracebackType
from typing import Any, BinaryIO, Final, Protocol

from pymavlink import mavutil

from bridge.config import MavlinkConfig
from bridge.errors import ConfigError, LinkError
from bridge.mavlink import load_dialect
from bridge.mavlink.actuators import decoder_for
from bridge.mavlink.frames import MAGIC_V2, Frame
from bridge.mavlink.streams import StreamRequest, result_name
from bridge.mavlink.transport import (
    ACCEPTED_URL_FORMS,
    DEFAULT_BAUD,
    Endpoint,
    Transport,
    parse_url,
)
from bridge.mixer import INPUT_NAMES

__all__ = [
    "ACCEPTED_URL_FORMS",
    "DEFAULT_BAUD",
    "INPUT_VECTOR_LEN",
    "CommandHandler",
    "Endpoint",
    "InputSink",
    "LinkStats",
    "MavlinkLink",
    "OutputStats",
    "Transport",
    "check_endpoints",
    "parse_url",
]

log = logging.getLogger(__name__)

CommandHandler = Callable[[Any], int | None]
"""Takes a COMMAND_LONG addressed to the bridge; returns a MAV_RESULT, or None: not mine."""

COMMAND_ORIGIN: Final = "bridge_connection"
"""The attribute a COMMAND_LONG carries while the handlers see it: the URL (as configured) of
the connection it came in on, for :meth:`MavlinkLink.send`'s ``to``."""

INPUT_VECTOR_LEN: Final = len(INPUT_NAMES)
"""36: ``ch1..ch32``, then ``roll, pitch, yaw, thrust`` (the order of ``INPUT_NAMES``)."""

_NAN: Final = math.nan

_READ_SIZE: Final = 4096  # bytes per read; a UDP read returns one whole datagram whatever this is
_POLL_S: Final = 0.1  # readers and writers wake at least this often to notice close()
_REQUEST_PERIOD_NS: Final = 1_000_000_000  # check the streams (and ask) this often
_HEARD_NS: Final = 3_000_000_000  # the autopilot is there: a HEARTBEAT within this (3 missed)
_RATE_WINDOW_NS: Final = 1_000_000_000  # the arrival rate is measured over about this long
_RATE_LOG_CHANGE: Final = 0.2  # log the arrival rate again when it moves by this fraction
_BACKOFF_FIRST_S: Final = 0.1  # a restarting TCP peer is often listening again within this
_BACKOFF_CAP_S: Final = 5.0
_JOIN_TIMEOUT_S: Final = 2.0
# A write that blocks holds the connection's lock and would stall its reader; a UART without
# flow control never blocks this long, so hitting it means the port is wedged.
_SERIAL_WRITE_TIMEOUT_S: Final = 0.1
# Frames waiting for an output's writer. At the bridge's own rates (a HEARTBEAT, ~30 telemetry
# messages a second) this is seconds of backlog: a full queue means the output is stuck, and
# the oldest frames, the least useful ones, are dropped first.
_OUTPUT_QUEUE_FRAMES: Final = 256
_STATUSTEXT_LEN: Final = 50  # STATUSTEXT.text is char[50]
_SIGNATURE_LEN: Final = 6  # the truncated SHA-256 at the end of a signed MAVLink 2 frame
# How pymavlink's parser (robust mode) reports a message refused by signing: a BAD_DATA whose
# reason is this text. Those are counted as rejected_unsigned, not as bad_data.
_SIGNATURE_REJECTED: Final = "Invalid signature"
# MAVLink signing timestamps count 10 µs units since 2015-01-01T00:00:00Z.
_SIGNING_EPOCH_S: Final = 1_420_070_400
_SIGNING_TICKS_PER_S: Final = 100_000
# A .tlog record: the time it was logged, in µs since the Unix epoch, big-endian, then the frame.
_TLOG_STAMP: Final = struct.Struct(">Q")
_HEADER_V1: Final = 6  # bytes before the payload: magic, len, seq, sys, comp, msgid
_HEADER_V2: Final = 10  # magic, len, incompat, compat, seq, sys, comp, msgid (3 bytes)
_SERIAL_WRITE_FAILED: Final = -1  # what pymavlink's serial write returns after an exception


class InputSink(Protocol):
    """Receives what the autopilot commands. Called on the reader thread: keep it short."""

    def on_actuators(self, values: list[float], time_ns: int) -> None:
        """A fresh input vector of :data:`INPUT_VECTOR_LEN` floats (NaN = absent), stamped
        with ``time.monotonic_ns()`` at receipt. The list is the sink's to keep."""

    def on_armed(self, armed: bool, time_ns: int) -> None:
        """The autopilot's arming state, on each of its HEARTBEATs (and, with the
        ``hil_actuator_controls`` source, on each HIL_ACTUATOR_CONTROLS); monotonic ns."""


@dataclass
class LinkStats:
    """Counters of the autopilot's connection (and the link-wide ones), updated in place by
    the link's threads; read them field by field."""

    messages: int = 0
    """Well-formed MAVLink messages received on the autopilot's connection, from any sender."""
    outputs: int = 0
    """Configured output messages from the autopilot handed to the sink (each
    SERVO_OUTPUT_RAW port counts)."""
    ignored_foreign: int = 0
    """HEARTBEATs and configured output messages from any other system or component (a ground
    station's HEARTBEAT counts too)."""
    rejected_unsigned: int = 0
    """With a signing key: messages refused as unsigned, badly signed or replayed."""
    bad_data: int = 0
    """Stretches of bytes that were no valid MAVLink frame (junk, bad CRC, truncation)."""
    reconnects: int = 0
    """Times the connection was reopened after it dropped."""
    output_rate_hz: float = 0.0
    """Output messages per second over the last ~1 s; 0 once none arrived for ~1 s."""
    last_heartbeat_ns: int = 0
    """``time.monotonic_ns()`` of the autopilot's last HEARTBEAT; 0 = none yet."""
    last_output_ns: int = 0
    """``time.monotonic_ns()`` of the last output message handed to the sink; 0 = none yet."""
    send_failures: int = 0
    """Messages not sent to the autopilot because its connection was down (being reopened,
    or closed) or the write failed."""
    handler_errors: int = 0
    """Messages dropped because handling them raised (a fault in the sink or the command
    handler); logged."""
    commands: int = 0
    """COMMAND_LONGs addressed to the bridge, from any connection."""
    tlog_errors: int = 0
    """Frames that could not be appended to the recording (disk full, file closed)."""


@dataclass
class OutputStats:
    """Counters of one extra output, updated in place by its threads."""

    url: str
    """As configured."""
    messages: int = 0
    """Well-formed MAVLink messages received on it (only commands are acted on)."""
    rejected_unsigned: int = 0
    """With a signing key: messages refused as unsigned, badly signed or replayed."""
    bad_data: int = 0
    """Stretches of bytes that were no valid MAVLink frame."""
    reconnects: int = 0
    """Times it was reopened after it dropped (or opened late, after failing at start)."""
    sent: int = 0
    """Frames handed to its transport. pymavlink drops silently what a UDP or listening TCP
    output cannot deliver (no peer yet, unreachable), and those count here too."""
    send_failures: int = 0
    """Frames not sent: the output was down, its queue overflowed, or the write failed."""
    handler_errors: int = 0
    """Messages dropped because handling them raised; logged."""


_Counters = LinkStats | OutputStats


def check_endpoints(config: MavlinkConfig) -> tuple[Endpoint, list[Endpoint]]:
    """Parse ``url`` and every ``outputs`` entry, and refuse a connection listed twice.

    Two entries are the same connection when they have the same transport and address (a port
    written with leading zeros is the same port): opening both would fail, or send everything
    twice. Called by :meth:`MavlinkLink.start` and by the start-up check before it.

    Returns:
        The autopilot's endpoint and the outputs' endpoints, in ``outputs`` order.

    Raises:
        ConfigError: a URL is malformed (see :func:`parse_url`), or an output repeats the
            autopilot's URL or another output.
    """
    endpoint = parse_url(config.url)
    outputs = [parse_url(url, "outputs") for url in config.outputs]
    seen = {(endpoint.kind, endpoint.address): f"[mavlink] url {endpoint.url!r}"}
    for output in outputs:
        where = (output.kind, output.address)
        if where in seen:
            raise ConfigError(
                f"[mavlink] outputs {output.url!r} is the same connection as {seen[where]}; "
                "list each connection once"
            )
        seen[where] = repr(output.url)
    return endpoint, outputs


@functools.cache
def _codec_class(dialect: ModuleType) -> Any:
    """The dialect's MAVLink 2 codec, verifying a signature before trusting its timestamp.

    pymavlink records a signed packet's timestamp as the stream's newest *before* it checks the
    signature, so a single forged packet with a far-future timestamp would make every genuine
    packet of that (link, system, component) look like a replay from then on. Checking the
    signature first keeps forged packets from touching the replay state.
    """

    class Codec(dialect.MAVLink):  # type: ignore[misc, name-defined]  # pymavlink is untyped
        counters: _Counters | None = None
        """Where a parser counts refused signatures (set per connection)."""

        def check_signature(self, msgbuf: bytearray, src_system: int, src_component: int) -> bool:
            key: bytes = self.signing.secret_key
            digest = hashlib.sha256(key + bytes(msgbuf[:-_SIGNATURE_LEN])).digest()
            if not hmac.compare_digest(digest[:_SIGNATURE_LEN], bytes(msgbuf[-_SIGNATURE_LEN:])):
                return False
            return bool(super().check_signature(msgbuf, src_system, src_component))

    return Codec


def _frame_of(msg: Any) -> Frame:
    """A pymavlink message as the frame the shared decoders read (checked by the parser).

    The payload is cut from the message's buffer: pymavlink's ``get_payload()`` of a parsed
    MAVLink 2 frame starts at the wrong offset."""
    raw = bytes(msg.get_msgbuf())
    version = 2 if raw[0] == MAGIC_V2 else 1
    header = _HEADER_V2 if version == 2 else _HEADER_V1
    return Frame(
        msg.get_msgId(),
        msg.get_srcSystem(),
        msg.get_srcComponent(),
        msg.get_seq(),
        raw[header : header + raw[1]],
        version,
        msg.get_signed(),
        raw,
    )


def _log_sparsely(level: int, count: int, text: str, *args: Any, exc_info: bool = False) -> None:
    """Log the 1st, 2nd, 4th, 8th... occurrence, so a flood of bad input cannot flood the log."""
    if count & (count - 1) == 0:
        log.log(level, text + " (%d so far)", *args, count, exc_info=exc_info)


def _wait_readable(fd: int, timeout_s: float) -> bool:
    """True when ``fd`` has data, an end of stream or an error to report (poll, not select:
    select fails for descriptors above 1023)."""
    poller = select.poll()
    poller.register(fd, select.POLLIN | select.POLLPRI)
    return bool(poller.poll(timeout_s * 1000))


class _Connection:
    """One transport the link reads and writes: the autopilot's, or an extra output."""

    def __init__(self, endpoint: Endpoint, counters: _Counters, is_autopilot: bool) -> None:
        self.endpoint = endpoint
        self.counters = counters
        self.is_autopilot = is_autopilot
        self.lock = threading.Lock()
        """Guards ``conn``: its reads, writes, closing and replacement."""
        self.conn: Any = None
        self.parser: Any = None
        """Owned by the reader thread; used under the link's codec lock (shared signing)."""
        # Outputs only: frames for the writer thread; oldest dropped first when full.
        self.queue: deque[bytes] = deque()
        self.queued = threading.Condition()

    @property
    def url(self) -> str:
        return self.endpoint.url


class MavlinkLink:
    """The autopilot's connection plus extra outputs: motor outputs and arming in, HEARTBEAT,
    STATUSTEXT, telemetry and command answers out.

    Use :meth:`start` once, then :meth:`close` (or a ``with`` block, which closes on exit).
    ``stats`` and ``output_stats`` are updated live. Build messages with
    ``link.mav.<name>_encode(...)`` and send them with :meth:`send`; never call
    ``mav.<name>_send``, which would bypass the locks.

    ``tlog``: when given, every MAVLink message received on any connection and every frame
    sent is appended to it in .tlog form (8-byte big-endian µs since the Unix epoch, then the
    frame as on the wire). The caller opens and closes the file; :meth:`close` flushes it.
    """

    def __init__(
        self,
        config: MavlinkConfig,
        sink: InputSink | None,
        tlog: BinaryIO | None = None,
        uplink: Callable[[], Any] | None = None,
        needed_rate_hz: float = 0.0,
    ) -> None:
        """``sink``: receives the autopilot's outputs and arming state; None when the owner of
        the autopilot's link acts on them (the daemon's control loop), which then reports the
        outputs it counted through :meth:`note_outputs`.
        ``tlog``: a binary file to record into (see the class docstring), or None.
        ``uplink``: opens the autopilot's connection (an object with pymavlink's transport
        methods: ``fd``, ``recv``, ``write``, ``close``); None: pymavlink's transport for
        ``config.url``. The daemon passes the control loop's relay
        (:class:`bridge.relay.MainConnection`): the loop owns the real link.
        ``needed_rate_hz``: the slowest output stream the control loop arms on (two inputs
        per input timeout); a slower one is reported loudly. 0: no such limit.

        Raises:
            DialectError: the project's MAVLink dialect could not be generated or loaded.
        """
        self._config = config
        self._sink = sink
        self._open_uplink = uplink
        self._tlog = tlog
        self._tlog_lock = threading.Lock()
        self._autopilot = (config.autopilot_system_id, config.autopilot_component_id)
        self.stats = LinkStats()
        self.output_stats = tuple(OutputStats(url) for url in config.outputs)
        """One per ``[mavlink] outputs`` entry, in that order."""
        self._send_lock = threading.Lock()
        self._codec_lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._connections: list[_Connection] = []
        self._uplink: _Connection | None = None  # the autopilot's connection, once started
        self._started = False
        self._closed = False
        # Replaced, never mutated: a reader walks the tuple it found without a lock.
        self._command_handlers: tuple[CommandHandler, ...] = ()
        self._handlers_lock = threading.Lock()  # serializes add/remove only
        self._dialect = load_dialect()
        # Our system ID is the vehicle's: the bridge is one more component of it.
        self._mav: Any = _codec_class(self._dialect)(
            None, srcSystem=config.autopilot_system_id, srcComponent=config.component_id
        )
        # The same decoder the control loop uses (bridge.mavlink.actuators), fed the frame of
        # each pymavlink message: one implementation of what an output message means.
        self._decoder = decoder_for(config.source, config.autopilot_system_id, config.component_id)
        self._output_name = self._decoder.name
        self._output_msg_id: int = getattr(self._dialect, f"MAVLINK_MSG_ID_{self._output_name}")
        self._armed_flag: int = self._dialect.MAV_MODE_FLAG_SAFETY_ARMED
        # Arrival-rate window, owned by the autopilot's reader thread.
        self._window_start_ns = 0
        self._window_count = 0
        self._outputs_noted = 0  # the last total given to note_outputs
        self._logged_rate_hz = 0.0
        self._needed_rate_hz = needed_rate_hz
        self._slow_logged = False
        self._foreign_seen: set[tuple[int, int]] = set()
        # The rates asked of the autopilot (MAV_CMD_SET_MESSAGE_INTERVAL): its outputs, and
        # its HEARTBEAT, which carries the arming state. One request goes out per check, so
        # a COMMAND_ACK (which does not say for which message) answers the newest request.
        autopilot = f"autopilot {self._autopilot[0]}/{self._autopilot[1]}"
        self._output_request = StreamRequest(self._output_name, autopilot, config.stream_rate_hz)
        self._heartbeat_request = StreamRequest(
            "HEARTBEAT", autopilot, config.autopilot_heartbeat_hz, gave_up_level=logging.WARNING
        )
        self._pending_request: StreamRequest | None = None
        self._asked_hz: dict[str, float] = {}  # the rate last asked, per message: log changes
        self._heartbeats = 0  # the autopilot's HEARTBEATs, for their arriving rate
        self._heartbeats_checked = (0, 0)  # (count, monotonic ns) at the previous check
        self._autopilot_type: int | None = None

    # -- public API ------------------------------------------------------------------------

    @property
    def mav(self) -> Any:
        """The pymavlink MAVLink 2 object, for building messages (``*_encode``) to :meth:`send`."""
        return self._mav

    @property
    def dialect(self) -> ModuleType:
        """The dialect module the link speaks (its constants: ``MAV_RESULT_*``, message IDs)."""
        return self._dialect

    @property
    def autopilot_type(self) -> int | None:
        """The obeyed autopilot's flight stack (MAV_AUTOPILOT: 3 ArduPilot, 12 PX4) from its
        latest HEARTBEAT; None before the first."""
        return self._autopilot_type

    def add_command_handler(self, handler: CommandHandler) -> None:
        """Pass COMMAND_LONGs addressed to the bridge to ``handler`` too, after the handlers
        added before it (adding one twice does nothing).

        Handlers run on a reader thread: keep them short and never wait there for a reply. Each
        returns a MAV_RESULT, or ``None`` when the command is not its; the first MAV_RESULT is
        sent back as COMMAND_ACK and the later handlers are not asked (see the module docstring
        for who gets an answer). A handler that raises is counted and logged and the next one
        is asked; if none answers, a command that named the bridge exactly is answered
        MAV_RESULT_FAILED.
        """
        with self._handlers_lock:  # two threads adding at once must not lose one
            if handler not in self._command_handlers:
                self._command_handlers = (*self._command_handlers, handler)

    def remove_command_handler(self, handler: CommandHandler) -> None:
        """Stop passing commands to ``handler``; removing one that is not there does nothing."""
        with self._handlers_lock:
            self._command_handlers = tuple(h for h in self._command_handlers if h != handler)

    def start(self) -> None:
        """Check every URL, open the autopilot's connection and the outputs, start the threads.

        An output that cannot be opened does not stop the start: it is logged and retried in
        the background with backoff (a GCS that is not up yet must not keep a vehicle from
        flying).

        Raises:
            ConfigError: a URL is malformed (the message names its key, the URL and the accepted
                forms), or an output repeats the autopilot's URL or another output.
            LinkError: the autopilot's connection cannot be opened (no such device, port in
                use, refused).
            RuntimeError: the link was started before, or closed.
        """
        if self._started or self._closed:
            raise RuntimeError("a MavlinkLink can be started once, and not after close()")
        endpoint, outputs = check_endpoints(self._config)
        if self._config.signing_key is not None:
            self._setup_signing(bytes.fromhex(self._config.signing_key))
        uplink = _Connection(endpoint, self.stats, is_autopilot=True)
        self._install(uplink, self._open(endpoint, is_autopilot=True))
        self._uplink = uplink
        self._connections = [uplink]
        self._started = True
        log.info(
            "MAVLink %s open: obeying %s from %d/%d, signing %s",
            endpoint.url,
            self._output_name,
            *self._autopilot,
            "required" if self._config.signing_key else "off",
        )
        for output, counters in zip(outputs, self.output_stats, strict=True):
            connection = _Connection(output, counters, is_autopilot=False)
            try:
                self._install(connection, self._open(output))
                log.info("MAVLink output %s open", output.url)
            except LinkError as exc:
                log.warning("%s; retrying in the background", exc)
            self._connections.append(connection)
        self._threads = [
            threading.Thread(
                target=self._run_reader, args=(uplink,), name=f"mavlink-reader {endpoint.url}"
            ),
            threading.Thread(target=self._run_heartbeat, name=f"mavlink-heartbeat {endpoint.url}"),
        ]
        for connection in self._connections[1:]:
            self._threads += [
                threading.Thread(
                    target=self._run_reader,
                    args=(connection,),
                    name=f"mavlink-reader {connection.url}",
                ),
                threading.Thread(
                    target=self._run_writer,
                    args=(connection,),
                    name=f"mavlink-writer {connection.url}",
                ),
            ]
        for thread in self._threads:
            thread.daemon = True  # a stuck link must not keep the process alive
            thread.start()

    def send(self, msg: Any, to: Collection[str] | None = None) -> None:
        """Send a pymavlink message object to the autopilot and every output, from any thread;
        with ``to``, only to the connections whose URL (``url`` or an ``outputs`` entry, as
        configured) it holds (the others see a skipped sequence number).

        Never raises for link trouble: a connection that is down (or closed) or whose write
        fails drops the frame and counts it in its ``send_failures`` (MAVLink is lossy anyway).
        Outputs are written by their own threads, so a stuck output never delays this call.
        """
        with self._send_lock:
            if not self._connections:  # not started
                self.stats.send_failures += 1
                return
            connections = [c for c in self._connections if to is None or c.url in to]
            if not connections:
                return
            frame = self._pack(msg)
            for connection in connections:
                self._deliver(connection, frame)

    def statustext(self, severity: int, text: str) -> None:
        """Send a STATUSTEXT to the autopilot (and so to the ground station) and the outputs.

        ``severity`` is a MAV_SEVERITY (0 = emergency .. 7 = debug). ``text`` is cut to 50
        characters, the field's size; characters outside ASCII become ``?`` since receivers
        decode the field as ASCII.

        Raises:
            ValueError: ``severity`` is not 0..7.
        """
        if not 0 <= severity <= self._dialect.MAV_SEVERITY_DEBUG:
            raise ValueError(f"severity {severity} is not a MAV_SEVERITY (0..7)")
        raw = text[:_STATUSTEXT_LEN].encode("ascii", errors="replace")
        self.send(self._mav.statustext_encode(severity, raw))

    def close(self) -> None:
        """Stop the threads, close the connections and flush the recording; a second call does
        nothing."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        for connection in self._connections:
            with connection.queued:
                connection.queued.notify_all()
        for thread in self._threads:
            thread.join(_JOIN_TIMEOUT_S)
            if thread.is_alive():
                # Only a blocking TCP connect to a silent host can hold a thread this long; it
                # is a daemon thread and ends with the process.
                log.warning("%s did not stop within %.0f s", thread.name, _JOIN_TIMEOUT_S)
        for connection in self._connections:
            with connection.lock:
                self._drop_connection(connection)
        if self._tlog is not None:
            with self._tlog_lock:
                try:
                    self._tlog.flush()
                except (OSError, ValueError) as exc:  # ValueError: the file was closed first
                    log.warning("could not flush the MAVLink recording: %s", exc)
        if self._started:
            log.info("MAVLink %s closed", self._config.url)

    def __enter__(self) -> MavlinkLink:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # -- sending ---------------------------------------------------------------------------

    def _pack(self, msg: Any) -> bytes:
        """The frame for ``msg`` with the next sequence number (and signature), recorded.
        Called with the send lock held, so frames reach each connection in sequence order."""
        with self._codec_lock:
            frame = bytes(msg.pack(self._mav))
            self._mav.seq = (self._mav.seq + 1) % 256
        self._record(frame)
        return frame

    def _deliver(self, connection: _Connection, frame: bytes) -> None:
        """Write ``frame`` to the autopilot now, or queue it for an output's writer."""
        counters = connection.counters
        if not connection.is_autopilot:
            if self._stop.is_set():
                counters.send_failures += 1
                return
            with connection.queued:
                if len(connection.queue) >= _OUTPUT_QUEUE_FRAMES:
                    connection.queue.popleft()
                    counters.send_failures += 1
                    _log_sparsely(
                        logging.WARNING,
                        counters.send_failures,
                        "MAVLink output %s is not keeping up; dropped its oldest frame",
                        connection.url,
                    )
                connection.queue.append(frame)
                connection.queued.notify()
            return
        with connection.lock:
            self._write(connection, frame)

    def _write(self, connection: _Connection, frame: bytes) -> None:
        """Write one frame; called with the connection's lock held."""
        counters = connection.counters
        if connection.conn is None:
            counters.send_failures += 1
            return
        try:
            written = connection.conn.write(frame)
        # pymavlink's transports swallow most socket errors; whatever still escapes is the
        # connection's trouble, never the sender's.
        except Exception:  # noqa: BLE001
            counters.send_failures += 1
            _log_sparsely(
                logging.WARNING,
                counters.send_failures,
                "MAVLink %s: write failed",
                connection.url,
                exc_info=True,
            )
            return
        if written == _SERIAL_WRITE_FAILED:
            counters.send_failures += 1
            _log_sparsely(
                logging.WARNING, counters.send_failures, "MAVLink %s: write failed", connection.url
            )
        elif isinstance(counters, OutputStats):
            counters.sent += 1

    def _send_on(self, connection: _Connection, msg: Any) -> None:
        """Send ``msg`` on one connection only (a COMMAND_ACK, a request to the autopilot)."""
        with self._send_lock:
            self._deliver(connection, self._pack(msg))

    def _run_writer(self, connection: _Connection) -> None:
        """An output's writer: drains its queue, so its troubles stay its own."""
        while True:
            with connection.queued:
                while not connection.queue and not self._stop.is_set():
                    connection.queued.wait(_POLL_S)
                if self._stop.is_set():
                    return
                frames = list(connection.queue)
                connection.queue.clear()
            with connection.lock:
                for frame in frames:
                    self._write(connection, frame)

    def _record(self, frame: bytes) -> None:
        """Append one frame to the recording, if any, stamped now."""
        if self._tlog is None:
            return
        with self._tlog_lock:
            stamp_us = time.time_ns() // 1000
            try:
                self._tlog.write(_TLOG_STAMP.pack(stamp_us) + frame)
            except (OSError, ValueError) as exc:  # ValueError: the file was closed
                self.stats.tlog_errors += 1
                _log_sparsely(
                    logging.WARNING,
                    self.stats.tlog_errors,
                    "could not append to the MAVLink recording: %s",
                    exc,
                )

    # -- connection ------------------------------------------------------------------------

    def _setup_signing(self, key: bytes) -> None:
        """Sign what we send and refuse unsigned input. Every parser shares this state, which
        outlives reconnects (so replay protection does too)."""
        signing = self._mav.signing
        signing.secret_key = key
        signing.sign_outgoing = True
        signing.allow_unsigned_callback = self._refuse_unsigned
        signing.link_id = 0
        # Start at the wall clock: a receiver refuses timestamps older than the newest it saw.
        now_ticks = time.time_ns() * _SIGNING_TICKS_PER_S // 1_000_000_000
        signing.timestamp = max(0, now_ticks - _SIGNING_EPOCH_S * _SIGNING_TICKS_PER_S)

    def _open(self, endpoint: Endpoint, is_autopilot: bool = False) -> Any:
        """Open the transport. Raises LinkError."""
        if is_autopilot and self._open_uplink is not None:
            return self._open_uplink()
        ids = {
            "source_system": self._config.autopilot_system_id,
            "source_component": self._config.component_id,
        }
        try:
            if endpoint.kind == "serial":
                conn = mavutil.mavserial(endpoint.address, baud=endpoint.baud, **ids)
                conn.port.write_timeout = _SERIAL_WRITE_TIMEOUT_S
                return conn
            if endpoint.kind == "tcp":
                # retries=0 is a single attempt: the backoff between attempts is ours.
                return mavutil.mavtcp(endpoint.address, retries=0, **ids)
            if endpoint.kind == "tcpin":
                return mavutil.mavtcpin(endpoint.address, **ids)
            return mavutil.mavudp(endpoint.address, input=endpoint.kind == "udpin", **ids)
        except ImportError as exc:
            raise LinkError(
                f"cannot open MAVLink {endpoint.url!r}: serial links need pyserial ({exc})"
            ) from exc
        except (OSError, ValueError) as exc:
            raise LinkError(f"cannot open MAVLink {endpoint.url!r}: {exc}") from exc

    def _install(self, connection: _Connection, conn: Any) -> bool:
        """Make ``conn`` the live transport of ``connection``, with a fresh parser (no half
        frame carried over); False if the link was closed meanwhile (``conn`` is then closed)."""
        parser = _codec_class(self._dialect)(
            None, srcSystem=self._mav.srcSystem, srcComponent=self._mav.srcComponent
        )
        parser.robust_parsing = True  # malformed input becomes BAD_DATA instead of raising
        parser.signing = self._mav.signing
        parser.counters = connection.counters
        with connection.lock:
            if self._closed:  # close() gave up waiting for a reconnect that has now succeeded
                conn.close()
                return False
            connection.conn = conn
            connection.parser = parser
        if connection.is_autopilot:
            self._decoder.reset()
        return True

    @staticmethod
    def _drop_connection(connection: _Connection) -> None:
        """Close the live transport, if any. Called with the connection's lock held."""
        if connection.conn is not None:
            connection.conn.close()
        connection.conn = None

    def _reopen(self, connection: _Connection, reason: str) -> None:
        """Close the dropped transport and open it again, backing off, until it opens or the
        link is closed."""
        endpoint = connection.endpoint
        with connection.lock:
            self._drop_connection(connection)
        log.warning("MAVLink %s lost (%s); reconnecting", endpoint.url, reason)
        lost_at = time.monotonic()
        delay = _BACKOFF_FIRST_S
        attempts = 0
        # Jitter keeps several bridges that lost the same router from retrying in lockstep.
        while not self._stop.wait(delay * random.uniform(0.5, 1.0)):
            attempts += 1
            try:
                conn = self._open(endpoint, connection.is_autopilot)
            except LinkError as exc:
                log.debug("reconnect attempt %d failed: %s", attempts, exc)
                delay = min(delay * 2, _BACKOFF_CAP_S)
                continue
            if not self._install(connection, conn):
                return
            connection.counters.reconnects += 1
            log.info(
                "MAVLink %s reconnected after %.1f s, at attempt %d (%d reconnects in all)",
                endpoint.url,
                time.monotonic() - lost_at,
                attempts,
                connection.counters.reconnects,
            )
            return

    # -- reader threads --------------------------------------------------------------------

    def _run_reader(self, connection: _Connection) -> None:
        if connection.conn is None:  # an output that could not be opened at start
            self._reopen(connection, "could not be opened")
        while not self._stop.is_set():
            try:
                lost = self._read_once(connection)
            except EOFError as exc:
                # The link's owner ended it for good (the control loop stopped): nothing to
                # reopen, and no reason for alarm.
                log.info("MAVLink %s ended: %s", connection.url, exc)
                return
            except Exception as exc:
                # pymavlink's robust parser turns malformed input into BAD_DATA, so this is a
                # fault in the transport or parser; a fresh connection and parser clear it.
                log.exception("MAVLink reader of %s failed; reopening it", connection.url)
                lost = f"reader error: {exc!r}"
            if lost is not None:
                self._reopen(connection, lost)

    def _read_once(self, connection: _Connection) -> str | None:
        """Wait for one read's worth of input and handle it; the reason if the link dropped."""
        conn = connection.conn
        if conn is None:  # closing
            return None
        fd = conn.fd
        if not _wait_readable(fd, _POLL_S):
            return None
        with connection.lock:
            try:
                data = conn.recv(_READ_SIZE)
            except OSError as exc:
                return str(exc) or type(exc).__name__
            now = time.monotonic_ns()
            if not data:
                # Readable yet empty is the end of a stream, unless a tcpin listener just
                # accepted its client (its descriptor changes) or a datagram was empty.
                if connection.endpoint.is_stream and conn.fd == fd:
                    return "closed by the other end"
                return None
        with self._codec_lock:
            batch = connection.parser.parse_buffer(data) or []
        counters = connection.counters
        for msg in batch:
            try:
                self._handle(connection, msg, now)
            # A fault in the sink must not stop the reader: counted, and logged sparsely below.
            except Exception:  # noqa: BLE001
                counters.handler_errors += 1
                _log_sparsely(
                    logging.ERROR,
                    counters.handler_errors,
                    "dropped %s: handling it raised",
                    msg.get_type(),
                    exc_info=True,
                )
        return None

    def _refuse_unsigned(self, parser: Any, msg_id: int) -> bool:
        """pymavlink's allow_unsigned_callback: called for each unsigned or badly signed
        message once a key is set; refusing makes the parser report it as BAD_DATA."""
        counters: _Counters = getattr(parser, "counters", None) or self.stats
        counters.rejected_unsigned += 1
        _log_sparsely(
            logging.WARNING,
            counters.rejected_unsigned,
            "refused an unsigned or badly signed MAVLink message (id %d)",
            msg_id,
        )
        return False

    def _handle(self, connection: _Connection, msg: Any, now: int) -> None:
        kind: str = msg.get_type()
        counters = connection.counters
        if kind == "BAD_DATA":
            if msg.reason != _SIGNATURE_REJECTED:  # those were counted by _refuse_unsigned
                counters.bad_data += 1
                _log_sparsely(logging.INFO, counters.bad_data, "dropped bad MAVLink data")
            return
        counters.messages += 1
        self._record(bytes(msg.get_msgbuf()))
        if kind == "COMMAND_LONG":
            self._on_command(connection, msg)
            return
        if not connection.is_autopilot:
            return  # an output can send commands, never motor outputs or arming
        if kind == "COMMAND_ACK":
            self._on_ack(msg)
            return
        msg_id: int = msg.get_msgId()
        is_output = msg_id in self._decoder.msg_ids
        if not is_output and kind != "HEARTBEAT":
            return
        sender = (msg.get_srcSystem(), msg.get_srcComponent())
        if sender != self._autopilot:
            self.stats.ignored_foreign += 1
            if sender not in self._foreign_seen:
                self._foreign_seen.add(sender)
                log.info(
                    "ignoring %s from %d/%d: only %d/%d is obeyed", kind, *sender, *self._autopilot
                )
            return
        if not is_output:
            self.stats.last_heartbeat_ns = now
            self._heartbeats += 1
            self._autopilot_type = msg.autopilot
            self._decoder.identify(msg.autopilot)
            if self._sink is not None:
                self._sink.on_armed(bool(msg.base_mode & self._armed_flag), now)
            return
        if self._sink is None:
            return  # the link's owner acts on outputs and counts them (note_outputs)
        decoded = self._decoder.decode(_frame_of(msg))
        if decoded is not None:
            self._note_output(now)
            if decoded.armed is not None:
                self._sink.on_armed(decoded.armed, now)
            self._sink.on_actuators(decoded.values, now)

    def _on_command(self, connection: _Connection, msg: Any) -> None:
        """A COMMAND_LONG: pass it to the handler if it is addressed to us, and answer."""
        ours = (self._mav.srcSystem, self._config.component_id)
        target = (msg.target_system, msg.target_component)
        if target[0] not in (0, ours[0]) or target[1] not in (0, ours[1]):
            return
        self.stats.commands += 1
        named_us = target == ours
        setattr(msg, COMMAND_ORIGIN, connection.url)
        result: int | None = None
        failed = False
        for handler in self._command_handlers:
            try:
                result = handler(msg)
            # A handler's fault must not stop the reader; the sender learns it failed.
            except Exception:  # noqa: BLE001
                connection.counters.handler_errors += 1
                _log_sparsely(
                    logging.ERROR,
                    connection.counters.handler_errors,
                    "MAVLink command %d: a handler raised",
                    msg.command,
                    exc_info=True,
                )
                failed = True
                continue
            if result is not None:
                break
        if result is None and failed and named_us:
            result = self._dialect.MAV_RESULT_FAILED
        if result is None:
            if not named_us:
                return  # a broadcast nobody here handles is not ours to refuse
            result = self._dialect.MAV_RESULT_UNSUPPORTED
        ack = self._mav.command_ack_encode(
            msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()
        )
        self._send_on(connection, ack)

    def _on_ack(self, msg: Any) -> None:
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
        """Output messages counted by whoever reads them (the control loop, which owns the
        autopilot's link and relays them only when recording): ``total`` since start, as of
        ``now_ns``. Keeps the arrival rate, its log line and the stream requests going as if
        this link had read them; call it a few times a second."""
        new = total - self._outputs_noted
        self._outputs_noted = total
        if new > 0:
            self._note_output(now_ns, new)

    def _note_output(self, now: int, count: int = 1) -> None:
        """Count outputs and update the arrival-rate estimate."""
        self.stats.outputs += count
        if self._window_count == 0 or now - self.stats.last_output_ns > _RATE_WINDOW_NS:
            self._window_start_ns, self._window_count = now, count
        else:
            self._window_count += count
            elapsed = now - self._window_start_ns
            if elapsed >= _RATE_WINDOW_NS:
                rate = (self._window_count - count) * 1e9 / elapsed
                self.stats.output_rate_hz = rate
                self._window_start_ns, self._window_count = now, count
                self._log_rate(rate)
        self.stats.last_output_ns = now

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
                "%.0f Hz or more): the motors will not arm on it",
                self._output_name,
                *self._autopilot,
                rate_hz,
                self._needed_rate_hz,
            )
        self._slow_logged = slow

    # -- heartbeat thread ------------------------------------------------------------------

    def _run_heartbeat(self) -> None:
        beat_period_ns = round(1e9 / self._config.heartbeat_hz)
        next_beat = next_check = time.monotonic_ns()
        while True:
            now = time.monotonic_ns()
            if now >= next_beat:
                self.send(
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
            if self._stop.wait(max(0, min(next_beat, next_check) - time.monotonic_ns()) / 1e9):
                return

    def _check_stream(self, now: int) -> None:
        """Once a second: notice a stopped stream, and negotiate the rates of the autopilot's
        outputs and HEARTBEAT (:class:`~bridge.mavlink.streams.StreamRequest`)."""
        stats = self.stats
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
        if self._uplink is None:
            return
        # To the autopilot only: a GCS on an output has no use for it.
        self._send_on(
            self._uplink,
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
            ),
        )
