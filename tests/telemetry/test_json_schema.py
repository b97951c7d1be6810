"""A record's JSON Schema (bridge/telemetry/json_schema.py): it takes what the record encodes to,
refuses a missing or unknown field and a value of the wrong type, and knows every Zenoh key's
record."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any

import pytest

from bridge.telemetry.json_schema import DIALECT, record_schema, to_json
from bridge.telemetry.payload import RECORDS, EscTelemetryPayload, Temperatures

jsonschema = pytest.importorskip(
    "jsonschema", reason="jsonschema (in the test extra) is not installed: pip install -e '.[test]'"
)


def telemetry(**changes: object) -> EscTelemetryPayload:
    values: dict[str, object] = {
        "motor": 1,
        "node_id": 7,
        "online": True,
        "age_ms": 2.5,
        "rpm": -1200,
        "voltage_v": 24.1,
        "current_a": None,
        "motor_current_a": None,
        "throttle": 0.5,
        "temperature_c": Temperatures(mos=41.0, capacitor=None, motor=None, mcu=None),
        "status": None,
        "failure_flags": 4,
        "consumed_mah": 1.25,
        "command": 1100.0,
        "command_unit": "throttle",
    }
    values.update(changes)
    return EscTelemetryPayload(**values)  # type: ignore[arg-type]


def validator(cls: type) -> Any:
    schema = record_schema(cls)
    jsonschema.Draft202012Validator.check_schema(schema)
    return jsonschema.Draft202012Validator(schema)


def test_the_schema_takes_the_records_json_and_refuses_what_differs() -> None:
    check = validator(EscTelemetryPayload)
    schema = record_schema(EscTelemetryPayload)
    assert schema["$schema"] == DIALECT and schema["title"] == "EscTelemetryPayload"
    assert schema["description"].startswith("``esc/<n>/telemetry``")
    encoded = json.loads(json.dumps(to_json(telemetry())))
    check.validate(encoded)
    check.validate(json.loads(telemetry(time_unix_ms=5).encode()))  # omit_none: optional
    assert "time_unix_ms" not in schema["required"] and "rpm" in schema["required"]
    bad = [
        {k: v for k, v in encoded.items() if k != "rpm"},  # missing
        {**encoded, "colour": "red"},  # unknown
        {**encoded, "rpm": 1.5},  # an integer field
        {**encoded, "online": 1},  # a boolean field
        {**encoded, "temperature_c": {**encoded["temperature_c"], "mos": "hot"}},  # nested
    ]
    for document in bad:
        assert not check.is_valid(document), document


def test_every_zenoh_records_schema_takes_its_json() -> None:
    for cls in RECORDS:
        validator(cls)  # a valid schema, for every field type the records use


@dataclass(frozen=True)
class Inner:
    value: float


@dataclass(frozen=True)
class Outer:
    items: tuple[Inner, ...]
    names: dict[str, int]
    maybe: Inner | None
    skipped: str | None = field(default=None, metadata={"omit_none": True})


@dataclass(frozen=True)
class Odd:
    either: int | str


def test_tuples_and_maps() -> None:
    check = validator(Outer)
    record = Outer((Inner(1.0), Inner(2)), {"a": 1}, None)
    assert to_json(record) == {
        "items": [{"value": 1.0}, {"value": 2}],
        "names": {"a": 1},
        "maybe": None,
    }
    check.validate(to_json(record))
    assert not check.is_valid({**to_json(record), "names": {"a": "one"}})  # type: ignore[dict-item]


def test_a_type_without_a_json_form_is_named() -> None:
    with pytest.raises(TypeError, match=r"Odd\.either"):
        record_schema(Odd)
