"""The CKESC set-up client (bridge/escs/ckesc/setup.py) against simulated ESCs on a ``virtual`` bus,
plus a raw python-can peer for answers no well-behaved ESC gives (wrong node, malformed)."""

from __future__ import annotations

import itertools
import threading
import time
from collections.abc import Callable, Iterator

import can
import pytest

from bridge.errors import LinkError, NoAnswerError, RefusedError, SetupError, WrongNodeError
from bridge.escs import uavcan_v0
from bridge.escs.ckesc import codec, records
from bridge.escs.ckesc.results import CanTestResult, ScannedEsc, scan_warnings
from bridge.escs.ckesc.setup import CkescClient
from bridge.escs.ckesc.sim import ESC_INFO, SimCkesc
from bridge.sim.runner import Simulator

_channels = itertools.count()


@pytest.fixture
def channel() -> str:
    return f"esc-setup-{next(_channels)}"


@pytest.fixture
def client(channel: str) -> Iterator[CkescClient]:
    bus = can.Bus(interface="virtual", channel=channel)
    yield CkescClient(bus, timeout_s=0.3)
    bus.shutdown()


def simulate(channel: str, *escs: SimCkesc) -> Simulator:
    return Simulator(can.Bus(interface="virtual", channel=channel), escs, own_bus=True).start()


class Peer:
    """A raw bus peer that answers every service request with ``reply(request frame)``."""

    def __init__(self, channel: str, reply: Callable[[codec.CkescFrame], can.Message]) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel)
        self._reply = reply
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="peer", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            msg = self.bus.recv(0.01)
            if msg is None or not msg.arbitration_id & 0x8000:
                continue  # not a service request
            frame = codec.decode(msg)
            if frame is not None:
                self.bus.send(self._reply(frame))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1.0)
        self.bus.shutdown()


def info_from(node: int) -> Callable[[codec.CkescFrame], can.Message]:
    """An ESC Information response from ``node`` to any request, with its transfer ID."""

    def reply(request: codec.CkescFrame) -> can.Message:
        response = codec.CkescFrame(
            uavcan_v0.PRIORITY_MEDIUM, node, 0, request.transfer_id, ESC_INFO
        )
        return codec.encode(response)

    return reply


def test_an_answer_from_another_node_is_a_wrong_node_error(
    channel: str, client: CkescClient
) -> None:
    peer = Peer(channel, info_from(4))
    try:
        start = time.monotonic()
        with pytest.raises(WrongNodeError) as caught:
            client.info(3)
        assert time.monotonic() - start < 0.6
    finally:
        peer.close()
    text = str(caught.value)
    assert text.startswith("node 3 did not answer ESC Information (240) within 0.3 s")
    assert "node(s) 4 answered it instead" in text
    assert isinstance(caught.value, NoAnswerError) and isinstance(caught.value, TimeoutError)


def test_an_answer_with_another_transfer_id_is_not_the_answer(
    channel: str, client: CkescClient
) -> None:
    def stale(request: codec.CkescFrame) -> can.Message:
        assert request.transfer_id is not None
        earlier = (request.transfer_id - 1) % 32
        return codec.encode(codec.CkescFrame(uavcan_v0.PRIORITY_MEDIUM, 3, 0, earlier, ESC_INFO))

    peer = Peer(channel, stale)
    try:
        with pytest.raises(NoAnswerError) as caught:
            client.info(3)
    finally:
        peer.close()
    assert not isinstance(caught.value, WrongNodeError)


def test_the_addressed_node_wins_over_another_that_answers_too(
    channel: str, client: CkescClient
) -> None:
    peer = Peer(channel, info_from(4))
    sim = simulate(channel, SimCkesc(3, 1))
    try:
        assert client.info(3) == ESC_INFO
    finally:
        sim.close()
        peer.close()


def test_a_malformed_answer_is_named_when_no_good_one_follows(
    channel: str, client: CkescClient
) -> None:
    def short(request: codec.CkescFrame) -> can.Message:
        good = info_from(3)(request)
        return can.Message(arbitration_id=good.arbitration_id, data=good.data[:5])

    peer = Peer(channel, short)
    try:
        with pytest.raises(NoAnswerError) as caught:
            client.info(3)
    finally:
        peer.close()
    assert not isinstance(caught.value, WrongNodeError)
    assert "a malformed answer from node 3 (EscInfoResponse (240): DLC 5, expected 8)" in str(
        caught.value
    )


def test_shared_node_ids_are_found_and_block_set_id(channel: str, client: CkescClient) -> None:
    """Two factory-fresh ESCs: both answer as node 125 (two runners: one node ID each)."""
    first = simulate(channel, SimCkesc(records.FACTORY_NODE_ID, 1))
    second = simulate(channel, SimCkesc(records.FACTORY_NODE_ID, 1))
    try:
        escs = client.scan()
        assert [(e.node_id, e.info) for e in escs] == [(125, None), (125, None)]
        assert all(e.problem == "2 ESCs answer as node 125: not asked for details" for e in escs)
        warnings = scan_warnings(escs)
        assert warnings[0].startswith("2 ESCs answered as node 125: connect them one at a time")
        with pytest.raises(SetupError, match=r"2 ESCs answered GET_ESC_ID \(nodes 125, 125\)"):
            client.set_id(3, 1)
    finally:
        first.close()
        second.close()


def test_scan_warns_of_shared_throttle_channels() -> None:
    escs = [ScannedEsc(1, 2), ScannedEsc(4, 2), ScannedEsc(5, 3)]
    assert scan_warnings(escs) == [
        "nodes 1, 4 all follow throttle channel 2: they would spin together; give each its own "
        "channel (set-id)"
    ]


def spin(channel: str, stop: threading.Event) -> None:
    """Throttle 600 on channel 1 every 20 ms until ``stop``."""
    bus = can.Bus(interface="virtual", channel=channel)
    tids = uavcan_v0.TransferIds()
    while not stop.wait(0.02):
        bus.send(codec.encode_raw_12b(1, [600], tids.next(records.TYPE_RAW_COMMAND_12B)))
    bus.shutdown()


def test_settings_that_need_a_stopped_motor_are_refused_while_it_turns(
    channel: str, client: CkescClient
) -> None:
    esc = SimCkesc(1, 1)
    sim = simulate(channel, esc)
    stop = threading.Event()
    spinner = threading.Thread(target=spin, args=(channel, stop), daemon=True)
    spinner.start()
    try:
        deadline = time.monotonic() + 2.0
        while esc.motor.rpm < 100 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert esc.motor.rpm >= 100
        with pytest.raises(RefusedError) as caught:
            client.rotation(1, records.Rotation.REVERSED)
        assert str(caught.value) == (
            "node 1 refused Set Rotation (213): asked reversed, in effect normal; an ESC takes "
            "Set Rotation only with the motor stopped and its reports on (MSGControl resume)"
        )
        with pytest.raises(RefusedError, match=r"asked pwm-can, in effect can; .*zero throttle"):
            client.throttle_source(1, records.ThrottleSource.PWM_AND_CAN)
        with pytest.raises(RefusedError) as caught:
            client.expand(1, records.ExpandSetCommand.DIRECTION, 2)
        assert str(caught.value).startswith(
            "node 1 refused Expand Set (222): asked direction 2 (direction reversed yes), in "
            "effect direction reversed no (Get Major Configuration); an ESC takes Expand Set "
            "only with the motor stopped"
        )
    finally:
        stop.set()
        spinner.join(1.0)
        sim.close()
    assert not esc.reversed and esc.throttle_source == records.ThrottleSource.CAN


def test_report_intervals_written_in_part_keep_the_others(
    channel: str, client: CkescClient
) -> None:
    sim = simulate(channel, SimCkesc(2, 1))
    try:
        response = client.report_intervals(2, msg3_ms=250)
        assert (response.write, response.msg1_interval_ms, response.msg3_interval_ms) == (
            True,
            20,
            250,
        )
        assert client.report_intervals(2).msg3_interval_ms == 250
    finally:
        sim.close()


def test_can_test_counts_against_a_wrapping_counter() -> None:
    whole = CanTestResult(1, received=4, first_count=0xFFFF_FFFE, last_count=1, duration_s=1.0)
    assert (whole.expected, whole.lost) == (4, 0)
    gap = CanTestResult(1, received=3, first_count=0xFFFF_FFFE, last_count=1, duration_s=1.0)
    assert (gap.expected, gap.lost) == (4, 1)


def test_a_bus_that_fails_is_a_link_error(channel: str) -> None:
    bus = can.Bus(interface="virtual", channel=channel)
    client = CkescClient(bus, timeout_s=0.1)
    bus.shutdown()
    with pytest.raises(LinkError, match=r"cannot (send|read)") as caught:
        client.info(1)
    assert not isinstance(caught.value, NoAnswerError)


def test_client_checks_its_arguments(client: CkescClient) -> None:
    with pytest.raises(ValueError, match="timeout_s"):
        CkescClient(client.bus, timeout_s=0.0)
    with pytest.raises(ValueError, match="host_node = 126"):
        CkescClient(client.bus, host_node=126)
