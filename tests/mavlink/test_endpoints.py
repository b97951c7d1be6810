"""Connection strings: the accepted forms, malformed ones, and outputs that repeat a connection."""

from __future__ import annotations

import socket
import threading

import linkpeer
import pytest
from conftest import free_port

from bridge.config import MavlinkConfig
from bridge.errors import ConfigError
from bridge.mavlink.endpoints import ACCEPTED_URL_FORMS, DEFAULT_BAUD, Endpoint, parse_url
from bridge.mavlink.link import MavlinkLink

udp_address = linkpeer.udp_address


@pytest.mark.parametrize(
    ("url", "expected"),
    [
        ("udpin:0.0.0.0:14550", Endpoint("udpin:0.0.0.0:14550", "udpin", "0.0.0.0:14550")),
        ("udpout:localhost:14550", Endpoint("udpout:localhost:14550", "udpout", "localhost:14550")),
        ("tcp:127.0.0.1:5760", Endpoint("tcp:127.0.0.1:5760", "tcp", "127.0.0.1:5760")),
        ("tcpin:0.0.0.0:5760", Endpoint("tcpin:0.0.0.0:5760", "tcpin", "0.0.0.0:5760")),
        (
            "serial:/dev/ttyAMA0:921600",
            Endpoint("serial:/dev/ttyAMA0:921600", "serial", "/dev/ttyAMA0", 921600),
        ),
        ("serial:/dev/ttyACM0", Endpoint("serial:/dev/ttyACM0", "serial", "/dev/ttyACM0")),
        ("/dev/ttyUSB0", Endpoint("/dev/ttyUSB0", "serial", "/dev/ttyUSB0", DEFAULT_BAUD)),
        ("/dev/ttyUSB0:57600", Endpoint("/dev/ttyUSB0:57600", "serial", "/dev/ttyUSB0", 57600)),
        (  # by-path names contain colons; only a trailing :digits is a baud rate
            "serial:/dev/serial/by-path/platform-usb-0:1.3:1.0-port0:57600",
            Endpoint(
                "serial:/dev/serial/by-path/platform-usb-0:1.3:1.0-port0:57600",
                "serial",
                "/dev/serial/by-path/platform-usb-0:1.3:1.0-port0",
                57600,
            ),
        ),
    ],
)
def test_parse_url_accepts_the_documented_forms(url: str, expected: Endpoint) -> None:
    assert parse_url(url) == expected


@pytest.mark.parametrize(
    "url",
    [
        "",
        "udpin:127.0.0.1",
        "udpin:127.0.0.1:abc",
        "udpin:127.0.0.1:70000",
        "udp:127.0.0.1:14550",
        "tcp::5760",
        "serial:ttyAMA0",
        "serial:/dev/ttyAMA0:0",
        "flight.tlog",
    ],
)
def test_malformed_url_is_a_config_error_naming_it(url: str) -> None:
    with pytest.raises(ConfigError) as raised:
        MavlinkLink(MavlinkConfig(url=url)).start()
    assert repr(url) in str(raised.value)
    assert ACCEPTED_URL_FORMS in str(raised.value)


@pytest.mark.parametrize(
    ("outputs", "problem"),
    [
        (("udp:127.0.0.1:14550",), "'udp:127.0.0.1:14550' is not a connection string"),
        (("udpout:127.0.0.1:14550", "flight.tlog"), "'flight.tlog' is not a connection string"),
        (("tcpin:0.0.0.0:99999",), "port 99999 is not 1..65535"),
        (("udpout:127.0.0.1:14550", "udpout:127.0.0.1:14550"), "the same connection as"),
    ],
)
def test_bad_outputs_are_config_errors_before_anything_opens(
    outputs: tuple[str, ...], problem: str
) -> None:
    address = ("127.0.0.1", free_port(socket.SOCK_STREAM))
    link = MavlinkLink(MavlinkConfig(url=f"tcpin:{address[0]}:{address[1]}", outputs=outputs))
    with pytest.raises(ConfigError) as raised:
        link.start()
    message = str(raised.value)
    assert message.startswith("[mavlink] outputs ")
    assert problem in message
    if "same connection" not in problem:
        assert ACCEPTED_URL_FORMS in message
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(address)  # the autopilot's listener was never opened
    assert not any("mavlink" in t.name and address[0] in t.name for t in threading.enumerate())


def test_an_output_repeating_the_autopilot_url_is_refused(udp_address: str) -> None:
    url = f"udpin:{udp_address}"
    with pytest.raises(ConfigError, match=r"same connection as \[mavlink\] url"):
        MavlinkLink(MavlinkConfig(url=url, outputs=(url,))).start()
