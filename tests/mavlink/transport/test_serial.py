"""The serial transport against real ptys.

Every call into a transport under test is timed (:class:`watched.Watched`): one that waited
or spun fails the test.
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

import pytest
import watched
from watched import LOGGER, Open, Pty, pump, read_fd, receive

from bridge.errors import LinkError
from bridge.mavlink.endpoints import parse_url
from bridge.mavlink.transport import open_transport
from bridge.mavlink.transport.serial import SerialTransport

opened = watched.opened
pty = watched.pty


def test_serial_carries_every_byte_value_raw_both_ways(opened: Open, pty: Pty) -> None:
    serial = opened(f"serial:{pty.link}:921600")
    assert isinstance(serial.transport, SerialTransport)
    assert serial.stats.connected and serial.fileno() is not None
    # Raw 8N1, no flow control: CR, LF, ^C, ^S/^Q (XOFF/XON), ^D, 0x7f, 0xff pass unchanged.
    everything = bytes(range(256)) * 2
    os.write(pty.controller, everything)
    data, stamps = receive(serial, len(everything))
    assert data == everything
    assert all(stamp <= time.monotonic_ns() for stamp in stamps)
    assert serial.send(everything)
    assert read_fd(pty.controller, len(everything), serve=serial) == everything


def test_serial_device_that_goes_away_is_reopened(
    opened: Open, pty: Pty, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger=LOGGER)
    serial = opened(f"serial:{pty.link}:115200")
    os.write(pty.controller, b"before")
    assert receive(serial, 6)[0] == b"before"

    pty.close()  # the USB adapter is pulled
    pump(serial, until=lambda: serial.recv() is None and not serial.stats.connected, what="loss")
    assert serial.fileno() is None and serial.send(b"lost") is False
    deadline = time.monotonic() + 0.4
    while time.monotonic() < deadline:  # retrying meanwhile, quietly
        serial.service()
        time.sleep(0.002)
    assert serial.stats.attempts >= 3
    assert not serial.stats.connected

    pty.replace()  # plugged in again, under a new /dev/pts name behind the same link
    pump(serial, until=lambda: serial.stats.connected, what="the reopen")
    os.write(pty.controller, b"after")
    assert receive(serial, 5)[0] == b"after"
    assert serial.send(b"again")
    assert read_fd(pty.controller, 5, serve=serial) == b"again"
    assert serial.stats.reconnects == 1
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 2, warnings  # lost; then "not available" once, however many tries
    assert "lost (Input/output error)" in warnings[0]  # EIO: the device is gone
    assert "No such file or directory" in warnings[1]


def test_serial_device_absent_at_start_is_waited_for(opened: Open, tmp_path: Path) -> None:
    link = tmp_path / "ttyAUTOPILOT"
    with pytest.raises(LinkError, match=f"'serial:{link}'.*No such file"):
        open_transport(parse_url(f"serial:{link}"), wait_for_link=False)

    serial = opened(f"serial:{link}")
    assert not serial.stats.connected and serial.fileno() is None
    pump(serial, until=lambda: serial.stats.attempts >= 2, what="a retry")
    made = Pty(tmp_path)
    try:
        pump(serial, until=lambda: serial.stats.connected, what="the device")
        os.write(made.controller, b"hello")
        assert receive(serial, 5)[0] == b"hello"
        assert serial.stats.reconnects == 0
    finally:
        serial.close()
        made.close()
