"""A recording ready to draw: its ESCs' series and its spans, in seconds since its start.

:func:`load_flight` reads both files of a recording; :func:`flight` (pure) puts a capture's
series and a tlog's events together, on one time axis: both files are stamped with wall time,
and the flight starts at the first record of either.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Final

from bridge.capture import read_capture
from bridge.errors import ConfigError
from bridge.escs import registry
from bridge.plot.mcap_flight import read_mcap
from bridge.plot.recording import RecordingFiles, StatusText, TlogEvents, read_tlog
from bridge.plot.series import (
    DEFAULT_POLE_PAIRS,
    CanSummary,
    CaptureSeries,
    EscSeries,
    capture_series,
    guess_family,
    match_escs,
)
from bridge.plot.spans import Span, armed_spans, bridge_spans, stopped_while_armed

GUESS_FRAMES: Final = 5000
"""How many frames from the capture's start decide its family when none is named."""
SOURCES: Final = ("auto", "capture", "mcap")
"""What :func:`load_flight` reads: the candump log and the tlog (``capture``), the ``.mcap``, or
(``auto``) the first two where either is there, else the ``.mcap``."""


@dataclass(frozen=True)
class Flight:
    """A recording, ready to draw: times in seconds since :attr:`start_wall_s`."""

    name: str
    start_wall_s: float
    """Wall time of the first record in either file (seconds since the Unix epoch)."""
    duration_s: float
    escs: tuple[EscSeries, ...]
    spans: tuple[Span, ...]
    texts: tuple[StatusText, ...]
    can: CanSummary
    tlog_records: int = 0
    tlog_bad_records: int = 0

    def spans_of(self, kind: str) -> tuple[Span, ...]:
        return tuple(s for s in self.spans if s.kind == kind)


def flight(
    name: str,
    captured: CaptureSeries,
    tlog: TlogEvents,
    ids: Sequence[int] | None = None,
    channels: Sequence[int] | None = None,
) -> Flight:
    """The recording ``name`` ready to draw, from its capture and tlog.

    Raises:
        ConfigError: neither file holds anything, or ``channels`` has not one entry per ESC.
    """
    starts = [t for t in (captured.first_s, tlog.first_s) if t is not None]
    ends = [t for t in (captured.last_s, tlog.last_s) if t is not None]
    if not starts or not ends:
        raise ConfigError(f"recording {name}: both its files are empty; nothing to plot")
    start, end = min(starts), max(ends)
    armed = armed_spans(tlog.heartbeats, end)
    spans = [
        *armed,
        *bridge_spans(tlog.texts, end),
        *stopped_while_armed(captured.all_stopped, armed),
    ]
    return Flight(
        name,
        start,
        end - start,
        tuple(esc.shifted(start) for esc in match_escs(captured, ids, channels)),
        tuple(sorted((span.shifted(start) for span in spans), key=lambda s: s.start_s)),
        tuple(
            StatusText(t.t_s - start, t.severity, t.text, t.system, t.component) for t in tlog.texts
        ),
        captured.summary,
        tlog.records,
        tlog.bad_records,
    )


def load_flight(
    files: RecordingFiles,
    protocol: str = "auto",
    ids: Sequence[int] | None = None,
    channels: Sequence[int] | None = None,
    pole_pairs: Sequence[int] | int = DEFAULT_POLE_PAIRS,
    source: str = "auto",
) -> Flight:
    """Read a recording into a :class:`Flight`, from the files ``source`` names
    (:data:`SOURCES`). ``protocol``: a family's name, or "auto" for the one that reads most of
    the capture's first :data:`GUESS_FRAMES` frames. ``pole_pairs``: one for every ESC, or one
    per ESC of ``ids``. An MCAP needs neither (it holds rpm, and names its family and ESCs).

    Raises:
        ConfigError: a file is missing or unreadable, the capture holds no frame any family
            reads, or ``channels``/``pole_pairs`` do not fit ``ids``.
        ValueError: ``protocol`` names no family.
    """
    if source == "mcap" or (source == "auto" and not files.has_capture()):
        if not files.mcap_path.is_file():
            raise ConfigError(
                f"recording {files.name} in {files.directory}: its MCAP {files.mcap_path.name} "
                "is missing (esc-bridge run --record writes one beside the .log and .tlog)"
            )
        captured, events, recorded_ids = read_mcap(files.mcap_path)
        return flight(files.name, captured, events, ids or recorded_ids, channels)
    files.check()
    if protocol == "auto":
        head = list(itertools.islice(read_capture(files.log_path), GUESS_FRAMES))
        if not head:
            raise ConfigError(f"{files.log_path}: no CAN frame in it; nothing to plot")
        guessed = guess_family(head, ids)
        if guessed is None:
            raise ConfigError(
                f"{files.log_path}: no ESC family reads its frames; expected a capture of "
                f"{', '.join(f.title for f in registry.families())} ESCs"
            )
        family = guessed
    else:
        family = registry.family(protocol)
    if isinstance(pole_pairs, int):
        pairs: Mapping[int, int] | int = pole_pairs
    elif ids is not None and len(pole_pairs) == len(ids):
        pairs = dict(zip(ids, pole_pairs, strict=True))
    else:
        raise ConfigError(
            f"pole pairs {list(pole_pairs)}: expected one number, or one per ESC of the ESC list"
        )
    captured = capture_series(read_capture(files.log_path), family, pairs, ids)
    return flight(files.name, captured, read_tlog(files.tlog_path), ids, channels)
