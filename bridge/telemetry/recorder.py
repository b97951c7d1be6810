"""Recording a session to disk: every CAN frame as a candump log, the MAVLink traffic as a tlog,
and the flight as an MCAP.

:meth:`Recording.open` creates, in a directory, three files named by the start time::

    esc-bridge-20240405-193012.log    candump -L lines: (1712345678.123456) can0 1F4E5201#B90B4C04
    esc-bridge-20240405-193012.tlog   MAVLink: 8-byte big-endian µs timestamp + raw message, ...
    esc-bridge-20240405-193012.mcap   JSON channels: ESC telemetry, commands, outputs, logs

The ``.log`` is what ``esc-bridge decode`` and python-can's ``CanutilsLogReader`` read; the
``.tlog`` is what MAVProxy, QGroundControl and pymavlink read; the ``.mcap`` is what Foxglove and
PlotJuggler open (:mod:`bridge.telemetry.mcap_out` writes it, :attr:`Recording.mcap`).
:meth:`Recording.can` is the CAN reader's recorder: it runs on the reader thread for every
frame (thousands a second), so it only formats a line and appends it to a list. A writer thread
moves the lines to the file at least once a second and flushes both files;
:meth:`Recording.close` writes the rest.

The tlog is handed out as a plain binary file (:attr:`Recording.tlog`): the MAVLink link writes
its records itself, under its own lock.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path
from types import TracebackType
from typing import BinaryIO, TextIO

import can

from bridge._compat import Self
from bridge.config import CanConfig
from bridge.errors import ConfigError
from bridge.mavlink.traffic import TrafficReader
from bridge.telemetry.mcap_out import McapRecording

log = logging.getLogger(__name__)

FLUSH_INTERVAL_S = 0.5
"""How often the writer thread moves recorded lines to disk (at most a second apart)."""
NAME_FORMAT = "esc-bridge-%Y%m%d-%H%M%S"
"""Local start time; a second recording started within the same second gets ``-1``, ``-2``..."""
DEFAULT_CHANNEL = "can0"
MCAP_SUFFIX = ".mcap"

# Linux SocketCAN's error-frame flag and the bus-error class, as candump writes error frames
# (python-can's CanutilsLogReader reads a frame with both bits as an error frame).
_CAN_ERR_FLAG = 0x20000000
_CAN_ERR_BUSERROR = 0x00000080
_CANFD_BRS = 0x01
_CANFD_ESI = 0x02
_MAX_SUFFIX = 1000


def candump_line(msg: can.Message, channel: str, timestamp: float) -> str:
    """One ``candump -L`` line for ``msg`` (with its newline)."""
    data = msg.data.hex().upper() if msg.data else ""
    if msg.is_error_frame:
        frame = f"{_CAN_ERR_FLAG | _CAN_ERR_BUSERROR | msg.arbitration_id:08X}#{data}"
    else:
        frame = f"{msg.arbitration_id:08X}#" if msg.is_extended_id else f"{msg.arbitration_id:03X}#"
        if msg.is_remote_frame:
            frame += f"R{msg.dlc}" if msg.dlc else "R"
        elif msg.is_fd:
            brs = _CANFD_BRS if msg.bitrate_switch else 0
            esi = _CANFD_ESI if msg.error_state_indicator else 0
            frame += f"#{brs | esi:X}{data}"
        else:
            frame += data
    return f"({timestamp:.6f}) {channel} {frame}\n"


class _Writer:
    """The lines recorded but not yet written, and the thread that writes them.

    Kept apart from :class:`Recording` so that the thread holds no reference to it, and a
    recording that is dropped without :meth:`Recording.close` can still be noticed.
    """

    def __init__(self, log_file: TextIO, tlog: BinaryIO) -> None:
        self.log_file = log_file
        self.tlog = tlog
        self.pending: list[str] = []
        self.lock = threading.Lock()  # guards pending: held for one append or one swap
        self.write_lock = threading.Lock()  # one writer of the files at a time
        self.errors = 0
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, name="recorder", daemon=True)

    def _run(self) -> None:
        while not self.stop.wait(FLUSH_INTERVAL_S):
            self.write()

    def write(self) -> None:
        """Move the pending lines to the log file and flush both files."""
        with self.write_lock:
            with self.lock:
                lines, self.pending = self.pending, []
            try:
                if lines:
                    self.log_file.write("".join(lines))
                self.log_file.flush()
                self.tlog.flush()
            except (OSError, ValueError) as exc:  # ValueError: a file closed under us
                self.errors += 1
                if self.errors == 1 or self.errors % 100 == 0:
                    log.warning("recording: cannot write (%d times): %s", self.errors, exc)


class Recording:
    """A candump ``.log`` of every CAN frame, a MAVLink ``.tlog`` and an ``.mcap``, named by
    start time.

    A context manager; :meth:`close` tolerates a second call.
    """

    def __init__(
        self,
        log_path: Path,
        tlog_path: Path,
        log_file: TextIO,
        tlog: BinaryIO,
        channel: str,
        mcap: McapRecording,
    ) -> None:
        """Use :meth:`open`."""
        self.log_path = log_path
        """The candump log."""
        self.tlog_path = tlog_path
        """The MAVLink tlog."""
        self.mcap_path = log_path.with_suffix(MCAP_SUFFIX)
        self.mcap = mcap
        """The MCAP: fed by the CAN reader, the MAVLink link, the supervisor and the log."""
        self.tlog = tlog
        """The tlog file, opened ``wb``: whoever writes MAVLink appends its records here."""
        self.channel = channel
        """The channel name written on every candump line."""
        self.frames = 0
        """Frames recorded so far."""
        self._writer = _Writer(log_file, tlog)
        self._closed = False
        self._writer.thread.start()

    @classmethod
    def open(
        cls,
        directory: Path,
        can_config: CanConfig | None = None,
        *,
        traffic: TrafficReader | None = None,
        metadata: dict[str, str] | None = None,
    ) -> Recording:
        """Create ``directory`` if needed and the three files in it, named by the current time.

        The candump channel name is ``can_config.channel`` (``can0`` without a config).
        ``traffic`` reads the MAVLink frames for the MCAP (None: the MCAP has none of them);
        ``metadata``: its ``esc-bridge`` record (:func:`bridge.telemetry.mcap_channels.metadata`).

        Raises:
            ConfigError: naming the directory, when it or a file in it cannot be created.
        """
        directory = Path(directory)
        channel = _channel_name(can_config.channel if can_config else DEFAULT_CHANNEL)
        try:
            directory.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise ConfigError(
                f"recording directory {directory}: cannot create it: {exc.strerror or exc}"
            ) from exc
        stem = time.strftime(NAME_FORMAT)
        for suffix in range(_MAX_SUFFIX):
            name = stem if suffix == 0 else f"{stem}-{suffix}"
            log_path, tlog_path = directory / f"{name}.log", directory / f"{name}.tlog"
            try:
                log_file = log_path.open("x", encoding="ascii", newline="\n")
            except FileExistsError:
                continue
            except OSError as exc:
                raise _cannot_create(directory, log_path, exc) from exc
            mcap_path = log_path.with_suffix(MCAP_SUFFIX)
            try:
                tlog = tlog_path.open("xb")
            except OSError as exc:
                log_file.close()
                log_path.unlink(missing_ok=True)
                if isinstance(exc, FileExistsError):
                    continue
                raise _cannot_create(directory, tlog_path, exc) from exc
            try:
                mcap_file = mcap_path.open("xb")
            except OSError as exc:
                for file, path in ((log_file, log_path), (tlog, tlog_path)):
                    file.close()
                    path.unlink(missing_ok=True)
                if isinstance(exc, FileExistsError):
                    continue
                raise _cannot_create(directory, mcap_path, exc) from exc
            log.info(
                "recording CAN to %s, MAVLink to %s and both to %s",
                log_path,
                tlog_path.name,
                mcap_path.name,
            )
            mcap = McapRecording(mcap_file, traffic, metadata)
            return cls(log_path, tlog_path, log_file, tlog, channel, mcap)
        raise ConfigError(
            f"recording directory {directory}: {stem}.log and {_MAX_SUFFIX - 1} more exist"
        )

    def can(self, msg: can.Message) -> None:
        """Record one frame, stamped ``msg.timestamp`` (the receive time) or, if it has none,
        now. Thread-safe and cheap: the line reaches the file within a second. Frames that
        arrive after :meth:`close` are dropped."""
        if self._closed:
            return  # a reader still running after close(): nowhere to write to
        line = candump_line(msg, self.channel, msg.timestamp or time.time())
        writer = self._writer
        with writer.lock:
            writer.pending.append(line)
            self.frames += 1

    def flush(self) -> None:
        """Write what is recorded so far and flush both files now."""
        if not self._closed:
            self._writer.write()

    def close(self) -> None:
        """Write the rest, flush and close the files; a second call does nothing."""
        if self._closed:
            return
        self._closed = True
        self.mcap.close()
        writer = self._writer
        writer.stop.set()
        writer.thread.join()
        writer.write()
        for file in (writer.log_file, writer.tlog):
            try:
                file.close()
            except OSError as exc:
                log.warning("recording: closing %s failed: %s", file.name, exc)

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def __del__(self) -> None:
        if not getattr(self, "_closed", True):
            log.warning("recording %s was not closed; closing it now", self.log_path)
            self.close()


def _cannot_create(directory: Path, path: Path, exc: OSError) -> ConfigError:
    return ConfigError(
        f"recording directory {directory}: cannot create {path.name}: {exc.strerror or exc}"
    )


def _channel_name(channel: str) -> str:
    # A candump line is three space-separated fields: the channel must be one word.
    name = "".join("_" if c.isspace() else c for c in channel.strip())
    return name or DEFAULT_CHANNEL
