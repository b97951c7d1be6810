"""The bridge's JSON records: their JSON form (:func:`to_json`) and its JSON Schema
(:func:`record_schema`), both from the records' dataclass fields.

A record (a dataclass, as in :mod:`bridge.telemetry.payload`) is one JSON object: its fields by
name, nested records as objects, tuples as arrays, ``dict[str, X]`` as objects, and a field that
may be None as that type or ``null``. A field whose metadata says ``omit_none`` is left out when
None, so it is optional; every other field is required, and no other name is allowed. The
schema is made from the same fields, so it cannot drift from its record.

Pure: no I/O.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from typing import Any, Final

DIALECT: Final = "https://json-schema.org/draft/2020-12/schema"
"""The JSON Schema version written (``$schema``)."""

_SCALARS: Final[dict[type, str]] = {bool: "boolean", int: "integer", float: "number", str: "string"}


_PLAIN: Final = frozenset({str, int, float, bool, type(None)})
_FIELDS: dict[type, tuple[tuple[str, bool], ...]] = {}
"""Per record class: (field name, left out when None), in order; read once, not per record
(the Zenoh publisher and the MCAP writer encode hundreds of records a second, and
``dataclasses.fields()`` per record was most of the publisher's CPU)."""


def _fields(cls: type) -> tuple[tuple[str, bool], ...]:
    found = _FIELDS.get(cls)
    if found is None:
        found = _FIELDS[cls] = tuple(
            (f.name, bool(f.metadata.get("omit_none"))) for f in dataclasses.fields(cls)
        )
    return found


def to_json(value: object) -> object:
    """``value`` (a record, or a field's value) as the JSON encoder takes it."""
    kind = type(value)
    if kind in _PLAIN:
        return value
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        out: dict[str, object] = {}
        for name, omit_none in _fields(kind):
            item = getattr(value, name)
            if item is not None:
                out[name] = to_json(item)
            elif not omit_none:
                out[name] = None
        return out
    if isinstance(value, tuple | list):
        return [to_json(item) for item in value]
    if isinstance(value, dict):
        return {name: to_json(item) for name, item in value.items()}
    return value


def record_schema(cls: type[Any], title: str | None = None) -> dict[str, Any]:
    """The JSON Schema of the record class ``cls``, titled ``title`` (default: the class's
    name) and described by the first paragraph of its docstring.

    Raises:
        TypeError: a field's type has no JSON form here.
    """
    schema: dict[str, Any] = {"$schema": DIALECT, "title": title or cls.__name__}
    doc = (cls.__doc__ or "").strip().split("\n\n")[0]
    if doc:
        schema["description"] = " ".join(doc.split())
    schema.update(_object(cls))
    return schema


def _object(cls: type[Any]) -> dict[str, Any]:
    hints = typing.get_type_hints(cls)
    properties: dict[str, Any] = {}
    required: list[str] = []
    for field in dataclasses.fields(cls):
        properties[field.name] = _schema(hints[field.name], f"{cls.__name__}.{field.name}")
        if not field.metadata.get("omit_none"):
            required.append(field.name)
    return {
        "type": "object",
        "properties": properties,
        "required": required,
        "additionalProperties": False,
    }


def _schema(kind: Any, where: str) -> dict[str, Any]:
    origin = typing.get_origin(kind)
    if origin is types.UnionType or origin is typing.Union:
        options = [a for a in typing.get_args(kind) if a is not type(None)]
        if len(options) != 1:
            raise TypeError(f"{where}: a union of {options} has no JSON form here")
        inner = _schema(options[0], where)
        if set(inner) == {"type"}:
            return {"type": [inner["type"], "null"]}
        return {"anyOf": [inner, {"type": "null"}]}
    if isinstance(kind, type) and dataclasses.is_dataclass(kind):
        return _object(kind)
    if origin is tuple:
        return {"type": "array", "items": _schema(typing.get_args(kind)[0], f"{where}[]")}
    if origin is dict:
        return {
            "type": "object",
            "additionalProperties": _schema(typing.get_args(kind)[1], f"{where}{{}}"),
        }
    if kind in _SCALARS:
        return {"type": _SCALARS[kind]}
    raise TypeError(f"{where}: {kind!r} has no JSON form here")
