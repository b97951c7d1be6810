"""Reading CAN captures in any format python-can reads, line by line where the format has lines.

python-can's readers stop at the first line they cannot parse. A user holding the capture of a
misbehaving bus wants everything around that line, so text formats are read through a line
source that counts lines: when a reader raises, the line is reported as :class:`BadLine` and a
fresh reader resumes after it, with the file's header replayed so that header state (the ASC
number base, the TRC column layout, the CSV header row) is the same as before.
Binary formats (.blf, .mf4, .db) cannot be resynchronised: an error there ends the read.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Collection, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO, cast

import can
from can.io.generic import MessageReader

from bridge.errors import ConfigError, FrameError
from bridge.escs import registry
from bridge.escs.family import EscFamily, EscFrame

# Text formats python-can reads, with their fixed header length in lines (None: the header
# runs until the first frame); the rest are binary.
TEXT_HEADER_LINES: dict[str, int | None] = {".log": 0, ".csv": 1, ".asc": None, ".trc": None}
TEXT_SUFFIXES = frozenset(TEXT_HEADER_LINES)
BINARY_SUFFIXES = frozenset({".blf", ".mf4", ".db"})


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

    def __init__(self, file: TextIO, header_lines: int | None) -> None:
        self._file = file
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
        return line

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
    with path.open(encoding="utf-8", errors="replace") as file:
        source = _LineSource(file, TEXT_HEADER_LINES[suffix])
        while True:
            try:
                for msg in _text_reader(suffix, source):
                    source.end_header()
                    yield msg
                return
            except Exception as exc:  # noqa: BLE001 - any parse failure is one bad line
                yield BadLine(source.line_no, source.last_line.rstrip("\r\n"), _reason(exc))
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
    for item in read_capture(path):
        if isinstance(item, BadLine):
            yield item
            continue
        candidates = fixed or registry.families_of(item.arbitration_id)
        if not candidates:
            yield UndecodedFrame(item, "", None)
            continue
        yield _decode_one(item, candidates, esc_nodes)


def _decode_one(
    msg: can.Message, candidates: Sequence[EscFamily], esc_nodes: Collection[int] | None
) -> DecodedFrame | UndecodedFrame:
    error: FrameError | None = None
    blamed = candidates[0].name
    for family in candidates:
        try:
            frame = family.decode(msg, esc_nodes)
        except FrameError as exc:
            if error is None:
                error, blamed = exc, family.name
            continue
        if frame is not None:
            return DecodedFrame(msg, family.name, frame)
    return UndecodedFrame(msg, blamed, error)
