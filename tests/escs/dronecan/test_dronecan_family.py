"""The DroneCAN family behind the interface (bridge/escs/dronecan/family.py): its ID space, a
decoder per reading thread, the node a malformed frame names, the ESC numbers' mapping onto
RawCommand slots, the simulators and the configuration checks."""

from __future__ import annotations

import threading

import pytest

from bridge.config import build_config, with_esc_count
from bridge.errors import ConfigError, CrcError
from bridge.escs import registry
from bridge.escs.dronecan import codec, wire
from bridge.escs.dronecan.codec import DronecanFrame, EscStatus, RawCommand, TransferPart
from bridge.escs.dronecan.keys import DronecanKeys
from bridge.escs.dronecan.sim import SimDronecanEsc, simulators
from bridge.escs.family import EscSetup

FAMILY = registry.family("dronecan")


def test_id_space() -> None:
    assert FAMILY.owns(0x0704060A)  # RawCommand from node 10
    assert FAMILY.owns(0x10040A14) and FAMILY.owns(0x1F015514)  # Status, NodeStatus
    assert not FAMILY.owns(0x1F4E5203)  # CKESC MSG1
    assert not FAMILY.owns(0x0000030C)  # FT
    assert not FAMILY.owns(0x10040A00)  # anonymous
    assert not FAMILY.owns(0x10040A94)  # the service bit


def test_a_decoder_per_stream() -> None:
    """Two threads reading the same frames (two readers of one bus), each with its decoder,
    each put every transfer together: their reassembly does not mix."""
    frames = codec.encode(EscStatus(2, 0, 16.0, 1.0, 300.0, 100, 5), 22, 0)
    results: dict[str, list[object]] = {"a": [], "b": []}
    step = [threading.Barrier(2) for _ in frames]

    def read(name: str) -> None:
        decoder = FAMILY.decoder()
        for msg, barrier in zip(frames, step, strict=True):
            barrier.wait()
            results[name].append(decoder.decode(msg))

    threads = [threading.Thread(target=read, args=(name,)) for name in results]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(5)
    for got in results.values():
        assert [type(f.message) for f in got if isinstance(f, DronecanFrame)] == [
            TransferPart,
            TransferPart,
            EscStatus,
        ]


def test_esc_nodes_and_node_of() -> None:
    frames = codec.encode(EscStatus(2, 0, 16.0, 1.0, 300.0, 100, 5), 23, 1)
    decoder = FAMILY.decoder()
    done = [decoder.decode(msg, {1, 2, 3}) for msg in frames][-1]  # ESC 3 is index 2: ours
    assert isinstance(done, DronecanFrame) and done.esc_index == 2
    telemetry = decoder.telemetry(done)
    assert telemetry is not None and telemetry.node_id == 3
    assert decoder.node_of(frames[0]) == 3  # node 23 said it is ESC 3
    bad = codec.encode(EscStatus(2, 0, 16.0, 1.0, 300.0, 100, 5), 23, 2)
    bad[0].data[0] ^= 1
    with pytest.raises(CrcError):
        for msg in bad:
            decoder.decode(msg)
    assert decoder.node_of(bad[-1]) == 3
    assert decoder.node_of(codec.encode(EscStatus(0, 0, 1.0, 1.0, 1.0, 0, 0), 99, 0)[0]) is None
    others = [decoder.decode(msg, {1, 2}) for msg in frames]
    assert others[-1] is None  # ESC 3 is not ours now


def test_esc_numbers_are_slots_plus_one() -> None:
    config = with_esc_count(
        build_config(
            {
                "output": {"protocol": "dronecan"},
                "escs": {"ids": [2, 4], "dronecan_node_id": 42, "dronecan_reversible": [4]},
                "mixer": {"name": "passthrough-4"},
            },
            "v",
        ),
        2,
    )
    driver = FAMILY.driver(config.esc_setup)
    command, node_status = driver.tick_frames(0, [0.5, -0.5])  # one frame, and our NodeStatus
    assert FAMILY.owns(node_status.arbitration_id)
    decoder = FAMILY.decoder()
    frame = decoder.decode(command)
    assert isinstance(frame, DronecanFrame) and frame.source_node == 42
    assert frame.message == RawCommand((0, 4096, 0, -4096))  # slots 1 and 3; ESC 4 reverses
    assert [(c.node_id, c.value) for c in decoder.commands_seen(frame)] == [
        (1, 0.0),
        (2, 4096.0),
        (3, 0.0),
        (4, -4096.0),
    ]
    assert driver.describe_esc(1) == "DroneCAN ESC 4 (esc_index 3)"
    assert driver.describe_command(0.5) == "DroneCAN RawCommand 4096"
    assert driver.kind == "RawCommand x4"


def test_simulators() -> None:
    escs = simulators(EscSetup((1, 3), DronecanKeys()), None)
    assert [e.node_id for e in escs] == [1, 3]
    assert all(isinstance(e, SimDronecanEsc) for e in escs)
    assert [e.esc_index for e in escs if isinstance(e, SimDronecanEsc)] == [0, 2]


def test_config_checks() -> None:
    assert FAMILY.default_bitrate == 1_000_000 and wire.DEFAULT_NODE_ID == 10
    with pytest.raises(ConfigError, match="dronecan_reversible names ESCs"):
        build_config(
            {"output": {"protocol": "dronecan"}, "escs": {"ids": [1], "dronecan_reversible": [2]}},
            "v",
        )
