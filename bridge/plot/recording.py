"""A recording's files, and what the plot needs from its tlog.

A recording (:mod:`bridge.telemetry.recorder`) is three files named by its start time in one
directory: the candump ``.log`` of every CAN frame (read by :mod:`bridge.capture`), the ``.tlog``
of the MAVLink traffic and the ``.mcap`` (read by :mod:`bridge.plot.mcap_flight`); the plot
draws from the first two, or from the ``.mcap`` alone. Each tlog record is an 8-byte big-endian
µs wall-clock stamp and one frame as received or sent. From the tlog the plot takes the
autopilot's HEARTBEATs (its arming state) and every STATUSTEXT (the bridge's own reports of its
output state among them); the other messages are skipped by their ID without being decoded.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

from bridge.errors import ConfigError

NAME_PREFIX: Final = "esc-bridge-"
"""Every recording's files start so (:data:`bridge.telemetry.recorder.NAME_FORMAT`)."""
LOG_SUFFIX: Final = ".log"
TLOG_SUFFIX: Final = ".tlog"
MCAP_SUFFIX: Final = ".mcap"
MAV_AUTOPILOT_INVALID: Final = 8
"""The ``autopilot`` of a HEARTBEAT from no flight stack: the bridge's own, a ground station's."""
MAV_MODE_FLAG_SAFETY_ARMED: Final = 0x80
HEARTBEAT_ID: Final = 0
STATUSTEXT_ID: Final = 253
_TLOG_STAMP_BYTES: Final = 8
_MAGIC_V1: Final = 0xFE
_MAGIC_V2: Final = 0xFD
EARLIEST_US: Final = 946_684_800_000_000
"""2000-01-01 in µs since the Unix epoch: no tlog record is older."""
LATEST_US: Final = 4_102_444_800_000_000
"""2100-01-01."""
_DAY_US: Final = 86_400_000_000


@dataclass(frozen=True, slots=True)
class Heartbeat:
    """The autopilot's HEARTBEAT: its arming state at ``t_s``."""

    t_s: float
    armed: bool


@dataclass(frozen=True, slots=True)
class StatusText:
    """A STATUSTEXT in the tlog (the bridge's own, or another system's)."""

    t_s: float
    severity: int
    text: str
    system: int
    component: int


@dataclass(frozen=True)
class TlogEvents:
    """What the plot needs from a tlog."""

    heartbeats: tuple[Heartbeat, ...] = ()
    """The autopilot's (HEARTBEATs of a flight stack: not the bridge's, not a ground station's)."""
    texts: tuple[StatusText, ...] = ()
    first_s: float | None = None
    """The first record's time."""
    last_s: float | None = None
    records: int = 0
    bad_records: int = 0
    """Records whose frame could not be read (cut short, a bad CRC)."""


# -- files --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RecordingFiles:
    """The files of one recording: ``<name>.log``, ``<name>.tlog`` and ``<name>.mcap`` in
    ``directory``."""

    directory: Path
    name: str

    @property
    def log_path(self) -> Path:
        return self.directory / f"{self.name}{LOG_SUFFIX}"

    @property
    def tlog_path(self) -> Path:
        return self.directory / f"{self.name}{TLOG_SUFFIX}"

    @property
    def mcap_path(self) -> Path:
        return self.directory / f"{self.name}{MCAP_SUFFIX}"

    def has_capture(self) -> bool:
        """Whether the candump log or the tlog is there (then both are wanted)."""
        return self.log_path.is_file() or self.tlog_path.is_file()

    def check(self) -> None:
        """The candump log and the tlog are both there.

        Raises:
            ConfigError: naming the missing file.
        """
        for path, what in ((self.log_path, "CAN capture"), (self.tlog_path, "MAVLink tlog")):
            if not path.is_file():
                raise ConfigError(
                    f"recording {self.name} in {self.directory}: its {what} {path.name} is "
                    "missing (esc-bridge run --record writes a .log and a .tlog of one name)"
                )


def find_recordings(directory: Path) -> tuple[RecordingFiles, ...]:
    """The recordings in ``directory`` (a ``--record`` directory), oldest first: every name
    that has a ``.log``, a ``.tlog`` or an ``.mcap`` (:meth:`RecordingFiles.check` tells
    whether the first two are both there).

    Raises:
        ConfigError: ``directory`` does not exist, is no directory, or holds no recording.
    """
    if not directory.exists():
        raise ConfigError(f"recording directory {directory}: no such directory")
    if not directory.is_dir():
        raise ConfigError(
            f"{directory}: not a directory; expected the directory given to esc-bridge run --record"
        )
    names = {
        path.stem
        for path in directory.iterdir()
        if path.name.startswith(NAME_PREFIX)
        and path.suffix in (LOG_SUFFIX, TLOG_SUFFIX, MCAP_SUFFIX)
        and path.is_file()
    }
    if not names:
        raise ConfigError(
            f"{directory}: not a recording; expected {NAME_PREFIX}YYYYmmdd-HHMMSS{LOG_SUFFIX} "
            f"and {TLOG_SUFFIX} (or {MCAP_SUFFIX}) in it, as esc-bridge run --record DIR writes"
        )
    return tuple(RecordingFiles(directory, name) for name in sorted(names))


# -- the tlog -------------------------------------------------------------------------------------


def tlog_records(data: bytes) -> Iterable[tuple[float, bytes | None]]:
    """Split a tlog into (time, MAVLink frame) records. A record whose stamp is no plausible
    wall time (:data:`EARLIEST_US` .. :data:`LATEST_US`, and within a day of the previous
    record's) or whose bytes make no frame starts a damaged stretch: the reader looks for the
    next good record one byte further on each time, and yields the stretch once, as
    (time of the record before it, None)."""
    i, end = 0, len(data)
    previous_us: int | None = None
    damaged = False
    while i + _TLOG_STAMP_BYTES + 2 <= end:
        stamp_us = int.from_bytes(data[i : i + _TLOG_STAMP_BYTES], "big")
        start = i + _TLOG_STAMP_BYTES
        magic, length = data[start], data[start + 1]
        size = 0
        if magic == _MAGIC_V1:
            size = 8 + length
        elif magic == _MAGIC_V2 and start + 2 < end:
            size = 12 + length + (13 if data[start + 2] & 1 else 0)
        plausible = EARLIEST_US <= stamp_us <= LATEST_US and (
            previous_us is None or abs(stamp_us - previous_us) <= _DAY_US
        )
        if size == 0 or not plausible or start + size > end:
            if not damaged:
                yield (previous_us or 0) / 1e6, None
                damaged = True
            i += 1
            continue
        damaged = False
        previous_us = stamp_us
        yield stamp_us / 1e6, data[start : start + size]
        i = start + size
    if i < end and not damaged:
        yield (previous_us or 0) / 1e6, None  # a record cut short at the end


def _message_id(frame: bytes) -> int:
    if frame[0] == _MAGIC_V1:
        return frame[5]
    return int.from_bytes(frame[7:10], "little")


def tlog_events(data: bytes, dialect: Any) -> TlogEvents:
    """The autopilot's HEARTBEATs and every STATUSTEXT of a tlog's bytes, decoded with
    ``dialect`` (a pymavlink dialect module, e.g. :func:`bridge.mavlink.load_dialect`'s)."""
    mav = dialect.MAVLink(None)
    heartbeats: list[Heartbeat] = []
    texts: list[StatusText] = []
    first_s = last_s = None
    records = bad = 0
    for t_s, frame in tlog_records(data):
        if frame is None:
            bad += 1
            continue
        records += 1
        first_s = t_s if first_s is None else first_s
        last_s = t_s
        if _message_id(frame) not in (HEARTBEAT_ID, STATUSTEXT_ID):
            continue
        try:
            msg = mav.decode(bytearray(frame))
        except Exception:  # noqa: BLE001 - pymavlink raises several kinds for one bad frame
            bad += 1
            continue
        kind = msg.get_type()
        if kind == "HEARTBEAT" and msg.autopilot != MAV_AUTOPILOT_INVALID:
            armed = bool(msg.base_mode & MAV_MODE_FLAG_SAFETY_ARMED)
            heartbeats.append(Heartbeat(t_s, armed))
        elif kind == "STATUSTEXT":
            text = (
                msg.text if isinstance(msg.text, str) else bytes(msg.text).decode(errors="replace")
            )
            texts.append(
                StatusText(
                    t_s,
                    int(msg.severity),
                    text.rstrip("\x00"),
                    msg.get_srcSystem(),
                    msg.get_srcComponent(),
                )
            )
    return TlogEvents(tuple(heartbeats), tuple(texts), first_s, last_s, records, bad)


def read_tlog(path: Path) -> TlogEvents:
    """:func:`tlog_events` of the file at ``path``, with the bridge's dialect.

    Raises:
        ConfigError: the file cannot be read.
    """
    from bridge.mavlink import load_dialect

    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ConfigError(f"tlog {path}: cannot read it: {exc.strerror or exc}") from exc
    return tlog_events(data, load_dialect())
