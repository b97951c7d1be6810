"""Reading CAN captures in any format python-can reads, line by line where the format has lines.

python-can's readers stop at the first line they cannot parse. A user holding the capture of a
misbehaving bus wants everything around that line, so text formats are read through a line
source that counts lines: when a reader raises, the line is reported as :class:`BadLine` and a
fresh reader resumes after it, with the file's header replayed so that header state (the ASC
number base, the TRC column layout, the CSV header row) is the same as before.
Binary formats (.blf, .mf4, .db) cannot be resynchronised: an error there ends the read.

A ``.log`` may hold ``candump -L`` lines (``(1712345678.123456) can0 1F4E5201#B90B4C04``, what
python-can reads) or candump's default output, as printed on a terminal (``  can0  1F4E5201
[4]  B9 0B 4C 04``, with or without ``-t`` timestamps); the latter are rewritten into the former
line by line (:func:`candump_line`), so one capture may even mix them.
"""

from __future__ import annotations

import re
from collections import Counter
from collections.abc import Callable, Collection, Iterator, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import TextIO, cast

import can
from can.io.generic import MessageReader

from bridge.errors import ConfigError, FrameError
from bridge.escs import registry
from bridge.escs.family import EscDecoder, EscFamily, EscFrame

# Text formats python-can reads, with their fixed header length in lines (None: the header
# runs until the first frame); the rest are binary.
TEXT_HEADER_LINES: dict[str, int | None] = {".log": 0, ".csv": 1, ".asc": None, ".trc": None}
TEXT_SUFFIXES = frozenset(TEXT_HEADER_LINES)
BINARY_SUFFIXES = frozenset({".blf", ".mf4", ".db"})

CANDUMP_FORMS = (
    "expected a candump line: `candump -L` such as '(1712345678.123456) can0 1F4E5201#B90B4C04', "
    "or candump's default such as '  can0  1F4E5201   [4]  B9 0B 4C 04'"
)
"""What a ``.log`` line may be, for the message about one that is neither."""

# candump's default line: an optional "(time)" (-t a, d, z: seconds; -t A: a date and time),
# the interface, "RX - -"-style flags with -x, the ID (3 hex digits: 11-bit, 8: 29-bit), the
# length in brackets ([08] for CAN FD), then the bytes or "remote request", and with -a the
# bytes as ASCII in quotes.
_CANDUMP = re.compile(
    r"\s*(?:\((?P<time>[^)]*)\)\s+)?(?P<channel>\S+)\s+(?:(?:RX|TX)\s+\S+\s+\S+\s+)?"
    r"(?P<id>[0-9A-Fa-f]{3}|[0-9A-Fa-f]{8})\s+\[(?P<length>\d{1,2})\]"
    r"(?P<rest>(?:\s+[0-9A-Fa-f]{2})*|\s+remote request)\s*(?:'.*')?\s*"
)


def candump_line(line: str) -> str | None:
    """A line of candump's default output as a ``candump -L`` line (the time 0 when it has
    none, or seconds since the epoch for -t A's local date and time); None when it is not one
    (or its bytes are not as many as its length says)."""
    match = _CANDUMP.fullmatch(line.rstrip("\r\n"))
    if match is None:
        return None
    stamp = match["time"] or "0.0"
    if " " in stamp:  # -t A: "2024-04-05 19:30:12.123456", local time
        try:
            stamp = f"{datetime.strptime(stamp, '%Y-%m-%d %H:%M:%S.%f').timestamp():.6f}"
        except ValueError:
            return None
    rest = match["rest"].strip()
    if rest == "remote request":
        payload = f"R{int(match['length'])}"
    else:
        payload = rest.replace(" ", "")
        if len(payload) != 2 * int(match["length"]):  # candump prints every byte it counts
            return None
        if match["length"].startswith("0") or len(payload) > 16:  # CAN FD: "##<flags><data>"
            payload = "#0" + payload
    return f"({stamp}) {match['channel']} {match['id']}#{payload}\n"


@dataclass(frozen=True, slots=True)
class BadLine:
    """A line of a capture that could not be read (``line_no`` counts from 1)."""

    line_no: int
    text: str
    reason: str


class _LineSource:
    """Iterates a text file's lines for a python-can reader, counting them.

    Until :meth:`end_header` it also keeps every line it hands out, so the header can be
    replayed to a fresh reader; replayed lines come first and are not counted again.
    """

    def __init__(
        self, file: TextIO, header_lines: int | None, translate: Callable[[str], str] | None = None
    ) -> None:
        self._file = file
        self._translate = translate
        self._replay: list[str] = []
        # Formats with a fixed header know it at once; ASC and TRC only at their first frame.
        self._kept: list[str] | None = [] if header_lines is None else None
        self.header: list[str] | None = None
        self.line_no = 0
        if header_lines is not None:
            self.header = [next(file, "") for _ in range(header_lines)]
            self.line_no = header_lines
            self._replay = list(self.header)
        self.last_line = ""

    def end_header(self) -> None:
        """The last line handed out held the first frame: all before it was header."""
        if self._kept is not None:
            self.header = self._kept[:-1]
            self._kept = None

    def replay_header(self) -> None:
        self._replay = list(self.header or [])

    def __iter__(self) -> _LineSource:
        return self

    def __next__(self) -> str:
        if self._replay:
            return self._replay.pop(0)
        line = next(self._file)
        self.line_no += 1
        self.last_line = line
        if self._kept is not None:
            self._kept.append(line)
        return line if self._translate is None else self._translate(line)

    def close(self) -> None:
        """python-can readers close their file when done; the caller owns this one."""


def read_capture(path: str | Path) -> Iterator[can.Message | BadLine]:
    """Yield the frames of a capture in order, and a :class:`BadLine` for each unreadable line.

    Raises:
        ConfigError: the file does not exist or its format is not one python-can reads.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if not path.is_file():
        raise ConfigError(f"capture {path}: no such file")
    if suffix in TEXT_SUFFIXES:
        yield from _read_text(path, suffix)
    elif suffix in BINARY_SUFFIXES:
        yield from _read_binary(path)
    else:
        known = ", ".join(sorted(TEXT_SUFFIXES | BINARY_SUFFIXES))
        raise ConfigError(f"capture {path}: unknown format {suffix!r}; expected one of {known}")


def _text_reader(suffix: str, source: _LineSource) -> MessageReader:
    readers: dict[str, Callable[[TextIO], MessageReader]] = {
        ".log": can.CanutilsLogReader,
        ".asc": can.ASCReader,
        ".csv": can.CSVReader,
        ".trc": can.TRCReader,
    }
    # The readers only iterate their file's lines (and close it), which the line source does.
    return readers[suffix](cast(TextIO, source))


def _read_text(path: Path, suffix: str) -> Iterator[can.Message | BadLine]:
    candump = suffix == ".log"
    with path.open(encoding="utf-8", errors="replace") as file:
        source = _LineSource(
            file,
            TEXT_HEADER_LINES[suffix],
            (lambda line: candump_line(line) or line) if candump else None,
        )
        while True:
            try:
                for msg in _text_reader(suffix, source):
                    source.end_header()
                    yield msg
                return
            except Exception as exc:  # noqa: BLE001 - any parse failure is one bad line
                reason = CANDUMP_FORMS if candump else _reason(exc)
                yield BadLine(source.line_no, source.last_line.rstrip("\r\n"), reason)
                if source.header is None:
                    # Still in the header: without it nothing after can be read correctly.
                    return
                source.replay_header()


def _read_binary(path: Path) -> Iterator[can.Message | BadLine]:
    count = 0
    try:
        with can.LogReader(path) as reader:
            for msg in reader:
                count += 1
                yield msg
    except Exception as exc:  # noqa: BLE001 - a binary capture cannot be resynchronised
        yield BadLine(0, f"after frame {count}", _reason(exc))


def _reason(exc: BaseException) -> str:
    text = str(exc) or type(exc).__name__
    return f"{type(exc).__name__}: {text}"


@dataclass(frozen=True, slots=True)
class DecodedFrame:
    """A frame of a capture that one of our protocols understood."""

    msg: can.Message
    protocol: str
    frame: EscFrame

    @property
    def type_name(self) -> str:
        return type(self.frame.message).__name__


@dataclass(frozen=True, slots=True)
class UndecodedFrame:
    """A frame no protocol understood (``error`` is None) or a malformed one of ours."""

    msg: can.Message
    protocol: str
    error: FrameError | None

    @property
    def why(self) -> str:
        """Why no family took a frame none understood (``""``: an ID in no family's space, or
        one that no family decodes)."""
        msg = self.msg
        if self.error is not None or self.protocol:
            return ""
        if msg.is_error_frame:
            return "an error frame (the CAN controller's report of a bus error)"
        if msg.is_remote_frame:
            return "a remote (RTR) frame: no ESC family here uses them"
        if not msg.is_extended_id:
            return "an 11-bit ID: every ESC family here uses 29-bit IDs (another device's frame)"
        return ""


CaptureItem = DecodedFrame | UndecodedFrame | BadLine


@dataclass
class CaptureSummary:
    """What a capture held: frames per protocol and type, and everything that was not right."""

    frames: int = 0
    by_type: Counter[str] = field(default_factory=Counter)
    errors: Counter[str] = field(default_factory=Counter)
    not_ours: int = 0
    bad_lines: int = 0

    def add(self, item: CaptureItem) -> None:
        if isinstance(item, BadLine):
            self.bad_lines += 1
            return
        self.frames += 1
        if isinstance(item, DecodedFrame):
            self.by_type[f"{item.protocol} {item.type_name}"] += 1
        elif item.error is None:
            self.not_ours += 1
        else:
            self.errors[type(item.error).__name__] += 1

    def as_dict(self) -> dict[str, object]:
        return {
            "frames": self.frames,
            "by_type": dict(self.by_type),
            "errors": dict(self.errors),
            "not_ours": self.not_ours,
            "bad_lines": self.bad_lines,
        }


def decode_capture(
    path: str | Path,
    protocol: str = "auto",
    esc_nodes: Collection[int] | None = None,
) -> Iterator[CaptureItem]:
    """Read a capture and decode each frame as ``protocol`` (a family's name), or with "auto"
    as the first family whose ID space holds it and that understands it (a malformed frame is
    reported as the first such family's); see :func:`read_capture` for what it raises.

    Raises:
        ValueError: ``protocol`` names no family.
    """
    fixed = None if protocol == "auto" else (registry.family(protocol),)
    decoders: dict[str, EscDecoder] = {}  # one per family: this capture is one stream
    for item in read_capture(path):
        if isinstance(item, BadLine):
            yield item
            continue
        data_frame = item.is_extended_id and not (item.is_remote_frame or item.is_error_frame)
        # Every family's ID space is of 29-bit data frames: other frames are no family's.
        candidates = fixed or (registry.families_of(item.arbitration_id) if data_frame else ())
        if not candidates:
            yield UndecodedFrame(item, "", None)
            continue
        yield _decode_one(item, candidates, decoders, esc_nodes)


def _decode_one(
    msg: can.Message,
    candidates: Sequence[EscFamily],
    decoders: dict[str, EscDecoder],
    esc_nodes: Collection[int] | None,
) -> DecodedFrame | UndecodedFrame:
    error: FrameError | None = None
    blamed = candidates[0].name
    for family in candidates:
        decoder = decoders.get(family.name)
        if decoder is None:
            decoder = decoders[family.name] = family.decoder()
        try:
            frame = decoder.decode(msg, esc_nodes)
        except FrameError as exc:
            if error is None:
                error, blamed = exc, family.name
            continue
        if frame is not None:
            return DecodedFrame(msg, family.name, frame)
    return UndecodedFrame(msg, blamed, error)
