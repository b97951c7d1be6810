"""The PING scan (bridge/escs/vesc/setup.py) against simulated VESCs on a python-can virtual bus:
who answers, the status frames each sends, the warnings, and no answer at all."""

from __future__ import annotations

import itertools
from collections.abc import Iterator

import can
import pytest

from bridge.errors import NoAnswerError, ValueRangeError
from bridge.escs.vesc.records import HwType, Packet
from bridge.escs.vesc.setup import STATUS_ON_HINT, FoundVesc, scan, scan_warnings
from bridge.escs.vesc.sim import STATUS_1_TO_5, SimVesc
from bridge.sim.runner import Simulator

_channels = itertools.count()


@pytest.fixture
def channel() -> str:
    return f"vesc-scan-{next(_channels)}"


@pytest.fixture
def host(channel: str) -> Iterator[can.BusABC]:
    bus = can.Bus(interface="virtual", channel=channel)
    yield bus
    bus.shutdown()


def simulate(channel: str, *escs: SimVesc) -> Simulator:
    bus = can.Bus(interface="virtual", channel=channel)
    return Simulator(bus, escs, own_bus=True, name=f"sim-{channel}").start()


def test_scan_finds_every_vesc_and_its_status_frames(channel: str, host: can.BusABC) -> None:
    with simulate(
        channel,
        SimVesc(5, status=STATUS_1_TO_5),
        SimVesc(23),
        SimVesc(100, status=frozenset({Packet.STATUS}), status_hz=10.0),
    ):
        found = scan(host, listen_s=0.3)
    assert found == [
        FoundVesc(5, HwType.VESC, 1, frozenset(STATUS_1_TO_5)),
        FoundVesc(23, HwType.VESC, 1, frozenset()),
        FoundVesc(100, HwType.VESC, 1, frozenset({Packet.STATUS})),
    ]
    assert found[0].hw_name == "VESC"
    assert scan_warnings(found) == [
        f"VESC 23: sends no status frames: {STATUS_ON_HINT}",
        f"VESC 100: sends no STATUS_2, STATUS_3, STATUS_4, STATUS_5: {STATUS_ON_HINT}",
    ]
    assert "Can Messages Rate 1: Status 1 to 5" in STATUS_ON_HINT


def test_a_shared_id_is_found(channel: str, host: can.BusABC) -> None:
    with (
        simulate(channel, SimVesc(7, status=STATUS_1_TO_5)),
        simulate(channel, SimVesc(7, status=STATUS_1_TO_5)),
    ):
        found = scan(host, ids=range(10), listen_s=0.2)
    assert [(v.controller_id, v.answers) for v in found] == [(7, 2)]
    (warning,) = scan_warnings(found)
    assert warning.startswith("VESC 7: 2 answers to one PING: VESCs that share an ID")


def test_no_answer(host: can.BusABC) -> None:
    with pytest.raises(NoAnswerError, match=r"no VESC answered a PING to IDs 0\.\.254"):
        scan(host, listen_s=0.05)


def test_bad_ids_are_refused_before_sending(host: can.BusABC) -> None:
    with pytest.raises(ValueRangeError, match="VESC ID 255"):
        scan(host, host_id=255)
    with pytest.raises(ValueRangeError, match="VESC ID -1"):
        scan(host, ids=[-1, 3])
    assert host.recv(0.0) is None


def test_other_hardware_is_listed_without_status_warnings() -> None:
    bms = FoundVesc(10, HwType.VESC_BMS, 1)
    assert bms.hw_name == "VESC_BMS" and FoundVesc(11, 9, 1).hw_name == "9"
    assert scan_warnings([bms]) == []
