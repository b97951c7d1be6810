"""open_transport: what will not get better is a LinkError naming the URL, at start.

Every call into a transport under test is timed (:class:`watched.Watched`): one that waited
or spun fails the test.
"""

from __future__ import annotations

import socket
from collections.abc import Callable

import pytest
import watched
from conftest import free_port
from watched import Pty, occupied_tcp, occupied_udp

from bridge.errors import LinkError
from bridge.mavlink.endpoints import parse_url
from bridge.mavlink.transport import open_transport

pty = watched.pty


@pytest.mark.parametrize(
    ("url", "reason"),
    [
        ("udpin:192.0.2.1:14550", "Cannot assign requested address"),  # TEST-NET: not ours
        ("tcpin:192.0.2.1:5760", "Cannot assign requested address"),
        ("udpout:no-such-host.invalid:14550", "unknown host 'no-such-host.invalid'"),
        ("tcp:no-such-host.invalid:5760", "unknown host 'no-such-host.invalid'"),
        ("serial:/dev/null", "Inappropriate ioctl"),  # not a terminal
    ],
)
def test_what_will_not_get_better_is_a_link_error_naming_the_url(url: str, reason: str) -> None:
    with pytest.raises(LinkError) as raised:
        open_transport(parse_url(url))
    assert f"cannot open MAVLink {url!r}" in str(raised.value)
    assert reason in str(raised.value)


@pytest.mark.parametrize("occupy", [occupied_udp, occupied_tcp])
def test_an_address_in_use_is_a_link_error(occupy: Callable[[], tuple[socket.socket, str]]) -> None:
    sock, url = occupy()
    with sock, pytest.raises(LinkError, match=f"'{url}': Address already in use"):
        open_transport(parse_url(url))


def test_a_non_standard_baud_rate_is_a_link_error(pty: Pty) -> None:
    url = f"serial:{pty.link}:123456"
    with pytest.raises(LinkError, match=f"'{url}': 123456 bit/s is not a standard rate"):
        open_transport(parse_url(url))


def test_without_waiting_an_absent_tcp_server_is_a_link_error() -> None:
    url = f"tcp:127.0.0.1:{free_port(socket.SOCK_STREAM)}"
    with pytest.raises(LinkError, match=f"cannot open MAVLink '{url}': Connection refused"):
        open_transport(parse_url(url), wait_for_link=False)
    with (
        socket.create_server(("127.0.0.1", int(url.rsplit(":", 1)[1]))),
        open_transport(parse_url(url), wait_for_link=False) as transport,
    ):
        assert transport.stats.connected and transport.fileno() is not None
