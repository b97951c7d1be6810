"""What the supervisor says about the autopilot's UDP address (bridge/daemon/address_reports.py),
from the loop's real counters as the input side writes them."""

from __future__ import annotations

import logging

import pytest

from bridge.config import build_config
from bridge.daemon.address_reports import ADDRESSES_REPORTED, AddressReports
from bridge.daemon.severity import SEVERITY_WARNING
from bridge.mavlink.autopilot_address import address_code
from bridge.output.mailbox import LoopStats

URL = "udpin:0.0.0.0:14550"
AUTOPILOT = ("127.0.0.1", 14555)


class Reported:
    def __init__(self) -> None:
        config = build_config(
            {
                "mavlink": {"url": URL, "autopilot_system_id": 3},
                "output": {"arming_timeout_ms": 2000},
            },
            "test",
        )
        self.statustexts: list[tuple[int, str]] = []
        self.reports = AddressReports(
            config, lambda severity, text: self.statustexts.append((severity, text))
        )
        self.stats = LoopStats()

    def refused(self, address: tuple[str, int], count: int) -> None:
        self.stats["input_other_address"] = count
        self.stats["input_other_address_from"] = address_code(address)


def test_the_autopilots_address_is_logged_once_when_known(
    caplog: pytest.LogCaptureFixture,
) -> None:
    r = Reported()
    with caplog.at_level(logging.INFO):
        r.reports.check(r.stats)
        assert caplog.messages == []  # not known yet
        r.stats["link_autopilot_address"] = address_code(AUTOPILOT)
        r.reports.check(r.stats)
        r.reports.check(r.stats)
    assert caplog.messages == [
        f"MAVLink {URL}: the autopilot 3/1 is at 127.0.0.1:14555; frames claiming to be 3/1 "
        "from any other address are ignored"
    ]
    assert r.statustexts == []


def test_each_other_address_is_named_once_in_the_log_and_a_statustext(
    caplog: pytest.LogCaptureFixture,
) -> None:
    r = Reported()
    r.stats["link_autopilot_address"] = address_code(AUTOPILOT)
    r.reports.check(r.stats)
    caplog.clear()
    with caplog.at_level(logging.INFO):
        r.refused(("10.0.0.7", 14550), 3)
        r.reports.check(r.stats)
        r.refused(("10.0.0.7", 14550), 40)  # the same address again: said already
        r.reports.check(r.stats)
        r.refused(("192.168.100.200", 65535), 41)
        r.reports.check(r.stats)
    assert [(rec.levelno, rec.getMessage()) for rec in caplog.records] == [
        (
            logging.WARNING,
            f"MAVLink {URL}: frames claiming to be the autopilot 3/1 came from 10.0.0.7:14550, "
            "not from its address 127.0.0.1:14555: ignored (3 so far). A second route to the "
            "autopilot, another sender using its IDs, or the autopilot back from a new address, "
            "which takes the old one's place after 2000 ms of silence from it "
            "(docs/troubleshooting.md)",
        ),
        (logging.WARNING, caplog.records[1].getMessage()),
    ]
    assert "came from 192.168.100.200:65535" in caplog.records[1].getMessage()
    assert r.statustexts == [
        (SEVERITY_WARNING, "Ignoring 3/1 from 10.0.0.7:14550"),
        (SEVERITY_WARNING, "Ignoring 3/1 from 192.168.100.200:65535"),
    ]
    assert all(len(text) <= 50 for _, text in r.statustexts)  # a STATUSTEXT's room


def test_a_sender_on_ever_new_ports_is_named_only_so_often() -> None:
    r = Reported()
    for port in range(1000, 1100):
        r.refused(("10.0.0.7", port), port)
        r.reports.check(r.stats)
    assert len(r.statustexts) == ADDRESSES_REPORTED


def test_a_move_is_a_warning_and_a_statustext(caplog: pytest.LogCaptureFixture) -> None:
    r = Reported()
    r.stats["link_autopilot_address"] = address_code(AUTOPILOT)
    r.reports.check(r.stats)
    with caplog.at_level(logging.INFO):
        r.stats["link_autopilot_address"] = address_code(("127.0.0.1", 40123))
        r.stats["link_autopilot_moves"] = 1
        r.reports.check(r.stats)
    assert [(rec.levelno, rec.getMessage()) for rec in caplog.records] == [
        (
            logging.WARNING,
            f"MAVLink {URL}: the autopilot 3/1 now speaks from 127.0.0.1:40123: nothing came "
            "from 127.0.0.1:14555 for over 2000 ms (arming_timeout_ms); disarmed until its "
            "HEARTBEAT says otherwise (docs/troubleshooting.md)",
        )
    ]
    assert r.statustexts == [(SEVERITY_WARNING, "Autopilot 3/1 now at 127.0.0.1:40123")]
