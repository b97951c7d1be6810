"""The MAVLink edge: the autopilot's motor outputs and arming state in, the bridge's HEARTBEAT out.

The only module besides the dialect that imports pymavlink. A :class:`MavlinkLink` opens one
connection to the autopilot and runs two named daemon threads:

* the reader drains the connection, decodes the configured output message into a
  :data:`INPUT_VECTOR_LEN`-vector (``ch1..ch32, roll, pitch, yaw, thrust``, the order of
  ``bridge.mixer.INPUT_NAMES``; NaN = absent) and hands it, with the arming state from the
  autopilot's HEARTBEAT, to an :class:`InputSink`. When a TCP or serial link drops it reopens
  it with jittered, capped exponential backoff.
* the heartbeat thread sends the bridge's own HEARTBEAT, asks the autopilot for the output
  stream (MAV_CMD_SET_MESSAGE_INTERVAL) every second while none arrives, and notices when the
  stream stops.

Only the configured autopilot (system and component ID) is obeyed. Everything that arrives is
counted in :class:`LinkStats`, and nothing that arrives can stop the reader: junk, bad CRCs and
refused signatures are counted and dropped.

Encoding and decoding use pymavlink's MAVLink 2 dialect module directly rather than the one
``mavutil`` picks, because ``mavutil`` chooses MAVLink 1 or 2 from the ``MAVLINK20``
environment variable and switches it process-wide when it first sees a MAVLink 2 frame. The
MAVLink 2 parser reads MAVLink 1 frames too. ``mavutil`` is used only to open the transport.

pymavlink is not thread-safe: a send updates the sequence number and the signing timestamp,
which the parser also updates, and the UDP server connection's list of peers is changed by
reads while writes walk it. One lock therefore covers every send and every read-and-parse;
callbacks run after the lock is released.
"""

from __future__ import annotations

import hashlib
import hmac
import logging
import math
import random
import re
import select
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from types import TracebackType
from typing import Any, Final, Literal, Protocol, cast

from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as dialect

from bridge.config import MavlinkConfig
from bridge.errors import ConfigError, LinkError
from bridge.mixer import AXIS_NAMES, CHANNEL_COUNT, INPUT_NAMES

__all__ = [
    "ACCEPTED_URL_FORMS",
    "DEFAULT_BAUD",
    "INPUT_VECTOR_LEN",
    "Endpoint",
    "InputSink",
    "LinkStats",
    "MavlinkLink",
    "Transport",
    "parse_url",
]

log = logging.getLogger(__name__)

Transport = Literal["udpin", "udpout", "tcp", "tcpin", "serial"]

INPUT_VECTOR_LEN: Final = len(INPUT_NAMES)
"""36: ``ch1..ch32``, then ``roll, pitch, yaw, thrust`` (the order of ``INPUT_NAMES``)."""

_AXIS_SLOTS: Final = tuple(INPUT_NAMES.index(name) for name in AXIS_NAMES)
_NAN: Final = math.nan
_SERVO_PORT_CHANNELS: Final = 16  # SERVO_OUTPUT_RAW carries 16 channels per port
_SERVO_FIELDS: Final = tuple(f"servo{i}_raw" for i in range(1, _SERVO_PORT_CHANNELS + 1))
_HIL_CHANNELS: Final = 16

ACCEPTED_URL_FORMS: Final = (
    "udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT, tcpin:HOST:PORT, "
    "serial:DEVICE[:BAUD] or a device path DEVICE[:BAUD] (e.g. serial:/dev/ttyAMA0:921600)"
)
DEFAULT_BAUD: Final = 115_200  # pymavlink's default; USB CDC links ignore it
_NETWORK_URL: Final = re.compile(r"(udpin|udpout|tcp|tcpin):([^:\s]+):([0-9]{1,5})")
# The device ends at the last ":digits", if any: /dev/serial/by-path names contain colons.
_SERIAL_URL: Final = re.compile(r"(?:serial:)?(/\S*?)(?::([0-9]+))?")

_READ_SIZE: Final = 4096  # bytes per read; a UDP read returns one whole datagram whatever this is
_POLL_S: Final = 0.1  # the reader wakes at least this often to notice close()
_REQUEST_PERIOD_NS: Final = 1_000_000_000  # ask for the stream this often while none arrives
_RATE_WINDOW_NS: Final = 1_000_000_000  # the arrival rate is measured over about this long
_RATE_LOG_CHANGE: Final = 0.2  # log the arrival rate again when it moves by this fraction
_BACKOFF_FIRST_S: Final = 0.1  # a restarting TCP peer is often listening again within this
_BACKOFF_CAP_S: Final = 5.0
_JOIN_TIMEOUT_S: Final = 2.0
# A write that blocks holds the link's lock and would stall the reader; a UART without flow
# control never blocks this long, so hitting it means the port is wedged.
_SERIAL_WRITE_TIMEOUT_S: Final = 0.1
_STATUSTEXT_LEN: Final = 50  # STATUSTEXT.text is char[50]
_SIGNATURE_LEN: Final = 6  # the truncated SHA-256 at the end of a signed MAVLink 2 frame
# How pymavlink's parser (robust mode) reports a message refused by signing: a BAD_DATA whose
# reason is this text. Those are counted as rejected_unsigned, not as bad_data.
_SIGNATURE_REJECTED: Final = "Invalid signature"

_ARMED_FLAG: Final = dialect.MAV_MODE_FLAG_SAFETY_ARMED


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
    """Counters of one link, updated in place by its threads; read them field by field."""

    messages: int = 0
    """Well-formed MAVLink messages received, from any sender."""
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
    """Times the link was reopened after it dropped."""
    output_rate_hz: float = 0.0
    """Output messages per second over the last ~1 s; 0 once none arrived for ~1 s."""
    last_heartbeat_ns: int = 0
    """``time.monotonic_ns()`` of the autopilot's last HEARTBEAT; 0 = none yet."""
    last_output_ns: int = 0
    """``time.monotonic_ns()`` of the last output message handed to the sink; 0 = none yet."""
    send_failures: int = 0
    """Messages not sent because the link was down (being reopened, or closed)."""
    handler_errors: int = 0
    """Messages dropped because handling them raised (a fault in the sink); logged."""


@dataclass(frozen=True)
class Endpoint:
    """A validated connection string."""

    url: str
    """As configured, for messages."""
    kind: Transport
    address: str
    """``HOST:PORT``, or the serial device path."""
    baud: int = DEFAULT_BAUD
    """Serial only, in bit/s."""

    @property
    def is_stream(self) -> bool:
        """A byte stream that can end (TCP, serial) rather than datagrams."""
        return self.kind in ("tcp", "tcpin", "serial")


def parse_url(url: str) -> Endpoint:
    """Check a connection string and split it into what pymavlink opens.

    Only the forms in :data:`ACCEPTED_URL_FORMS` are accepted: pymavlink would also take a file
    name (and replay it as a log, or run it if it looks like a program), which must never
    happen by accident on a vehicle.

    Raises:
        ConfigError: naming the URL and the accepted forms.
    """
    network = _NETWORK_URL.fullmatch(url)
    if network is not None:
        kind, host, port = network.groups()
        if not 1 <= int(port) <= 65535:
            raise ConfigError(
                f"[mavlink] url {url!r}: port {port} is not 1..65535; "
                f"expected one of {ACCEPTED_URL_FORMS}"
            )
        return Endpoint(url, cast(Transport, kind), f"{host}:{int(port)}")
    serial = _SERIAL_URL.fullmatch(url)
    if serial is not None:
        device, baud = serial.groups()
        if baud is not None and int(baud) == 0:
            raise ConfigError(
                f"[mavlink] url {url!r}: baud rate 0; expected one of {ACCEPTED_URL_FORMS}"
            )
        return Endpoint(url, "serial", device, int(baud) if baud else DEFAULT_BAUD)
    raise ConfigError(
        f"[mavlink] url {url!r} is not a connection string esc-bridge accepts; "
        f"expected one of {ACCEPTED_URL_FORMS}"
    )


class _Codec(dialect.MAVLink):  # type: ignore[misc]  # pymavlink is untyped
    """pymavlink's MAVLink 2 codec, verifying a signature before trusting its timestamp.

    pymavlink records a signed packet's timestamp as the stream's newest *before* it checks the
    signature, so a single forged packet with a far-future timestamp would make every genuine
    packet of that (link, system, component) look like a replay from then on. Checking the
    signature first keeps forged packets from touching the replay state.
    """

    def check_signature(self, msgbuf: bytearray, src_system: int, src_component: int) -> bool:
        key: bytes = self.signing.secret_key
        digest = hashlib.sha256(key + bytes(msgbuf[:-_SIGNATURE_LEN])).digest()
        if not hmac.compare_digest(digest[:_SIGNATURE_LEN], bytes(msgbuf[-_SIGNATURE_LEN:])):
            return False
        return bool(super().check_signature(msgbuf, src_system, src_component))


def _finite_or_nan(value: float) -> float:
    """An autopilot's inf is no command: it would saturate the output. Treat it as absent."""
    return value if math.isfinite(value) else _NAN


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


class MavlinkLink:
    """One connection to the autopilot: motor outputs and arming in, HEARTBEAT out.

    Use :meth:`start` once, then :meth:`close` (or a ``with`` block, which closes on exit).
    ``stats`` is updated live. Build messages with ``link.mav.<name>_encode(...)`` and send them
    with :meth:`send`; never call ``mav.<name>_send``, which would bypass the lock.
    """

    def __init__(self, config: MavlinkConfig, sink: InputSink) -> None:
        self._config = config
        self._sink = sink
        self._autopilot = (config.autopilot_system_id, config.autopilot_component_id)
        self.stats = LinkStats()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._started = False
        self._closed = False
        self._conn: Any = None
        # Our system ID is the vehicle's: the bridge is one more component of it.
        self._mav: Any = _Codec(
            None, srcSystem=config.autopilot_system_id, srcComponent=config.component_id
        )
        self._parser: Any = None
        decoders: dict[str, dict[str, Callable[[Any, int], list[float] | None]]] = {
            "servo_output_raw": {"SERVO_OUTPUT_RAW": self._from_servo_output_raw},
            "actuator_output_status": {"ACTUATOR_OUTPUT_STATUS": self._from_actuator_output_status},
            "hil_actuator_controls": {"HIL_ACTUATOR_CONTROLS": self._from_hil_actuator_controls},
            "actuator_control_target": {
                "ACTUATOR_CONTROL_TARGET": self._from_actuator_control_target,
                "SET_ACTUATOR_CONTROL_TARGET": self._from_set_actuator_control_target,
            },
        }
        self._decoders = decoders[config.source]
        self._output_name = next(iter(self._decoders))
        self._output_msg_id: int = getattr(dialect, f"MAVLINK_MSG_ID_{self._output_name}")
        # SERVO_OUTPUT_RAW state: channels 1..32 as last received, and per port whether the
        # other port arrived since this one last did (see _from_servo_output_raw).
        self._servo = [_NAN] * CHANNEL_COUNT
        self._other_port_seen = [True, True]
        # Arrival-rate window, owned by the reader thread.
        self._window_start_ns = 0
        self._window_count = 0
        self._logged_rate_hz = 0.0
        self._requesting = False
        self._foreign_seen: set[tuple[int, int]] = set()

    # -- public API ------------------------------------------------------------------------

    @property
    def mav(self) -> Any:
        """The pymavlink MAVLink 2 object, for building messages (``*_encode``) to :meth:`send`."""
        return self._mav

    def start(self) -> None:
        """Open the connection and start the reader and heartbeat threads.

        Raises:
            ConfigError: the URL is malformed (the message names it and the accepted forms).
            LinkError: the connection cannot be opened (no such device, port in use, refused).
            RuntimeError: the link was started before, or closed.
        """
        if self._started or self._closed:
            raise RuntimeError("a MavlinkLink can be started once, and not after close()")
        endpoint = parse_url(self._config.url)
        conn = self._open(endpoint)
        self._install(conn)
        if self._config.signing_key is not None:
            # setup_signing acts on conn.mav, which _install made our codec; its signing state
            # is shared with every parser, and outlives reconnects.
            conn.setup_signing(
                bytes.fromhex(self._config.signing_key),
                sign_outgoing=True,
                allow_unsigned_callback=self._refuse_unsigned,
                link_id=0,
            )
        self._started = True
        log.info(
            "MAVLink %s open: obeying %s from %d/%d, signing %s",
            endpoint.url,
            self._output_name,
            *self._autopilot,
            "required" if self._config.signing_key else "off",
        )
        self._threads = [
            threading.Thread(
                target=self._run_reader, args=(endpoint,), name=f"mavlink-reader {endpoint.url}"
            ),
            threading.Thread(target=self._run_heartbeat, name=f"mavlink-heartbeat {endpoint.url}"),
        ]
        for thread in self._threads:
            thread.daemon = True  # a stuck link must not keep the process alive
            thread.start()

    def send(self, msg: Any) -> None:
        """Send a pymavlink message object, from any thread.

        Never raises for link trouble: while the link is down the message is dropped and
        counted in ``stats.send_failures`` (MAVLink is lossy anyway).
        """
        with self._lock:
            if self._conn is None:
                self.stats.send_failures += 1
                return
            self._mav.send(msg)

    def statustext(self, severity: int, text: str) -> None:
        """Send a STATUSTEXT to the autopilot (and so to the ground station).

        ``severity`` is a MAV_SEVERITY (0 = emergency .. 7 = debug). ``text`` is cut to 50
        characters, the field's size; characters outside ASCII become ``?`` since receivers
        decode the field as ASCII.

        Raises:
            ValueError: ``severity`` is not 0..7.
        """
        if not 0 <= severity <= dialect.MAV_SEVERITY_DEBUG:
            raise ValueError(f"severity {severity} is not a MAV_SEVERITY (0..7)")
        raw = text[:_STATUSTEXT_LEN].encode("ascii", errors="replace")
        self.send(self._mav.statustext_encode(severity, raw))

    def close(self) -> None:
        """Stop the threads and close the connection; a second call does nothing."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        for thread in self._threads:
            thread.join(_JOIN_TIMEOUT_S)
            if thread.is_alive():
                # Only a blocking TCP connect to a silent host can hold a thread this long; it
                # is a daemon thread and ends with the process.
                log.warning("%s did not stop within %.0f s", thread.name, _JOIN_TIMEOUT_S)
        with self._lock:
            self._drop_connection()
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

    # -- connection ------------------------------------------------------------------------

    def _open(self, endpoint: Endpoint) -> Any:
        """Open the transport. Raises LinkError."""
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

    def _install(self, conn: Any) -> bool:
        """Make ``conn`` the live connection, with a fresh parser (no half frame carried over);
        False if the link was closed meanwhile (``conn`` is then closed)."""
        parser = _Codec(None, srcSystem=self._mav.srcSystem, srcComponent=self._mav.srcComponent)
        parser.robust_parsing = True  # malformed input becomes BAD_DATA instead of raising
        parser.signing = self._mav.signing
        with self._lock:
            if self._closed:  # close() gave up waiting for a reconnect that has now succeeded
                conn.close()
                return False
            conn.mav = self._mav
            self._mav.file = conn
            self._conn = conn
            self._parser = parser
        self._servo = [_NAN] * CHANNEL_COUNT
        self._other_port_seen = [True, True]
        return True

    def _drop_connection(self) -> None:
        """Close the live connection, if any. Called with the lock held."""
        if self._conn is not None:
            self._conn.close()
        self._conn = None
        self._mav.file = None

    def _reopen(self, endpoint: Endpoint, reason: str) -> None:
        """Close the dropped connection and open it again, backing off, until it opens or
        the link is closed."""
        with self._lock:
            self._drop_connection()
        log.warning("MAVLink %s lost (%s); reconnecting", endpoint.url, reason)
        lost_at = time.monotonic()
        delay = _BACKOFF_FIRST_S
        attempts = 0
        # Jitter keeps several bridges that lost the same router from retrying in lockstep.
        while not self._stop.wait(delay * random.uniform(0.5, 1.0)):
            attempts += 1
            try:
                conn = self._open(endpoint)
            except LinkError as exc:
                log.debug("reconnect attempt %d failed: %s", attempts, exc)
                delay = min(delay * 2, _BACKOFF_CAP_S)
                continue
            if not self._install(conn):
                return
            self.stats.reconnects += 1
            log.info(
                "MAVLink %s reconnected after %.1f s, at attempt %d (%d reconnects in all)",
                endpoint.url,
                time.monotonic() - lost_at,
                attempts,
                self.stats.reconnects,
            )
            return

    # -- reader thread ---------------------------------------------------------------------

    def _run_reader(self, endpoint: Endpoint) -> None:
        while not self._stop.is_set():
            try:
                lost = self._read_once(endpoint.is_stream)
            except Exception as exc:
                # pymavlink's robust parser turns malformed input into BAD_DATA, so this is a
                # fault in the transport or parser; a fresh connection and parser clear it.
                log.exception("MAVLink reader failed; reopening the link")
                lost = f"reader error: {exc!r}"
            if lost is not None:
                self._reopen(endpoint, lost)

    def _read_once(self, is_stream: bool) -> str | None:
        """Wait for one read's worth of input and handle it; the reason if the link dropped."""
        conn = self._conn
        fd = conn.fd
        if not _wait_readable(fd, _POLL_S):
            return None
        with self._lock:
            try:
                data = conn.recv(_READ_SIZE)
            except OSError as exc:
                return str(exc) or type(exc).__name__
            now = time.monotonic_ns()
            if not data:
                # Readable yet empty is the end of a stream, unless a tcpin listener just
                # accepted its client (its descriptor changes) or a datagram was empty.
                if is_stream and conn.fd == fd:
                    return "closed by the other end"
                return None
            batch = self._parser.parse_buffer(data) or []
        for msg in batch:
            try:
                self._handle(msg, now)
            # A fault in the sink must not stop the reader: counted, and logged sparsely below.
            except Exception:  # noqa: BLE001
                self.stats.handler_errors += 1
                _log_sparsely(
                    logging.ERROR,
                    self.stats.handler_errors,
                    "dropped %s: handling it raised",
                    msg.get_type(),
                    exc_info=True,
                )
        return None

    def _refuse_unsigned(self, _mav: Any, msg_id: int) -> bool:
        """pymavlink's allow_unsigned_callback: called for each unsigned or badly signed
        message once a key is set; refusing makes the parser report it as BAD_DATA."""
        self.stats.rejected_unsigned += 1
        _log_sparsely(
            logging.WARNING,
            self.stats.rejected_unsigned,
            "refused an unsigned or badly signed MAVLink message (id %d)",
            msg_id,
        )
        return False

    def _handle(self, msg: Any, now: int) -> None:
        kind: str = msg.get_type()
        if kind == "BAD_DATA":
            if msg.reason != _SIGNATURE_REJECTED:  # those were counted by _refuse_unsigned
                self.stats.bad_data += 1
                _log_sparsely(logging.INFO, self.stats.bad_data, "dropped bad MAVLink data")
            return
        self.stats.messages += 1
        decode = self._decoders.get(kind)
        if decode is None and kind != "HEARTBEAT":
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
        if decode is None:
            self.stats.last_heartbeat_ns = now
            self._sink.on_armed(bool(msg.base_mode & _ARMED_FLAG), now)
            return
        values = decode(msg, now)
        if values is not None:
            self._note_output(now)
            self._sink.on_actuators(values, now)

    def _note_output(self, now: int) -> None:
        """Count an output and update the arrival-rate estimate."""
        self.stats.outputs += 1
        if self._window_count == 0 or now - self.stats.last_output_ns > _RATE_WINDOW_NS:
            self._window_start_ns, self._window_count = now, 1
        else:
            self._window_count += 1
            elapsed = now - self._window_start_ns
            if elapsed >= _RATE_WINDOW_NS:
                rate = (self._window_count - 1) * 1e9 / elapsed
                self.stats.output_rate_hz = rate
                self._window_start_ns, self._window_count = now, 1
                logged = self._logged_rate_hz
                if logged == 0 or abs(rate - logged) > _RATE_LOG_CHANGE * logged:
                    self._logged_rate_hz = rate
                    log.info(
                        "%s from %d/%d arriving at %.0f Hz (asked for %.0f Hz)",
                        self._output_name,
                        *self._autopilot,
                        rate,
                        self._config.stream_rate_hz,
                    )
        self.stats.last_output_ns = now

    # -- output decoders: a message in, a fresh input vector (or None: not a usable output) --

    def _from_servo_output_raw(self, msg: Any, _now: int) -> list[float] | None:
        port: int = msg.port
        if port > 1:
            return None  # ports 2.. would be channels 33..: more than the mixer takes
        other = 1 - port
        if not self._other_port_seen[port]:
            # The other port missed a whole round of this one. ArduPilot stops sending a port
            # once all its channels are off, so its last values must not be held: absent.
            start = other * _SERVO_PORT_CHANNELS
            self._servo[start : start + _SERVO_PORT_CHANNELS] = [_NAN] * _SERVO_PORT_CHANNELS
        self._other_port_seen[port] = False
        self._other_port_seen[other] = True
        base = port * _SERVO_PORT_CHANNELS
        for i, name in enumerate(_SERVO_FIELDS):
            raw: int = getattr(msg, name)  # 0 = no output; MAVLink 1 carries servo1..8 only
            self._servo[base + i] = float(raw) if raw else _NAN
        return self._servo + [_NAN] * len(AXIS_NAMES)

    def _from_actuator_output_status(self, msg: Any, _now: int) -> list[float] | None:
        active: int = msg.active
        values = [
            _finite_or_nan(value) if active >> i & 1 else _NAN
            for i, value in enumerate(msg.actuator[:CHANNEL_COUNT])
        ]
        return values + [_NAN] * (INPUT_VECTOR_LEN - len(values))

    def _from_hil_actuator_controls(self, msg: Any, now: int) -> list[float] | None:
        self._sink.on_armed(bool(msg.mode & _ARMED_FLAG), now)
        values = [_finite_or_nan(value) for value in msg.controls[:_HIL_CHANNELS]]
        return values + [_NAN] * (INPUT_VECTOR_LEN - len(values))

    def _from_actuator_control_target(self, msg: Any, _now: int) -> list[float] | None:
        if msg.group_mlx != 0:
            return None  # group 0 is the flight controls; others are gimbal, payload, ...
        values = [_NAN] * INPUT_VECTOR_LEN
        for slot, value in zip(_AXIS_SLOTS, msg.controls, strict=False):
            values[slot] = _finite_or_nan(value)
        return values

    def _from_set_actuator_control_target(self, msg: Any, now: int) -> list[float] | None:
        if msg.target_system not in (0, self._mav.srcSystem) or msg.target_component not in (
            0,
            self._config.component_id,
        ):
            return None  # a command addressed to another component
        return self._from_actuator_control_target(msg, now)

    # -- heartbeat thread ------------------------------------------------------------------

    def _run_heartbeat(self) -> None:
        beat_period_ns = round(1e9 / self._config.heartbeat_hz)
        next_beat = next_check = time.monotonic_ns()
        while True:
            now = time.monotonic_ns()
            if now >= next_beat:
                self.send(
                    self._mav.heartbeat_encode(
                        dialect.MAV_TYPE_ONBOARD_CONTROLLER,
                        dialect.MAV_AUTOPILOT_INVALID,
                        0,
                        0,
                        dialect.MAV_STATE_ACTIVE,
                    )
                )
                next_beat = max(next_beat + beat_period_ns, now)
            if now >= next_check:
                self._check_stream(now)
                next_check = max(next_check + _REQUEST_PERIOD_NS, now)
            if self._stop.wait(max(0, min(next_beat, next_check) - time.monotonic_ns()) / 1e9):
                return

    def _check_stream(self, now: int) -> None:
        """Once a second: notice a stopped stream, and ask for it while it is missing."""
        last = self.stats.last_output_ns
        if last and now - last <= _REQUEST_PERIOD_NS:
            self._requesting = False
            return
        if self.stats.output_rate_hz > 0:
            log.warning(
                "no %s from %d/%d for %.1f s",
                self._output_name,
                *self._autopilot,
                (now - last) / 1e9,
            )
        self.stats.output_rate_hz = 0.0
        self._logged_rate_hz = 0.0
        rate_hz = self._config.stream_rate_hz
        if rate_hz <= 0:
            return
        log.log(
            logging.DEBUG if self._requesting else logging.INFO,
            "asking %d/%d for %s at %.0f Hz (MAV_CMD_SET_MESSAGE_INTERVAL)",
            *self._autopilot,
            self._output_name,
            rate_hz,
        )
        self._requesting = True
        self.send(
            self._mav.command_long_encode(
                *self._autopilot,
                dialect.MAV_CMD_SET_MESSAGE_INTERVAL,
                0,
                float(self._output_msg_id),
                float(round(1e6 / rate_hz)),  # interval in µs
                0,
                0,
                0,
                0,
                0,  # param7 0: the flight stack's default target (us, the requester)
            )
        )
