"""The MAVLink edge: the autopilot's motor outputs and arming state in; the bridge's HEARTBEAT,
STATUSTEXT and ESC telemetry out, to the autopilot and to any extra outputs (a GCS).

The main process's MAVLink, on pymavlink's codec (the dialect) and, through
:mod:`~bridge.mavlink.connection`, its transports. A :class:`MavlinkLink` opens one connection
to the autopilot plus one per ``[mavlink] outputs`` entry, and runs named daemon threads:

* one reader per connection. On the autopilot's connection it decodes the configured output
  message (:mod:`bridge.mavlink.actuators`) into an ``INPUT_VECTOR_LEN``-vector (``ch1..ch32,
  roll, pitch, yaw, thrust``, the order of ``bridge.mixing.definition.INPUT_NAMES``; NaN =
  absent) and hands it, with the arming state from the autopilot's HEARTBEAT, to an
  :class:`InputSink`, and reads its boot clock from its SYSTEM_TIME and TIMESYNC
  (:mod:`bridge.mavlink.boot_time`, the outgoing ESC reports' stamps). On every connection it
  passes COMMAND_LONGs addressed to the bridge to the command handlers
  (:mod:`bridge.mavlink.commands`) and answers with COMMAND_ACK. When a TCP or serial
  connection drops it reopens it with jittered, capped exponential backoff
  (:mod:`bridge.mavlink.connection`).
* one writer per extra output: :meth:`MavlinkLink.send` only queues frames for an output, so a
  congested or dead output (a wedged UART, a stalled TCP client) delays nobody but itself.
* the heartbeat thread (:mod:`bridge.mavlink.heartbeat`) sends the bridge's own HEARTBEAT
  everywhere, negotiates the rates of the autopilot's output stream and of its HEARTBEAT
  (MAV_CMD_SET_MESSAGE_INTERVAL, autopilot link only; :mod:`bridge.mavlink.streams`), and
  notices when the stream stops.

Motor outputs and arming are obeyed only from the configured autopilot (system and component
ID) on the autopilot's connection; an output can never move a motor. The bridge is no router:
nothing is forwarded between connections. Everything that arrives is counted
(:class:`~bridge.mavlink.stats.LinkStats` for the autopilot's connection,
:class:`~bridge.mavlink.stats.OutputStats` per output), and nothing that arrives can stop a
reader: junk, bad CRCs and refused signatures are counted and dropped. With a signing key every
connection signs what it sends and refuses unsigned input, outputs included
(:mod:`bridge.mavlink.signing`).

Commands (COMMAND_LONG) addressed to the bridge go to the registered handlers
(:meth:`MavlinkLink.add_command_handler`; who is addressed and which answer wins:
:mod:`bridge.mavlink.commands`). The COMMAND_ACK goes back to the sender on the connection the
command came in on, only: the autopilot would otherwise forward a GCS's answers back to it a
second time.

Every frame is packed once: one sequence number and one signature serve all connections, so a
recording (``tlog``, :mod:`bridge.mavlink.tlog`) holds exactly the bytes on the wire. A
COMMAND_ACK or a stream request goes to one connection only, and a message sent with ``to``
(the ESC telemetry of one connection's message set) to those named, which the others see as a
skipped sequence number.

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

import logging
import threading
import time
from collections.abc import Callable, Collection
from types import ModuleType, TracebackType
from typing import Any, BinaryIO, Final, Protocol

from bridge.config import MavlinkConfig
from bridge.errors import LinkError
from bridge.mavlink import load_dialect
from bridge.mavlink.actuators import decoder_for
from bridge.mavlink.boot_time import AutopilotBootTime
from bridge.mavlink.commands import CommandDispatcher, CommandHandler
from bridge.mavlink.connection import POLL_S, Connection, open_pymavlink, wait_readable
from bridge.mavlink.endpoints import Endpoint, check_endpoints
from bridge.mavlink.frames import MAGIC_V2, Frame
from bridge.mavlink.heartbeat import Heartbeat
from bridge.mavlink.signing import SIGNATURE_REJECTED, codec_class, new_parser, setup_signing
from bridge.mavlink.stats import LinkStats, OutputStats, log_sparsely
from bridge.mavlink.tlog import Tlog

__all__ = ["RELAYED_MESSAGES", "InputSink", "MavlinkLink", "relayed_msg_ids"]

log = logging.getLogger(__name__)

_READ_SIZE: Final = 4096  # bytes per read; a UDP read returns one whole datagram whatever this is
_JOIN_TIMEOUT_S: Final = 2.0
_STATUSTEXT_LEN: Final = 50  # STATUSTEXT.text is char[50]
_HEADER_V1: Final = 6  # bytes before the payload: magic, len, seq, sys, comp, msgid
_HEADER_V2: Final = 10  # magic, len, incompat, compat, seq, sys, comp, msgid (3 bytes)


RELAYED_MESSAGES: Final = ("HEARTBEAT", "COMMAND_LONG", "COMMAND_ACK", "SYSTEM_TIME", "TIMESYNC")
"""What the link acts on from the autopilot's connection besides its outputs: all the control
loop need relay to it when the link is not recorded (:meth:`MavlinkLink._handle`)."""


def relayed_msg_ids() -> frozenset[int]:
    """The IDs of :data:`RELAYED_MESSAGES` in the project's dialect.

    Raises:
        DialectError: the dialect could not be generated or loaded.
    """
    dialect = load_dialect()
    return frozenset(getattr(dialect, f"MAVLINK_MSG_ID_{name}") for name in RELAYED_MESSAGES)


class InputSink(Protocol):
    """Receives what the autopilot commands. Called on the reader thread: keep it short."""

    def on_actuators(self, values: list[float], time_ns: int) -> None:
        """A fresh input vector of :data:`~bridge.mavlink.actuators.INPUT_VECTOR_LEN` floats
        (NaN = absent), stamped with ``time.monotonic_ns()`` at receipt. The list is the sink's
        to keep."""

    def on_armed(self, armed: bool, time_ns: int) -> None:
        """The autopilot's arming state, on each of its HEARTBEATs (and, with the
        ``hil_actuator_controls`` source, on each HIL_ACTUATOR_CONTROLS); monotonic ns."""


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
        tlog_tap: Callable[[int, bytes], None] | None = None,
    ) -> None:
        """``sink``: receives the autopilot's outputs and arming state; None when the owner of
        the autopilot's link acts on them (the daemon's control loop), which then reports the
        outputs it counted through :meth:`note_outputs`.
        ``tlog``: a binary file to record into (see the class docstring), or None.
        ``uplink``: opens the autopilot's connection (an object with pymavlink's transport
        methods: ``fd``, ``recv``, ``write``, ``close``); None: pymavlink's transport for
        ``config.url``. The daemon passes the control loop's relay
        (:class:`bridge.mavlink.relay.MainConnection`): the loop owns the real link.
        ``needed_rate_hz``: the slowest output stream the control loop arms on (two inputs
        per input timeout); a slower one is reported loudly. 0: no such limit.
        ``tlog_tap``: gets every frame recorded in ``tlog`` with its stamp (µs since the epoch),
        on the thread that records it (the MCAP recording).

        Raises:
            DialectError: the project's MAVLink dialect could not be generated or loaded.
        """
        self._config = config
        self._sink = sink
        self._open_uplink = uplink
        self._autopilot = (config.autopilot_system_id, config.autopilot_component_id)
        self.stats = LinkStats()
        self.output_stats = tuple(OutputStats(url) for url in config.outputs)
        """One per ``[mavlink] outputs`` entry, in that order."""
        self._tlog = None if tlog is None else Tlog(tlog, self.stats, tlog_tap)
        self._send_lock = threading.Lock()
        self._codec_lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._connections: list[Connection] = []
        self._uplink: Connection | None = None  # the autopilot's connection, once started
        self._started = False
        self._closed = False
        self._dialect = load_dialect()
        # Our system ID is the vehicle's: the bridge is one more component of it.
        self._mav: Any = codec_class(self._dialect)(
            None, srcSystem=config.autopilot_system_id, srcComponent=config.component_id
        )
        self._commands = CommandDispatcher(
            (config.autopilot_system_id, config.component_id),
            self._dialect.MAV_RESULT_FAILED,
            self._dialect.MAV_RESULT_UNSUPPORTED,
        )
        # The same decoder the control loop uses (bridge.mavlink.actuators), fed the frame of
        # each pymavlink message: one implementation of what an output message means.
        self._decoder = decoder_for(config.source, config.autopilot_system_id, config.component_id)
        self._output_name = self._decoder.name
        self._armed_flag: int = self._dialect.MAV_MODE_FLAG_SAFETY_ARMED
        self._foreign_seen: set[tuple[int, int]] = set()
        self._boot_time = AutopilotBootTime()  # written by the autopilot's reader thread
        self._heartbeat = Heartbeat(
            config,
            self._mav,
            self._dialect,
            self._output_name,
            self.stats,
            needed_rate_hz,
            self.send,
            self._send_to_autopilot,
        )

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
        return self._heartbeat.autopilot_type

    def autopilot_boot_usec(self, now_ns: int) -> int | None:
        """The obeyed autopilot's µs since boot at the local monotonic ``now_ns``, from its
        SYSTEM_TIME and TIMESYNC (:mod:`bridge.mavlink.boot_time`); None until it sent one."""
        return self._boot_time.boot_usec(now_ns)

    def add_command_handler(self, handler: CommandHandler) -> None:
        """Pass COMMAND_LONGs addressed to the bridge to ``handler`` too, after the handlers
        added before it (adding one twice does nothing).

        Handlers run on a reader thread: keep them short and never wait there for a reply. Each
        returns a MAV_RESULT, or ``None`` when the command is not its; the first MAV_RESULT is
        sent back as COMMAND_ACK and the later handlers are not asked (see
        :mod:`bridge.mavlink.commands` for who gets an answer). A handler that raises is counted
        and logged and the next one is asked; if none answers, a command that named the bridge
        exactly is answered MAV_RESULT_FAILED.
        """
        self._commands.add(handler)

    def remove_command_handler(self, handler: CommandHandler) -> None:
        """Stop passing commands to ``handler``; removing one that is not there does nothing."""
        self._commands.remove(handler)

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
            setup_signing(self._mav, bytes.fromhex(self._config.signing_key), self.stats)
        uplink = Connection(endpoint, self.stats, is_autopilot=True)
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
            connection = Connection(output, counters, is_autopilot=False)
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
            threading.Thread(
                target=self._heartbeat.run,
                args=(self._stop,),
                name=f"mavlink-heartbeat {endpoint.url}",
            ),
        ]
        for connection in self._connections[1:]:
            self._threads += [
                threading.Thread(
                    target=self._run_reader,
                    args=(connection,),
                    name=f"mavlink-reader {connection.url}",
                ),
                threading.Thread(
                    target=connection.run_writer,
                    args=(self._stop,),
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

    def note_outputs(self, total: int, now_ns: int) -> None:
        """Output messages counted by whoever reads them (the control loop, which owns the
        autopilot's link and relays them only when recording): ``total`` since start, as of
        ``now_ns``. Keeps the arrival rate, its log line and the stream requests going as if
        this link had read them; call it a few times a second."""
        self._heartbeat.note_outputs(total, now_ns)

    def close(self) -> None:
        """Stop the threads, close the connections and flush the recording; a second call does
        nothing."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        for connection in self._connections:
            connection.wake_writer()
        for thread in self._threads:
            thread.join(_JOIN_TIMEOUT_S)
            if thread.is_alive():
                # Only a blocking TCP connect to a silent host can hold a thread this long; it
                # is a daemon thread and ends with the process.
                log.warning("%s did not stop within %.0f s", thread.name, _JOIN_TIMEOUT_S)
        for connection in self._connections:
            with connection.lock:
                connection.drop()
        if self._tlog is not None:
            self._tlog.flush()
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
        if self._tlog is not None:
            self._tlog.record(frame)
        return frame

    def _deliver(self, connection: Connection, frame: bytes) -> None:
        """Write ``frame`` to the autopilot now, or queue it for an output's writer."""
        if not connection.is_autopilot:
            if self._stop.is_set():
                connection.counters.send_failures += 1
                return
            connection.enqueue(frame)
            return
        with connection.lock:
            connection.write(frame)

    def _send_on(self, connection: Connection, msg: Any) -> None:
        """Send ``msg`` on one connection only (a COMMAND_ACK, a request to the autopilot)."""
        with self._send_lock:
            self._deliver(connection, self._pack(msg))

    def _send_to_autopilot(self, msg: Any) -> None:
        """Send ``msg`` on the autopilot's connection only; nothing before :meth:`start`."""
        if self._uplink is not None:
            self._send_on(self._uplink, msg)

    # -- connection ------------------------------------------------------------------------

    def _open(self, endpoint: Endpoint, is_autopilot: bool = False) -> Any:
        """Open the transport. Raises LinkError."""
        if is_autopilot and self._open_uplink is not None:
            return self._open_uplink()
        return open_pymavlink(endpoint, self._config.autopilot_system_id, self._config.component_id)

    def _install(self, connection: Connection, conn: Any) -> bool:
        """Make ``conn`` the live transport of ``connection``, with a fresh parser (no half
        frame carried over); False if the link was closed meanwhile (``conn`` is then closed)."""
        parser = new_parser(self._dialect, self._mav, connection.counters)
        with connection.lock:
            if self._closed:  # close() gave up waiting for a reconnect that has now succeeded
                conn.close()
                return False
            connection.conn = conn
            connection.parser = parser
        if connection.is_autopilot:
            self._decoder.reset()
        return True

    def _reopen(self, connection: Connection, reason: str) -> None:
        """Reopen a dropped connection, backing off, until it opens or the link is closed."""
        connection.reopen(
            reason,
            self._stop,
            lambda: self._open(connection.endpoint, connection.is_autopilot),
            self._install,
        )

    # -- reader threads --------------------------------------------------------------------

    def _run_reader(self, connection: Connection) -> None:
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

    def _read_once(self, connection: Connection) -> str | None:
        """Wait for one read's worth of input and handle it; the reason if the link dropped."""
        conn = connection.conn
        if conn is None:  # closing
            return None
        fd = conn.fd
        if not wait_readable(fd, POLL_S):
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
                log_sparsely(
                    log,
                    logging.ERROR,
                    counters.handler_errors,
                    "dropped %s: handling it raised",
                    msg.get_type(),
                    exc_info=True,
                )
        return None

    def _handle(self, connection: Connection, msg: Any, now: int) -> None:
        kind: str = msg.get_type()
        counters = connection.counters
        if kind == "BAD_DATA":
            if msg.reason != SIGNATURE_REJECTED:  # those were counted when refused
                counters.bad_data += 1
                log_sparsely(log, logging.INFO, counters.bad_data, "dropped bad MAVLink data")
            return
        counters.messages += 1
        if self._tlog is not None:
            self._tlog.record(bytes(msg.get_msgbuf()))
        if kind == "COMMAND_LONG":
            self._on_command(connection, msg)
            return
        if not connection.is_autopilot:
            return  # an output can send commands, never motor outputs or arming
        if kind == "COMMAND_ACK":
            self._heartbeat.on_ack(msg)
            return
        if kind in ("SYSTEM_TIME", "TIMESYNC"):
            if (msg.get_srcSystem(), msg.get_srcComponent()) == self._autopilot:
                if kind == "SYSTEM_TIME":
                    self._boot_time.on_system_time(msg.time_boot_ms, now)
                else:
                    self._boot_time.on_timesync(msg.tc1, msg.ts1, now)
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
            self._heartbeat.on_heartbeat(msg.autopilot, now)
            self._decoder.identify(msg.autopilot)
            if self._sink is not None:
                self._sink.on_armed(bool(msg.base_mode & self._armed_flag), now)
            return
        if self._sink is None:
            return  # the link's owner acts on outputs and counts them (note_outputs)
        decoded = self._decoder.decode(_frame_of(msg))
        if decoded is not None:
            self._heartbeat.note_output(now)
            if decoded.armed is not None:
                self._sink.on_armed(decoded.armed, now)
            self._sink.on_actuators(decoded.values, now)

    def _on_command(self, connection: Connection, msg: Any) -> None:
        """A COMMAND_LONG: pass it to the handlers if it is addressed to us, and answer."""
        if not self._commands.addressed(msg):
            return
        self.stats.commands += 1
        result = self._commands.dispatch(msg, connection.url, connection.counters)
        if result is None:
            return
        ack = self._mav.command_ack_encode(
            msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()
        )
        self._send_on(connection, ack)
