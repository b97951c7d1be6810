"""What the byte-stream transports (TCP either side, serial) share: bounded reads, a bounded
pending buffer for writes, loss handling and reopening with backoff (see
:mod:`bridge.mavlink.transport`)."""

from __future__ import annotations

import logging
import random
import time
from abc import abstractmethod
from collections import deque
from typing import Final

from bridge.mavlink.endpoints import Endpoint
from bridge.mavlink.transport.base import AutopilotTransport, reason

__all__ = ["READ_SIZE", "ReopeningStream", "StreamTransport"]

log = logging.getLogger(__name__)

READ_SIZE: Final = 4096
"""Bytes per stream read."""
_BACKOFF_FIRST_S: Final = 0.1  # a restarting TCP peer is often listening again within this
_BACKOFF_CAP_S: Final = 5.0
_NS_PER_S: Final = 1_000_000_000


class StreamTransport(AutopilotTransport):
    """What TCP (either side) and serial share: reads of up to 4096 bytes, a bounded pending
    buffer for writes, and loss handling."""

    def __init__(self, endpoint: Endpoint, pending_limit_bytes: int) -> None:
        super().__init__(endpoint)
        if pending_limit_bytes <= 0:
            raise ValueError(f"pending_limit_bytes {pending_limit_bytes} is not positive")
        self._pending_limit = pending_limit_bytes
        self._pending = bytearray()
        # The sizes of the frames (the first: of its unsent rest) in _pending, oldest first, so
        # a lost stream counts the frames it took with it.
        self._pending_frames: deque[int] = deque()
        self._fd: int | None = None
        self._ever_connected = False
        self._down_since_ns = time.monotonic_ns()

    # What a subclass provides: the raw operations on its connected descriptor, which raise
    # OSError (BlockingIOError: not now).

    @abstractmethod
    def _read_some(self) -> bytes | None:
        """Up to 4096 bytes; b"" at the end of the stream; None (or BlockingIOError) when
        there is nothing to read now."""

    @abstractmethod
    def _write_some(self, data: bytes | bytearray) -> int: ...

    @abstractmethod
    def _close_stream(self) -> None:
        """Close the connected descriptor (only)."""

    @abstractmethod
    def _on_lost(self, reason: str) -> None:
        """Log the loss and arrange the way back (a reopen after backoff, a new client)."""

    def fileno(self) -> int | None:
        return self._fd

    def wants_write(self) -> bool:
        return bool(self._pending)

    def recv(self) -> tuple[bytes, int] | None:
        if self._fd is None:
            return None
        try:
            data = self._read_some()
        except BlockingIOError:
            return None
        except OSError as exc:  # ECONNRESET, ETIMEDOUT; EIO from a serial port that went away
            self._lose(reason(exc))
            return None
        if data is None:
            return None
        now_ns = time.monotonic_ns()
        if not data:  # readable yet empty: the end of the stream (a hang-up on a tty)
            self._lose("closed by the other end")
            return None
        self.stats.reads += 1
        self.stats.bytes_in += len(data)
        return data, now_ns

    def send(self, frame: bytes) -> bool:
        if self._fd is None or len(frame) > self._pending_limit:
            self.stats.frames_dropped += 1
            return False
        if self._pending:
            self._flush()
            if self._fd is None:  # the flush found the stream lost
                self.stats.frames_dropped += 1
                return False
        if self._pending:  # still behind: the frame waits its turn, or does not fit
            if len(self._pending) + len(frame) > self._pending_limit:
                self.stats.frames_dropped += 1
                return False
            self._pending += frame
            self._pending_frames.append(len(frame))
            self.stats.frames_sent += 1
            return True
        try:
            written = self._write_some(frame)
        except BlockingIOError:
            written = 0
        except OSError as exc:  # EPIPE, ECONNRESET; EIO from a serial port that went away
            self.stats.frames_dropped += 1
            self._lose(reason(exc))
            return False
        self.stats.bytes_out += written
        self.stats.frames_sent += 1
        if written < len(frame):
            self._pending += frame[written:]
            self._pending_frames.append(len(frame) - written)
        return True

    def _flush(self) -> None:
        """Write what the kernel takes of the pending bytes now."""
        try:
            written = self._write_some(self._pending)
        except BlockingIOError:
            return
        except OSError as exc:
            self._lose(reason(exc))
            return
        self.stats.bytes_out += written
        del self._pending[:written]
        frames = self._pending_frames
        while frames and written >= frames[0]:
            written -= frames.popleft()
        if frames:
            frames[0] -= written

    def _drop_pending(self) -> None:
        self.stats.frames_dropped += len(self._pending_frames)
        self._pending.clear()
        self._pending_frames.clear()

    def _lose(self, reason: str) -> None:
        """The stream ended or failed: close it, drop what was pending, find a way back."""
        self._close_stream()
        self._drop_pending()
        self.stats.connected = False
        self.stats.last_error = reason
        self._logged_error = ""  # the first failure to come back is news again
        self._down_since_ns = time.monotonic_ns()
        self._on_lost(reason)

    def _connected(self, fd: int, detail: str) -> None:
        """A stream is up on ``fd`` (``detail`` says how, for the log): count it, say so once."""
        if self._ever_connected:
            self.stats.reconnects += 1
            down_s = 0.0 if self.stats.connected else time.monotonic_ns() - self._down_since_ns
            log.info(
                "MAVLink %s %s (reconnect %d, after %.1f s without a connection)",
                self.endpoint.url,
                detail,
                self.stats.reconnects,
                down_s / _NS_PER_S,
            )
        else:
            log.info("MAVLink %s %s", self.endpoint.url, detail)
        self._fd = fd
        self.stats.connected = True
        self._logged_error = ""
        self._ever_connected = True

    def _close_all(self) -> None:
        if self._fd is not None:
            self._close_stream()
        self._drop_pending()


class ReopeningStream(StreamTransport):
    """A stream this side opens (TCP client, serial): reopened after a loss, with jittered,
    capped exponential backoff, by :meth:`service`."""

    def __init__(self, endpoint: Endpoint, pending_limit_bytes: int) -> None:
        super().__init__(endpoint, pending_limit_bytes)
        self._retry_at_ns = 0
        self._backoff_s = _BACKOFF_FIRST_S

    def _schedule_retry(self) -> None:
        # Jitter keeps several bridges that lost the same router from retrying in lockstep.
        delay_s = self._backoff_s * random.uniform(0.5, 1.0)
        self._retry_at_ns = time.monotonic_ns() + round(delay_s * _NS_PER_S)
        self._backoff_s = min(self._backoff_s * 2, _BACKOFF_CAP_S)

    def _attempt_failed(self, reason: str) -> None:
        self._note_trouble(
            reason,
            "MAVLink %s not available (%s); retrying in the background",
            self.endpoint.url,
            reason,
        )
        self._schedule_retry()

    def _on_lost(self, reason: str) -> None:
        log.warning("MAVLink %s lost (%s); reconnecting", self.endpoint.url, reason)
        self._logged_error = reason  # a first retry failing the same way is no news
        self._backoff_s = _BACKOFF_FIRST_S
        self._schedule_retry()

    def _connected(self, fd: int, detail: str) -> None:
        super()._connected(fd, detail)
        self._backoff_s = _BACKOFF_FIRST_S
