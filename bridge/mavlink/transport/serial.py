"""The serial transport: a terminal device opened raw, reopened by a helper thread since a USB
adapter's driver sleeps in open() (see :mod:`bridge.mavlink.transport`)."""

from __future__ import annotations

import array
import contextlib
import errno
import fcntl
import logging
import os
import queue
import termios
import threading
from typing import Final

from bridge.errors import LinkError
from bridge.mavlink.endpoints import Endpoint
from bridge.mavlink.transport.base import PENDING_LIMIT_BYTES, reason
from bridge.mavlink.transport.stream import READ_SIZE, ReopeningStream

__all__ = ["SerialTransport"]

log = logging.getLogger(__name__)


# Opening a serial device that fails with one of these may work later: the USB adapter is not
# enumerated yet (ENOENT, ENODEV, ENXIO), is going away (EIO), udev has not set its group yet
# (EACCES, EPERM), or another program still holds it (EBUSY). Anything else (ENOTTY: not a
# terminal) is a configuration mistake.
_SERIAL_TRANSIENT: Final = frozenset(
    {
        errno.ENOENT,
        errno.ENODEV,
        errno.ENXIO,
        errno.EIO,
        errno.EACCES,
        errno.EPERM,
        errno.EBUSY,
        errno.EAGAIN,
    }
)


def _open_tty(path: str, speed: int) -> int:
    """Open a terminal device raw, 8N1, no flow control, non-blocking; raises OSError."""
    # O_NONBLOCK also keeps open() from waiting for a modem's carrier; O_NOCTTY keeps the
    # device from becoming our controlling terminal.
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK | os.O_CLOEXEC)
    try:
        iflag, oflag, cflag, lflag, _, _, cc = termios.tcgetattr(fd)
        iflag &= ~(
            termios.IGNBRK
            | termios.BRKINT
            | termios.PARMRK
            | termios.ISTRIP
            | termios.INLCR
            | termios.IGNCR
            | termios.ICRNL
            | termios.IXON
            | termios.IXOFF
            | termios.IXANY
            | termios.INPCK
        )
        oflag &= ~termios.OPOST
        lflag &= ~(termios.ECHO | termios.ECHONL | termios.ICANON | termios.ISIG | termios.IEXTEN)
        cflag &= ~(termios.CSIZE | termios.PARENB | termios.CSTOPB | termios.CRTSCTS)
        cflag |= termios.CS8 | termios.CREAD | termios.CLOCAL  # CLOCAL: ignore modem lines
        cc[termios.VMIN] = 0
        cc[termios.VTIME] = 0
        termios.tcsetattr(fd, termios.TCSANOW, [iflag, oflag, cflag, lflag, speed, speed, cc])
        # Bytes that waited in the driver before we opened would be stamped as just read.
        termios.tcflush(fd, termios.TCIOFLUSH)
    except termios.error as exc:
        os.close(fd)
        code, text = exc.args
        raise OSError(code, text) from exc
    except BaseException:
        os.close(fd)
        raise
    return fd


def _close_tty(fd: int) -> None:
    """Close a terminal device without waiting for its unsent output to drain (which close()
    would do, for up to the port's closing_wait, 30 s by default)."""
    with contextlib.suppress(termios.error):
        termios.tcflush(fd, termios.TCOFLUSH)
    with contextlib.suppress(OSError):
        os.close(fd)


_OPEN_REQUEST: Final = -1
"""Asks a serial helper to open its device; a descriptor (>= 0) asks it to close that one;
None asks it to stop."""


def _serve_serial(
    path: str,
    speed: int,
    requests: queue.SimpleQueue[int | None],
    results: queue.SimpleQueue[int | OSError],
) -> None:
    """A serial transport's helper thread: opens and closes the device, which a USB adapter's
    driver may sleep in for milliseconds (cdc-acm and ftdi_sio send USB control transfers
    from open() and tcsetattr() and wait for them), so the real-time thread never does.
    Holds no reference to the transport, so a forgotten transport is still collected."""
    while True:
        request = requests.get()
        if request is None:
            # Stopped: a device opened for a transport that has closed meanwhile is closed.
            while not results.empty():
                opened = results.get()
                if isinstance(opened, int):
                    _close_tty(opened)
            return
        if request >= 0:
            _close_tty(request)
            continue
        try:
            results.put(_open_tty(path, speed))
        except OSError as exc:
            results.put(exc)


class SerialTransport(ReopeningStream):
    """``serial``: a terminal device opened raw, 8N1, no flow control, non-blocking; reopened
    (by path, so a ``/dev/serial/by-id`` link finds a re-enumerated adapter) when it goes away.

    Opened with ``os.open`` and ``termios`` rather than pyserial: pyserial's ``write`` with
    ``write_timeout=0`` retries EAGAIN in a loop, busy-waiting as long as the port's buffer
    stays full, and its ``read`` calls ``select()`` (which fails for descriptors above 1023)
    before every read. Here a read or write is one system call. The price: only the rates
    ``termios`` names (50..4000000 bit/s, every rate an autopilot uses).

    Opening (after the first time, at construction) and closing run in a helper thread, one
    per transport and idle otherwise, since a USB adapter's driver sleeps in both;
    :meth:`service` hands it the work and picks up the result. Reads ask first how many bytes
    wait (see :meth:`_read_some`). The caller's own ``poll()`` on a tty with nothing in it may
    wait for the kernel's flip-buffer worker in the same way (``n_tty_poll``), which a poll
    with a timeout up to the next tick absorbs.
    """

    def __init__(
        self,
        endpoint: Endpoint,
        wait_for_link: bool = True,
        pending_limit_bytes: int = PENDING_LIMIT_BYTES,
    ) -> None:
        """Open the device now if it is there; with ``wait_for_link``, a device that is
        absent (or not yet accessible) is opened later by :meth:`service`.

        Raises:
            LinkError: the baud rate is not a standard one, the path is no terminal, or (without
                ``wait_for_link``) the device cannot be opened now.
        """
        super().__init__(endpoint, pending_limit_bytes)
        speed = getattr(termios, f"B{endpoint.baud}", None)
        if not isinstance(speed, int):
            raise LinkError(
                f"cannot open MAVLink {endpoint.url!r}: {endpoint.baud} bit/s is not a standard "
                "rate; expected one of 57600, 115200, 230400, 460800, 921600, 1500000, ..."
            )
        self._waiting = array.array("i", [0])  # TIOCINQ's answer, written in place
        self.stats.attempts += 1
        try:
            fd: int | None = _open_tty(endpoint.address, speed)
        except OSError as exc:
            if not wait_for_link or exc.errno not in _SERIAL_TRANSIENT:
                raise LinkError(f"cannot open MAVLink {endpoint.url!r}: {reason(exc)}") from exc
            fd, failure = None, reason(exc)
        self._requests: queue.SimpleQueue[int | None] = queue.SimpleQueue()
        self._results: queue.SimpleQueue[int | OSError] = queue.SimpleQueue()
        self._opening = False  # an open request is with the helper
        threading.Thread(
            target=_serve_serial,
            args=(endpoint.address, speed, self._requests, self._results),
            name=f"serial-helper {endpoint.address}",
            daemon=True,  # a driver stuck in open() must not keep the process alive
        ).start()
        self._closed = False
        if fd is None:
            self._attempt_failed(failure)
        else:
            self._connected(fd, f"open at {endpoint.baud} bit/s")

    def service(self, now_ns: int) -> None:
        if self._fd is not None:
            if self._pending:
                self._flush()
            return
        if self._closed:
            return
        if self._opening:
            if self._results.empty():
                return  # the helper is still at it
            self._opening = False
            result = self._results.get()
            if isinstance(result, OSError):
                self._attempt_failed(reason(result))
            else:
                self._connected(result, f"open at {self.endpoint.baud} bit/s")
        elif now_ns >= self._retry_at_ns:
            self.stats.attempts += 1
            self._opening = True
            self._requests.put(_OPEN_REQUEST)

    def _read_some(self) -> bytes | None:
        assert self._fd is not None
        # A tty read that finds the line discipline empty first waits for the kernel's
        # flip-buffer worker to finish (n_tty_read calls tty_buffer_flush_work), which on a
        # busy machine can take milliseconds to be scheduled. Asking how many bytes wait
        # (TIOCINQ) does not wait for it, and costs less than an empty read. A device that
        # went away answers EIO here.
        fcntl.ioctl(self._fd, termios.TIOCINQ, self._waiting, True)
        if self._waiting[0] == 0:
            return None
        return os.read(self._fd, READ_SIZE)

    def _write_some(self, data: bytes | bytearray) -> int:
        assert self._fd is not None
        return os.write(self._fd, data)

    def _close_stream(self) -> None:
        if self._fd is not None:
            self._requests.put(self._fd)  # the helper closes it: close() may wait in the driver
        self._fd = None

    def _close_all(self) -> None:
        super()._close_all()
        self._requests.put(None)
