"""The Zenoh schema (bridge/telemetry/payload.py): every key's record round-trips through its
JSON, its field names are those of docs/telemetry.md ("Zenoh out"), and garbage is refused
naming the key and the field."""

from __future__ import annotations

import json
import re
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
from payloads import ACTUATORS_INPUT, EVERY_KEY, HEALTH, INFO, STATUS, TELEMETRY

from bridge.errors import PayloadError
from bridge.escs.family import EscTelemetry
from bridge.telemetry.payload import (
    RECORDS,
    ActuatorsInputPayload,
    EscInfoPayload,
    EscStatusPayload,
    EscTelemetryPayload,
    HealthPayload,
    Payload,
)
from bridge.telemetry.state import EscTable

TELEMETRY_PAGE = Path(__file__).resolve().parents[2] / "docs" / "telemetry.md"


def test_there_is_a_sample_of_every_key() -> None:
    assert [type(p) for p in EVERY_KEY] == list(RECORDS)


@pytest.mark.parametrize("record", EVERY_KEY, ids=lambda r: r.KEY)
def test_every_key_round_trips(record: Payload) -> None:
    payload = record.encode()
    assert type(record).decode(payload) == record
    assert type(record).decode(payload).encode() == payload
    assert payload == json.dumps(json.loads(payload), separators=(",", ":")).encode()


def test_the_wire_keeps_its_form() -> None:
    # Compact JSON, time first, nested objects and arrays, null for "not reported".
    assert TELEMETRY.encode().startswith(b'{"time_unix_ms":1795330000123,"motor":1,"node_id":5,')
    assert b'"temperature_c":{"mos":42.0,"capacitor":30,"motor":null,"mcu":45.5}' in (
        TELEMETRY.encode()
    )
    status = json.loads(STATUS.encode())
    assert list(status) == ["time_unix_ms", "count", "online", "escs"]
    assert "time_unix_ms" not in status["escs"][0]  # the ESCs inside share the message's time
    assert json.loads(ACTUATORS_INPUT.encode())["mixed"] == [0.25, 0.5]
    health = json.loads(HEALTH.encode())
    assert health["motor_test"]["motors"] == [1, 2, 3, 4]
    assert "zenoh" not in json.loads(replace(HEALTH, zenoh=None).encode())  # Zenoh off: absent
    assert json.loads(replace(HEALTH, motor_test=None).encode())["motor_test"] is None


def test_a_snapshot_makes_the_same_json_as_before() -> None:
    table = EscTable([5], timeout_ms=500)
    table.ingest(EscTelemetry(node_id=5, rpm=1234, voltage_v=24.5, mos_temp_c=42.0), 1_000)
    table.ingest(EscTelemetry(node_id=5, current_a=3.0), 2_000)
    table.ingest(EscTelemetry(node_id=5, current_a=3.0), 3_600_000_000_000 + 2_000)
    (snap,) = table.snapshot(3_600_000_000_000 + 2_000 + 12_345_678)
    assert json.loads(EscTelemetryPayload.of(snap).encode()) == {
        "motor": 1,
        "node_id": 5,
        "online": True,
        "age_ms": 12.3,
        "rpm": 1234,
        "voltage_v": 24.5,
        "current_a": 3.0,
        "motor_current_a": None,
        "throttle": None,
        "temperature_c": {"mos": 42.0, "capacitor": None, "motor": None, "mcu": None},
        "status": None,
        "failure_flags": 0,
        "consumed_mah": 0.0,  # the gap was longer than the timeout: nothing added
        "command": None,
        "command_unit": "",
    }
    assert json.loads(EscInfoPayload.of(snap).encode()) == {
        "time_unix_ms": None,
        "motor": 1,
        "node_id": 5,
        "online": True,
        "frames": 3,
        "errors": 0,
        "failure_flags": 0,
        "counters": {},
    }
    status = EscStatusPayload.of([snap], 17)
    assert (status.time_unix_ms, status.count, status.online) == (17, 1, 1)


# -- the documented field names (docs/telemetry.md) -------------------------------------------


def _zenoh_section() -> str:
    text = TELEMETRY_PAGE.read_text(encoding="utf-8")
    return text[text.index("## Zenoh out") : text.index("### Latest values and liveliness")]


def _paragraph(section: str, key: str) -> str:
    start = section.index(f"`{key}`:")
    end = section.find("\n\n", start)
    return section[start : len(section) if end < 0 else end]


def _names(text: str) -> set[str]:
    """The names in backticks, and the quoted names of a JSON example in backticks."""
    names = set(re.findall(r"`([a-z_]+)`", text)) - {"null", "true", "false"}
    for example in re.findall(r"`(\{[^`]*\})`", text):
        names.update(re.findall(r'"([a-z_]+)"', example))
    return names


def _keys(record: Payload) -> set[str]:
    value = json.loads(record.encode())
    assert isinstance(value, dict)
    return set(value)


def test_telemetry_fields_are_the_documented_table() -> None:
    section = _zenoh_section()
    table = section[section.index("`esc/<n>/telemetry`:") : section.index("`esc/<n>/info`:")]
    documented = set(re.findall(r"^\| `([a-z_]+)`(?:, `([a-z_]+)`)? \|", table, re.MULTILINE))
    names = {name for pair in documented for name in pair if name}
    assert names == _keys(TELEMETRY)
    temperature = re.search(r"`temperature_c` \| `\{([^}]*)\}`", table)
    assert temperature is not None
    assert re.findall(r'"(\w+)"', temperature.group(1)) == list(
        json.loads(TELEMETRY.encode())["temperature_c"]
    )


@pytest.mark.parametrize(
    ("key", "record", "extra"),
    [
        ("esc/<n>/info", INFO, set()),
        ("esc/status", STATUS, set()),
        ("actuators/input", ACTUATORS_INPUT, set()),
        ("actuators/output", EVERY_KEY[-1], {"motor", "node_id", "value", "unit"}),
        ("bridge/health", HEALTH, {"session_up", "published", "dropped"}),
    ],
)
def test_each_keys_top_level_fields_are_the_documented_ones(
    key: str, record: Payload, extra: set[str]
) -> None:
    documented = _names(_paragraph(_zenoh_section(), key)) - {key.split("/")[-1]}
    if key == "esc/<n>/info":  # the counters' names are the ESC's, not the schema's
        documented -= {name for name in documented if name not in _keys(record)}
        assert {"power_on_count", "start_count"} <= _names(_paragraph(_zenoh_section(), key))
    if key == "bridge/health":  # the loop states named there are values of `state`
        documented -= {"no_input", "disarmed", "heartbeat_lost", "slow_stream", "stale"}
        documented -= {"invalid", "running", "stopping"}
    assert documented - extra == _keys(record)


def test_health_nested_fields() -> None:
    value: dict[str, Any] = json.loads(HEALTH.encode())
    assert {name: sorted(value[name]) for name in ("output", "input", "link", "can_rx")} == {
        "output": sorted(
            [
                "rate_hz",
                "configured_rate_hz",
                "ticks",
                "frames_sent",
                "send_errors",
                "overruns",
                "tick_errors",
                "bus_reopens",
                "realtime",
            ]
        ),
        "input": sorted(
            [
                "rate_hz",
                "outputs",
                "messages",
                "bad_data",
                "invalid",
                "mixer_errors",
                "age_ms",
                "out_of_order",
                "unsigned",
                "other_address",
            ]
        ),
        "link": ["reconnects", "relay_dropped", "send_dropped", "sent"],
        "can_rx": sorted(
            [
                "frames",
                "telemetry",
                "malformed",
                "read_errors",
                "kernel_drops",
                "unknown_esc_frames",
            ]
        ),
    }
    assert sorted(value["can_bus"]) == sorted(
        [
            "tx_state",
            "ticks_held",
            "tx_probes",
            "stuck",
            "down",
            "gone",
            "controller_state",
            "error_frames",
            "error_warning",
            "error_passive",
            "bus_off",
            "restarts",
            "receive_overflows",
            "reader_reopens",
        ]
    )
    assert sorted(value["zenoh"]) == ["dropped", "published", "session_up"]
    assert sorted(value["motor_test"]) == ["motor", "motors", "remaining_s", "throttle"]


# -- garbage ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("record", "payload", "message"),
    [
        (EscTelemetryPayload, b"", "esc/<n>/telemetry: not JSON"),
        (EscTelemetryPayload, b"null", "esc/<n>/telemetry: payload: expected an object, got null"),
        (EscInfoPayload, b'{"motor": 1}', "esc/<n>/info: field node_id missing"),
        (HealthPayload, b'{"state": 3}', "bridge/health: field state: expected a string, got 3"),
        (ActuatorsInputPayload, b"[]", "actuators/input: payload: expected an object, got []"),
    ],
)
def test_garbage_names_the_key_and_the_field(
    record: type[Payload], payload: bytes, message: str
) -> None:
    with pytest.raises(PayloadError, match=re.escape(message)):
        record.decode(payload)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"online": 1}, "field online: expected true or false, got 1"),
        ({"rpm": 1.5}, "field rpm: expected an integer, got 1.5"),
        ({"rpm": True}, "field rpm: expected an integer, got true"),
        ({"voltage_v": "12"}, 'field voltage_v: expected a number, got "12"'),
        ({"voltage_v": float("nan")}, "field voltage_v: expected a finite number, got nan"),
        ({"temperature_c": [1, 2]}, "field temperature_c: expected an object, got [1, 2]"),
        ({"temperature_c": {"mos": "hot"}}, "field temperature_c.mos: expected a number"),
        ({"command_unit": None}, "field command_unit: expected a string, got null"),
    ],
)
def test_a_wrong_field_is_named(change: dict[str, Any], message: str) -> None:
    value = json.loads(TELEMETRY.encode()) | change
    if isinstance(change.get("temperature_c"), dict):
        value["temperature_c"] = (
            json.loads(TELEMETRY.encode())["temperature_c"] | change["temperature_c"]
        )
    with pytest.raises(PayloadError, match=re.escape(f"esc/<n>/telemetry: {message}")):
        EscTelemetryPayload.decode(json.dumps(value).encode())


def test_deep_fields_are_named_with_their_path() -> None:
    value = json.loads(STATUS.encode())
    value["escs"][1]["temperature_c"]["mcu"] = "x"
    with pytest.raises(PayloadError, match=re.escape("field escs[1].temperature_c.mcu")):
        EscStatusPayload.decode(json.dumps(value).encode())
    value = json.loads(HEALTH.encode())
    del value["can_rx"]["kernel_drops"]
    with pytest.raises(PayloadError, match=re.escape("field can_rx.kernel_drops missing")):
        HealthPayload.decode(json.dumps(value).encode())


def test_nan_is_not_encoded() -> None:
    with pytest.raises(ValueError, match="JSON"):
        replace(TELEMETRY, voltage_v=float("nan")).encode()
