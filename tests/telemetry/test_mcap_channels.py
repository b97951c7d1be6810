"""The MCAP's channels (bridge/telemetry/mcap_channels.py): the messages built directly for speed
are the records' own JSON, every message fits its schema, and the levels Foxglove's Log panel
colours by."""

from __future__ import annotations

import logging
import re
from pathlib import Path

import pytest

from bridge.mavlink.traffic import AutopilotHeartbeat, MotorOutputs, StatusText
from bridge.telemetry import mcap_channels as channels
from bridge.telemetry.json_schema import to_json
from bridge.telemetry.mcap_channels import BridgeState, CommandsSent
from bridge.telemetry.payload import CommandOut, EscTelemetryPayload
from bridge.telemetry.state import EscSnapshot, LastCommand

jsonschema = pytest.importorskip(
    "jsonschema", reason="jsonschema (in the test extra) is not installed: pip install -e '.[test]'"
)

SNAPSHOTS = [
    EscSnapshot(
        1, 7, False, None, None, None, None, None, None, None, None, None, None, None, 0, 0, 0,
        0.0,
    ),
    EscSnapshot(
        3, 12, True, 12.3456, -4321, 24.1, 5.5, 7.25, -0.5, 41.0, 38.5, 60.0, 35.0, 0x0400, 65,
        1200, 3, 123.45678, {"start_count": 3}, 1100.0, "throttle",
    ),
]  # fmt: skip


def check(topic: str, message: object) -> None:
    jsonschema.Draft202012Validator(channels.SCHEMAS[channels.schema_of(topic)]).validate(message)


@pytest.mark.parametrize("snap", SNAPSHOTS)
def test_an_escs_message_is_its_zenoh_record(snap: EscSnapshot) -> None:
    topic, message = channels.esc_message(snap)
    assert topic == f"/esc/{snap.motor}/telemetry"
    assert message == to_json(EscTelemetryPayload.of(snap))
    check(topic, message)


def test_the_commands_message_is_its_record() -> None:
    commands = [LastCommand(1, 7, 0.25, "duty"), LastCommand(2, 8, None, "")]
    topic, message = channels.commands_message(commands)
    records = tuple(
        CommandOut(motor=c.motor, node_id=c.node_id, value=c.value, unit=c.unit) for c in commands
    )
    assert (topic, message) == (channels.COMMANDS_TOPIC, to_json(CommandsSent(commands=records)))
    check(topic, message)


def test_traffic_state_and_log_messages_fit_their_schemas() -> None:
    outputs = MotorOutputs("SERVO_OUTPUT_RAW", {"ch1": 1500.0}, None, 32, None)
    topic, message = channels.traffic_message(outputs, 0)
    assert (topic, message) == (channels.OUTPUTS_TOPIC, to_json(outputs))
    check(topic, message)
    beat = AutopilotHeartbeat(12, 2, 0x81, 0, 4, True)
    check(*channels.traffic_message(beat, 0))
    topic, message = channels.traffic_message(
        StatusText(2, "ESC out: FAILSAFE", 1, 191), 1_500_000_000
    )
    assert (topic, message) == (
        channels.STATUSTEXT_TOPIC,
        {
            "timestamp": {"sec": 1, "nsec": 500_000_000},
            "level": channels.LOG_FATAL,
            "message": "ESC out: FAILSAFE",
            "name": "1/191",
            "file": "",
            "line": 0,
        },
    )
    check(topic, message)
    check(*channels.state_message(BridgeState(state="stale", failsafe=True, severity=2, text="x")))
    check(
        channels.LOG_TOPIC, channels.log_message(5, channels.LOG_INFO, "hello", "bridge", "a.py", 3)
    )
    with pytest.raises(KeyError):
        channels.schema_of("/nothing")


def test_levels() -> None:
    severities = [channels.severity_level(s) for s in range(8)]
    assert severities == [5, 5, 5, 4, 3, 2, 2, 1]  # emergency..critical fatal, ..., debug
    levels = [logging.DEBUG, logging.INFO, logging.WARNING, logging.ERROR, logging.CRITICAL]
    assert [channels.python_level(level) for level in levels] == [1, 2, 3, 4, 5]
    assert channels.python_level(logging.NOTSET) == channels.LOG_UNKNOWN


def test_metadata_round_trip() -> None:
    meta = channels.metadata("fam", [5, 6, 7], mixer="quad-x")
    assert meta == {"protocol": "fam", "esc_ids": "5,6,7", "mixer": "quad-x"}
    assert channels.esc_ids_of(meta) == (5, 6, 7)
    assert channels.esc_ids_of({}) is None
    assert channels.esc_ids_of({"esc_ids": "1,x"}) is None


TELEMETRY_PAGE = Path(__file__).resolve().parents[2] / "docs" / "telemetry.md"


def test_the_channels_are_the_documented_table() -> None:
    text = TELEMETRY_PAGE.read_text(encoding="utf-8")
    section = text[text.index("### The MCAP: Foxglove and PlotJuggler") :]
    rows = re.findall(r"^\| `(/[^`]+)` \| `([\w.]+)` \| (.*) \|$", section, re.MULTILINE)
    documented = {topic: schema for topic, schema, _ in rows}
    assert documented == {
        "/esc/<n>/telemetry": "esc_bridge.EscTelemetry",
        **channels.TOPIC_SCHEMAS,
    }
    assert set(documented.values()) == set(channels.SCHEMAS)
    assert channels.schema_of(channels.esc_topic(3)) == documented["/esc/<n>/telemetry"]
    # Each of the bridge's own records names every field it has.
    described = {schema: what for _, schema, what in rows}
    for schema in ("MotorOutputs", "AutopilotHeartbeat", "BridgeState", "CommandsSent"):
        fields = set(channels.SCHEMAS[f"esc_bridge.{schema}"]["properties"])
        named = set(re.findall(r"`([a-z_]+)`", described[f"esc_bridge.{schema}"]))
        assert fields <= named, (schema, fields - named)
