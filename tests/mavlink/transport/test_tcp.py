"""The TCP transports (tcp, tcpin) against real sockets on 127.0.0.1.

Every call into a transport under test is timed (:class:`watched.Watched`): one that waited
or spun fails the test.
"""

from __future__ import annotations

import errno
import logging
import os
import socket
import time

import pytest
import watched
from conftest import free_port
from watched import LOGGER, TIMEOUT_S, Open, frame, pump, read_fd, receive

from bridge.mavlink.transport.tcp import TcpClientTransport, TcpServerTransport

opened = watched.opened


def test_tcp_and_tcpin_carry_data_both_ways(opened: Open) -> None:
    address = f"127.0.0.1:{free_port(socket.SOCK_STREAM)}"
    server = opened(f"tcpin:{address}")
    client = opened(f"tcp:{address}")
    assert isinstance(server.transport, TcpServerTransport)
    assert isinstance(client.transport, TcpClientTransport)
    assert server.fileno() is None  # listening, no client yet
    pump(
        server,
        client,
        until=lambda: server.stats.connected and client.stats.connected,
        what="a connection",
    )
    assert client.fileno() is not None and server.fileno() is not None

    assert client.send(frame(1)) and client.send(frame(2))
    assert receive(server, 200)[0] == frame(1) + frame(2)
    assert server.send(frame(3))
    assert receive(client, 100)[0] == frame(3)
    assert client.stats.reconnects == server.stats.reconnects == 0
    assert client.stats.bytes_out == server.stats.bytes_in == 200


def test_tcp_server_down_at_start_is_connected_to_by_itself_without_blocking(
    opened: Open, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger=LOGGER)
    port = free_port(socket.SOCK_STREAM)
    client = opened(f"tcp:127.0.0.1:{port}")  # nothing listens: no error, retried
    assert not client.open_blocked, f"open_transport took {client.open_ns / 1e6:.1f} ms"
    assert not client.stats.connected and client.fileno() is None
    assert client.send(frame(0)) is False

    deadline = time.monotonic() + 0.6
    while time.monotonic() < deadline:
        client.service()
        assert client.recv() is None
        time.sleep(0.002)
    attempts = client.stats.attempts
    # Backoff: 0.1 s doubling, jittered down to half: a few attempts, not one per service().
    assert 3 <= attempts <= 8, attempts
    assert client.stats.last_error == os.strerror(errno.ECONNREFUSED)
    warnings = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1 and "retrying in the background" in warnings[0].getMessage()

    with socket.create_server(("127.0.0.1", port)) as listener:
        listener.settimeout(TIMEOUT_S)
        pump(client, until=lambda: client.stats.connected, what="the connect")
        peer, _ = listener.accept()
        with peer:
            assert client.send(frame(7))
            assert read_fd(peer.fileno(), 100) == frame(7)
            peer.sendall(frame(8))
            assert receive(client, 100)[0] == frame(8)
    assert client.stats.reconnects == 0  # the first connection, however late, is no reconnect
    assert sum(r.levelno >= logging.WARNING for r in caplog.records) == 1
    assert any(r.getMessage().endswith(" connected") for r in caplog.records)
    client.assert_never_blocked()


def test_tcp_reconnects_when_the_server_restarts(opened: Open) -> None:
    port = free_port(socket.SOCK_STREAM)
    listener = socket.create_server(("127.0.0.1", port))
    client = opened(f"tcp:127.0.0.1:{port}")
    pump(client, until=lambda: client.stats.connected, what="the connect")
    peer, _ = listener.accept()
    peer.sendall(b"before")
    assert receive(client, 6)[0] == b"before"

    peer.close()
    listener.close()
    pump(client, until=lambda: client.recv() is None and not client.stats.connected, what="loss")
    assert client.fileno() is None
    assert client.stats.last_error == "closed by the other end"

    with socket.create_server(("127.0.0.1", port)) as listener:
        pump(client, until=lambda: client.stats.connected, what="the reconnect")
        peer, _ = listener.accept()
        with peer:
            assert client.send(b"after")
            assert read_fd(peer.fileno(), 5) == b"after"
            peer.sendall(b"again")
            assert receive(client, 5)[0] == b"again"
    assert client.stats.reconnects == 1


def test_tcp_connect_nobody_answers_is_given_up_without_blocking(
    opened: Open,
) -> None:
    # A listener whose one-slot accept queue is full drops further SYNs: a connect to it hangs.
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen(0)
        filler = socket.create_connection(listener.getsockname())
        time.sleep(0.05)
        client = opened(f"tcp:127.0.0.1:{listener.getsockname()[1]}")
        pump(client, until=lambda: client.stats.last_error.startswith("no answer"), what="give up")
        assert not client.stats.connected and client.fileno() is None

        accepted, _ = listener.accept()  # room in the queue: the next attempt gets through
        pump(client, until=lambda: client.stats.connected, what="the connect")
        assert client.stats.attempts >= 2
        filler.close()
        accepted.close()


def test_tcpin_new_client_replaces_the_old(opened: Open) -> None:
    port = free_port(socket.SOCK_STREAM)
    server = opened(f"tcpin:127.0.0.1:{port}")
    first = socket.create_connection(("127.0.0.1", port))
    second: socket.socket | None = None
    try:
        pump(server, until=lambda: server.stats.connected, what="the first client")
        first.sendall(b"first")
        assert receive(server, 5)[0] == b"first"

        second = socket.create_connection(("127.0.0.1", port))
        pump(server, until=lambda: server.stats.reconnects == 1, what="the second client")
        first.settimeout(TIMEOUT_S)
        assert first.recv(100) == b""  # the old client was closed
        assert server.send(b"to second")
        assert read_fd(second.fileno(), 9) == b"to second"
        second.sendall(b"second")
        assert receive(server, 6)[0] == b"second"

        second.close()
        second = None
        pump(
            server, until=lambda: server.recv() is None and not server.stats.connected, what="loss"
        )
        assert server.fileno() is None and server.send(b"nobody") is False
        with socket.create_connection(("127.0.0.1", port)) as third:
            pump(server, until=lambda: server.stats.connected, what="the third client")
            assert server.send(b"to third")
            assert read_fd(third.fileno(), 8) == b"to third"
        assert server.stats.reconnects == 2
        assert server.stats.attempts == 3
    finally:
        first.close()
        if second is not None:
            second.close()
