"""The MCAP of a recorded flight: a real demo flight recorded through the CLI (``demo --record``),
read back with the ``mcap`` package's reader, every message checked against its channel's JSON
Schema (``jsonschema``), and every ESC's rpm series against the one decoded from the candump log
of the same flight through the production codecs. Once per ESC family: the MCAP names none."""

from __future__ import annotations

import json
import subprocess
from collections import Counter, defaultdict
from pathlib import Path
from typing import Any

import pytest
from conftest import ESC_BRIDGE
from mcap.reader import make_reader

from bridge.capture import BadLine, read_capture
from bridge.errors import FrameError
from bridge.escs import registry
from bridge.plot.recording import find_recordings
from bridge.telemetry import mcap_channels

jsonschema = pytest.importorskip(
    "jsonschema", reason="jsonschema (in the test extra) is not installed: pip install -e '.[test]'"
)

TIME_SCALE = 4
EXPECTED_TOPICS = {
    mcap_channels.COMMANDS_TOPIC,
    mcap_channels.OUTPUTS_TOPIC,
    mcap_channels.HEARTBEAT_TOPIC,
    mcap_channels.STATE_TOPIC,
    mcap_channels.STATUSTEXT_TOPIC,
    mcap_channels.LOG_TOPIC,
}


@pytest.fixture(scope="module", params=registry.names())
def flight(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A directory holding one recorded demo flight (quad, flown 4 times faster)."""
    directory = tmp_path_factory.mktemp(f"record-{request.param}")
    demo = subprocess.run(
        [
            ESC_BRIDGE,
            "demo",
            "--plain",
            "--protocol",
            request.param,
            "--time-scale",
            str(TIME_SCALE),
            "--record",
            str(directory),
        ],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert demo.returncode == 0, demo.stdout[-3000:] + demo.stderr
    assert "flight complete" in demo.stdout
    return directory


def read_back(path: Path) -> tuple[list[tuple[Any, Any, Any]], dict[str, str]]:
    """Every message (schema, channel, message) in log-time order, and the esc-bridge metadata."""
    with path.open("rb") as file:
        reader = make_reader(file)
        messages = list(reader.iter_messages(log_time_order=True))
    with path.open("rb") as file:
        (meta,) = [m for m in make_reader(file).iter_metadata() if m.name == "esc-bridge"]
    return messages, dict(meta.metadata)


def test_every_message_fits_its_channels_schema(flight: Path) -> None:
    (files,) = find_recordings(flight)
    messages, meta = read_back(files.mcap_path)
    ids = [int(i) for i in meta["esc_ids"].split(",")]
    assert meta["protocol"] in registry.names() and ids == [1, 2, 3, 4]
    validators: dict[int, Any] = {}
    counts: Counter[str] = Counter()
    for schema, channel, message in messages:
        assert (channel.message_encoding, schema.encoding) == ("json", "jsonschema"), channel.topic
        assert schema.name == mcap_channels.schema_of(channel.topic)
        validator = validators.get(schema.id)
        if validator is None:
            document = json.loads(schema.data)
            jsonschema.Draft202012Validator.check_schema(document)
            validator = validators[schema.id] = jsonschema.Draft202012Validator(document)
        validator.validate(json.loads(message.data))
        assert message.publish_time > 0 and message.log_time > 0
        counts[channel.topic] += 1
    esc_topics = {mcap_channels.esc_topic(motor) for motor in range(1, len(ids) + 1)}
    assert set(counts) == EXPECTED_TOPICS | esc_topics, counts
    # What the flight did: armed, ran and stopped; Foxglove's Log panel has the bridge's words.
    topic_messages = defaultdict(list)
    for _, channel, message in messages:
        topic_messages[channel.topic].append(json.loads(message.data))
    states = [m["state"] for m in topic_messages[mcap_channels.STATE_TOPIC]]
    assert "running" in states and states[-1] == "stopping", states
    texts = [m["message"] for m in topic_messages[mcap_channels.STATUSTEXT_TOPIC]]
    assert "ESC out: armed, sending motor commands" in texts
    logs = [m["message"] for m in topic_messages[mcap_channels.LOG_TOPIC]]
    assert any(line.startswith("stopped after sending safe values") for line in logs), logs
    assert any(m["armed"] for m in topic_messages[mcap_channels.HEARTBEAT_TOPIC])
    outputs = topic_messages[mcap_channels.OUTPUTS_TOPIC]
    assert max(max(m["channels"].values(), default=0) for m in outputs) > 1100
    commands = topic_messages[mcap_channels.COMMANDS_TOPIC]
    assert [c["motor"] for c in commands[-1]["commands"]] == [1, 2, 3, 4]
    assert any(c["value"] for m in commands for c in m["commands"])


def test_the_rpm_series_are_the_candump_logs(flight: Path) -> None:
    (files,) = find_recordings(flight)
    messages, meta = read_back(files.mcap_path)
    family = registry.family(meta["protocol"])
    ids = [int(i) for i in meta["esc_ids"].split(",")]
    pole_pairs = int(meta["pole_pairs"])
    # From the candump log, through the production codecs: per motor, every telemetry frame's
    # receive time (µs) and the rpm it carried (None: a frame without rpm).
    decoded: dict[int, list[tuple[int, int | None]]] = defaultdict(list)
    for msg in read_capture(files.log_path):
        if isinstance(msg, BadLine):
            continue
        try:
            frame = family.decode(msg, frozenset(ids)) if family.owns(msg.arbitration_id) else None
        except FrameError:
            continue
        telemetry = None if frame is None else family.telemetry(frame)
        if telemetry is None or telemetry.node_id not in ids:
            continue
        rpm = telemetry.rpm
        if rpm is None and telemetry.erpm is not None:
            rpm = int(telemetry.erpm / pole_pairs)  # as the ESC state does
        decoded[ids.index(telemetry.node_id) + 1].append((round(msg.timestamp * 1e6), rpm))
    recorded: dict[int, list[tuple[int, int | None]]] = defaultdict(list)
    for _, channel, message in messages:
        if channel.topic.endswith("/telemetry"):
            record = json.loads(message.data)
            recorded[record["motor"]].append((round(message.log_time / 1000), record["rpm"]))
    assert sorted(recorded) == sorted(decoded) == [1, 2, 3, 4]
    for motor, frames in decoded.items():
        frames.sort(key=lambda f: f[0])  # stable: frames of one instant stay in turn
        got = recorded[motor]
        assert len(got) == len(frames), motor  # one message per telemetry frame, none lost
        assert all(abs(g[0] - f[0]) <= 1 for g, f in zip(got, frames, strict=True)), motor
        # Every frame that carried rpm: the message has it; the others keep the last one.
        assert [g[1] for g, f in zip(got, frames, strict=True) if f[1] is not None] == [
            f[1] for f in frames if f[1] is not None
        ], motor
        assert max(abs(f[1] or 0) for f in frames) > 1000, motor
