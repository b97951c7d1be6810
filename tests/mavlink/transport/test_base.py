"""Every transport's life cycle: closing twice, nothing left open, a forgotten transport warns.

Every call into a transport under test is timed (:class:`watched.Watched`): one that waited
or spun fails the test.
"""

from __future__ import annotations

import gc
import logging
import socket
import time
from contextlib import ExitStack
from pathlib import Path

import pytest
import watched
from conftest import free_port
from watched import LOGGER, Pty, open_descriptors, wait_for_helpers_to_stop

from bridge.mavlink.endpoints import parse_url
from bridge.mavlink.transport import open_transport

pty = watched.pty


@pytest.mark.parametrize("kind", ["udpin", "udpout", "tcp", "tcpin", "serial"])
def test_close_is_idempotent_and_leaves_nothing_open(
    tmp_path: Path, kind: str, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger=LOGGER)
    with ExitStack() as stack:
        if kind == "serial":
            pty = Pty(tmp_path)
            stack.callback(pty.close)
            url = f"serial:{pty.link}"
        elif kind == "tcp":  # a server to connect to, so that there is a socket to close
            listener = stack.enter_context(socket.create_server(("127.0.0.1", 0)))
            url = f"tcp:127.0.0.1:{listener.getsockname()[1]}"
        else:
            sock_type = socket.SOCK_STREAM if kind == "tcpin" else socket.SOCK_DGRAM
            url = f"{kind}:127.0.0.1:{free_port(sock_type)}"
        gc.collect()  # nothing forgotten by earlier tests closes in the middle
        before = open_descriptors()
        with open_transport(parse_url(url)) as transport:
            ours = open_descriptors() - before
            assert ours
            transport.close()
            transport.close()
            assert transport.fileno() is None and transport.recv() is None
            assert transport.send(b"x") is False and not transport.wants_write()
            transport.service(time.monotonic_ns())  # nothing reopens after close
            assert transport.fileno() is None and not transport.stats.connected
        wait_for_helpers_to_stop()
        assert not ours & open_descriptors()
    closed = [r for r in caplog.records if r.getMessage() == f"MAVLink {url} closed"]
    assert len(closed) == 1


@pytest.mark.parametrize("kind", ["udpin", "serial"])
def test_a_forgotten_transport_warns_when_collected(
    pty: Pty, kind: str, caplog: pytest.LogCaptureFixture
) -> None:
    # The serial helper thread holds no reference to its transport: it is collected too.
    url = f"serial:{pty.link}" if kind == "serial" else f"udpin:127.0.0.1:{free_port()}"
    transport = open_transport(parse_url(url))
    del transport
    assert f"MAVLink {url} was not closed; closing it now" in caplog.text
    wait_for_helpers_to_stop()
