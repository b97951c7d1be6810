"""The link's recording: every MAVLink frame received and sent, in .tlog form.

A .tlog record is the time it was logged, in µs since the Unix epoch as 8 bytes big-endian,
then the frame as on the wire. The caller opens and closes the file; :class:`Tlog` appends to
it from any thread and flushes it, and hands each frame with its stamp to a tap, if given (the
MCAP recording).
"""

from __future__ import annotations

import logging
import struct
import threading
import time
from collections.abc import Callable
from typing import BinaryIO, Final

from bridge.mavlink.stats import LinkStats, log_sparsely

__all__ = ["Tlog"]

log = logging.getLogger(__name__)

_TLOG_STAMP: Final = struct.Struct(">Q")


class Tlog:
    """Appends frames to ``file``, stamped when appended; a failed append is counted in
    ``stats.tlog_errors`` and logged sparsely, never raised. ``tap`` gets every frame too,
    with its stamp (µs since the epoch); it runs on the caller's thread, so it must be quick."""

    def __init__(
        self, file: BinaryIO, stats: LinkStats, tap: Callable[[int, bytes], None] | None = None
    ) -> None:
        self._file = file
        self._stats = stats
        self._tap = tap
        self._lock = threading.Lock()

    def record(self, frame: bytes) -> None:
        """Append one frame, stamped now."""
        with self._lock:
            stamp_us = time.time_ns() // 1000
            try:
                self._file.write(_TLOG_STAMP.pack(stamp_us) + frame)
            except (OSError, ValueError) as exc:  # ValueError: the file was closed
                self._stats.tlog_errors += 1
                log_sparsely(
                    log,
                    logging.WARNING,
                    self._stats.tlog_errors,
                    "could not append to the MAVLink recording: %s",
                    exc,
                )
            if self._tap is not None:
                self._tap(stamp_us, frame)

    def flush(self) -> None:
        """Flush the file; trouble is logged, never raised."""
        with self._lock:
            try:
                self._file.flush()
            except (OSError, ValueError) as exc:  # ValueError: the file was closed first
                log.warning("could not flush the MAVLink recording: %s", exc)
