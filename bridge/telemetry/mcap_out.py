"""The recording's ``.mcap``: the flight as JSON channels that Foxglove and PlotJuggler open.

What it holds is :mod:`bridge.telemetry.mcap_channels`' (its docstring lists the channels). Who
feeds it, from their own threads: the CAN reader (:class:`~bridge.telemetry.reader.StateRecorder`:
each ESC's state after each telemetry frame, every ESC's last command after each command), the
MAVLink link (every frame it receives and sends, as it writes them to the tlog), the supervisor
(the output loop's states) and the logging module (:class:`LogHandler`, the main process's log
lines).

Best effort, off every other path: a feeder only appends a tuple to a list under a short lock
(never waits on the file, never encodes). The writer thread takes the list every
:data:`WRITE_INTERVAL_S`, makes the messages (MAVLink decoding, JSON), writes them in log-time
order and closes a chunk every :data:`CHUNK_INTERVAL_S`, so a bridge that dies loses at most
that much: what is written is readable without the summary that :meth:`McapRecording.close`
adds. Past :data:`MAX_PENDING` waiting items (a writer that cannot keep up) new items are
dropped and counted. The output loop is in another process and never waits on any of it.

Times, in ns since the Unix epoch: a message's log time is when the bridge got the data (the
CAN frame's receive stamp, the MAVLink frame's tlog stamp, the log record's creation); its
publish time is the source's own where known (an autopilot's motor outputs stamped on its boot
clock, once the link knows that clock), else the log time.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any, BinaryIO, Final

from mcap.writer import CompressionType, Writer

from bridge.mavlink.traffic import MotorOutputs, TrafficReader, autopilot_stamp_unix_ns
from bridge.telemetry import mcap_channels as channels
from bridge.telemetry.mcap_channels import BridgeState
from bridge.telemetry.state import EscSnapshot, LastCommand

log = logging.getLogger(__name__)

WRITE_INTERVAL_S: Final = 0.5
"""How often the writer thread writes what was fed."""
CHUNK_INTERVAL_S: Final = 2.0
"""How often a chunk is closed and the file flushed: the most a bridge that dies loses."""
CHUNK_BYTES: Final = 4 * 1024 * 1024
"""A chunk is closed sooner when it holds this much (uncompressed)."""
MAX_PENDING: Final = 500_000
"""Items waiting for the writer beyond which new ones are dropped (~100 MB)."""
LIBRARY: Final = "esc-bridge"
_JSON: Final = json.JSONEncoder(
    separators=(",", ":"), allow_nan=False
)  # json.dumps makes one a call

# What a feeder appends: (kind, log time ns, data).
_ESC: Final = 0
_COMMANDS: Final = 1
_MAVLINK: Final = 2
_STATE: Final = 3
_LOG: Final = 4

AutopilotClock = Callable[[int], int | None]
"""The autopilot's µs since boot at a local monotonic ns (:meth:`MavlinkLink.autopilot_boot_usec
<bridge.mavlink.link.MavlinkLink.autopilot_boot_usec>`); None while unknown."""


class McapRecording:
    """The ``.mcap`` being written to ``file``, and its writer thread. Use :meth:`close` once
    (a second call does nothing); the feeding methods are safe from any thread, and do nothing
    after it."""

    def __init__(
        self,
        file: BinaryIO,
        traffic: TrafficReader | None = None,
        metadata: dict[str, str] | None = None,
    ) -> None:
        """``traffic`` reads the MAVLink frames (None: they are not recorded); ``metadata``: the
        ``esc-bridge`` metadata record (:func:`~bridge.telemetry.mcap_channels.metadata`)."""
        self._file = file
        self._traffic = traffic
        self.autopilot_clock: AutopilotClock | None = None
        """Set once the link exists: puts the autopilot's stamps on the wall clock."""
        self._writer = Writer(file, chunk_size=CHUNK_BYTES, compression=CompressionType.ZSTD)
        self._writer.start(library=LIBRARY)
        self._writer.add_metadata(channels.METADATA_NAME, metadata or {})
        self._schema_ids: dict[str, int] = {}
        self._channel_ids: dict[str, int] = {}
        self._pending: list[tuple[int, int, Any]] = []
        self._lock = threading.Lock()  # guards _pending: held for one append or one swap
        self._closed = False
        self.messages = 0
        """Messages written."""
        self.dropped = 0
        """Items dropped: the writer fell :data:`MAX_PENDING` behind."""
        self.errors = 0
        """Items that made no message (a number JSON cannot carry) and failed writes."""
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="recorder-mcap", daemon=True)
        self._thread.start()

    # -- feeding (any thread) ------------------------------------------------------------------

    def _add(self, kind: int, time_ns: int, data: Any) -> None:
        with self._lock:
            if self._closed or len(self._pending) >= MAX_PENDING:
                if not self._closed:
                    self.dropped += 1
                return
            self._pending.append((kind, time_ns, data))

    def esc(self, snapshot: EscSnapshot, time_s: float) -> None:
        """An ESC's state after a telemetry frame received at ``time_s``."""
        self._add(_ESC, round(time_s * 1e9), snapshot)

    def commands(self, commands: Sequence[LastCommand], time_s: float) -> None:
        """Every ESC's last command, after commands sent at ``time_s``."""
        self._add(_COMMANDS, round(time_s * 1e9), commands)

    def mavlink(self, stamp_us: int, frame: bytes) -> None:
        """A MAVLink frame received or sent, stamped as in the tlog (µs since the epoch)."""
        if self._traffic is not None:
            self._add(_MAVLINK, stamp_us * 1000, frame)

    def state(self, state: BridgeState) -> None:
        """A state the output loop entered, seen now."""
        self._add(_STATE, time.time_ns(), state)

    def log_record(self, record: logging.LogRecord, text: str) -> None:
        """A log line (``text``: its message, formatted)."""
        self._add(
            _LOG,
            round(record.created * 1e9),
            (
                channels.python_level(record.levelno),
                text,
                record.name,
                record.filename,
                record.lineno,
            ),
        )

    # -- writing (its own thread) --------------------------------------------------------------

    def _run(self) -> None:
        chunk_at = time.monotonic() + CHUNK_INTERVAL_S
        while not self._stop.wait(WRITE_INTERVAL_S):
            try:
                self._write()
            except Exception:  # a fault in one batch must not end the recording: it is lost
                self.errors += 1
                log.exception("recording: an MCAP batch could not be written; it is dropped")
            if time.monotonic() >= chunk_at:
                chunk_at = time.monotonic() + CHUNK_INTERVAL_S
                self._flush()

    def _write(self) -> None:
        with self._lock:
            items, self._pending = self._pending, []
        if not items:
            return
        items.sort(key=lambda item: item[1])  # log-time order; a stable sort keeps ties in turn
        clock = self.autopilot_clock
        boot_now = None if clock is None else clock(time.monotonic_ns())
        unix_now_ns = time.time_ns()
        errors = 0
        for kind, time_ns, data in items:
            publish_ns = time_ns
            if kind == _ESC:
                topic, message = channels.esc_message(data)
            elif kind == _COMMANDS:
                topic, message = channels.commands_message(data)
            elif kind == _MAVLINK:
                assert self._traffic is not None  # nothing is fed without it
                record = self._traffic.read(data)
                if record is None:
                    continue
                if isinstance(record, MotorOutputs) and record.time_usec and boot_now is not None:
                    stamp = autopilot_stamp_unix_ns(
                        record.time_usec, record.time_bits, boot_now, unix_now_ns
                    )
                    publish_ns = time_ns if stamp is None else stamp
                topic, message = channels.traffic_message(record, time_ns)
            elif kind == _STATE:
                topic, message = channels.state_message(data)
            else:
                level, text, name, file, line = data
                topic = channels.LOG_TOPIC
                message = channels.log_message(time_ns, level, text, name, file, line)
            try:
                encoded = _JSON.encode(message).encode()
                self._writer.add_message(self._channel(topic), time_ns, encoded, publish_ns)
            except ValueError:  # NaN or infinity: no JSON number
                errors += 1
                continue
            except OSError:
                errors += 1
                break  # the file: the rest of this batch would fail too
            self.messages += 1
        if errors:
            self._count_errors(errors)

    def _channel(self, topic: str) -> int:
        channel_id = self._channel_ids.get(topic)
        if channel_id is None:
            name = channels.schema_of(topic)
            schema_id = self._schema_ids.get(name)
            if schema_id is None:
                data = json.dumps(channels.SCHEMAS[name]).encode()
                schema_id = self._writer.register_schema(name, channels.SCHEMA_ENCODING, data)
                self._schema_ids[name] = schema_id
            channel_id = self._writer.register_channel(topic, channels.MESSAGE_ENCODING, schema_id)
            self._channel_ids[topic] = channel_id
        return channel_id

    def _flush(self) -> None:
        try:
            self._writer.flush()  # type: ignore[no-untyped-call]  # mcap 1.6 leaves it untyped
        except (OSError, ValueError) as exc:  # ValueError: the file was closed under us
            self._count_errors(1, exc)

    def _count_errors(self, errors: int, exc: BaseException | None = None) -> None:
        before = self.errors
        self.errors += errors
        if before == 0 or before // 100 != self.errors // 100:
            log.warning(
                "recording: %d MCAP messages or writes failed%s",
                self.errors,
                f": {exc}" if exc else " (a number JSON cannot carry, or the file)",
            )

    def close(self) -> None:
        """Write the rest and the summary, close the file; a second call does nothing."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        self._stop.set()
        self._thread.join()
        self._write()
        try:
            self._writer.finish()  # type: ignore[no-untyped-call]  # as flush
            self._file.close()
        except (OSError, ValueError) as exc:
            log.warning("recording: closing the MCAP file failed: %s", exc)
        if self.dropped:
            log.warning("recording: %d MCAP items dropped (the writer fell behind)", self.dropped)


class LogHandler(logging.Handler):
    """Passes every log record it is given to a recording's ``/bridge/log``."""

    def __init__(self, recording: McapRecording) -> None:
        super().__init__()
        self._recording = recording

    def emit(self, record: logging.LogRecord) -> None:
        try:
            text = record.getMessage()
            if record.exc_info:
                text += "\n" + logging.Formatter().formatException(record.exc_info)
        except Exception:  # noqa: BLE001 - a bad format string is the caller's; logging says so
            self.handleError(record)
            return
        self._recording.log_record(record, text)
