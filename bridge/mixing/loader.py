"""Loading mixer definitions: bundled ones by name, any other by path.

The loader fills defaults, names the file and the entry in each error, and refuses unknown and
duplicate keys; the rotor outputs' weights come from the geometry
(:func:`~bridge.mixing.geometry.mix_matrix`). Schema: ``mixers/README.md``.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from importlib import resources
from pathlib import Path

from bridge._compat import tomllib
from bridge.errors import ConfigError
from bridge.mixing.definition import AXIS_NAMES, PWM_RANGE_US, MixerDefinition, OutputSpec, Rotor
from bridge.mixing.geometry import mix_matrix

__all__ = ["bundled_mixer_names", "load_mixer"]

_NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*\Z")


def bundled_mixer_names() -> list[str]:
    """Names of the mixers shipped in ``bridge.mixers`` (file names without ``.toml``), sorted."""
    return sorted(
        entry.name.removesuffix(".toml")
        for entry in resources.files("bridge.mixers").iterdir()
        if entry.name.endswith(".toml")
    )


def load_mixer(
    name_or_path: str, *, input_range: tuple[float, float] | None = None
) -> MixerDefinition:
    """Load a bundled mixer by name (``"quad-x"``) or a definition file by path.

    A string ending in ``.toml`` or containing a path separator is a path. ``input_range``
    overrides every channel input range (see :meth:`MixerDefinition.with_input_range`).

    Raises:
        ConfigError: unknown name, unreadable file, invalid TOML, or an invalid definition;
            the message names the file and the entry.
    """
    if name_or_path.endswith(".toml") or "/" in name_or_path or "\\" in name_or_path:
        path = Path(name_or_path)
        source = str(path)
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise ConfigError(f"{source}: cannot read mixer: {exc.strerror or exc}") from exc
        stem = path.stem
    else:
        names = bundled_mixer_names()
        if name_or_path not in names:
            raise ConfigError(
                f"unknown mixer {name_or_path!r}; bundled: {', '.join(names)} (or give a path)"
            )
        resource = resources.files("bridge.mixers").joinpath(f"{name_or_path}.toml")
        source = str(resource)
        data = resource.read_bytes()
        stem = name_or_path
    try:
        text = data.decode("utf-8")
        document = tomllib.loads(text)
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{source}: not UTF-8 text: {exc}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{source}: invalid TOML: {exc}{_quote_line(text, str(exc))}") from exc
    definition = _parse_definition(document, source, stem)
    if input_range is not None:
        definition = definition.with_input_range(*input_range)
    return definition


def _quote_line(text: str, message: str) -> str:
    """Quote the line a TOML error points at, or return "" when the message names none.

    tomllib reports a duplicate key by line number only; the line's text names the entry.
    """
    match = re.search(r"at line (\d+)", message)
    lines = text.splitlines()
    if match is None or not 1 <= int(match.group(1)) <= len(lines):
        return ""
    return f": {lines[int(match.group(1)) - 1].strip()!r}"


# Keys each entry accepts; a default table accepts the same minus the entry's identity keys.
_OUTPUT_SHAPE_KEYS = frozenset({"idle", "max", "slew_up", "slew_down"})
_OUTPUT_KEYS = _OUTPUT_SHAPE_KEYS | {
    "name",
    "source",
    "offset",
    "input_range",
    "reversed",
    "deadband",
    "min",
}
_OUTPUT_DEFAULT_KEYS = _OUTPUT_KEYS - {"name", "source"}
_ROTOR_KEYS = _OUTPUT_SHAPE_KEYS | {"name", "position", "axis", "direction", "Ct", "Cm"}
_ROTOR_DEFAULT_KEYS = _ROTOR_KEYS - {"name", "position"}
_TOP_KEYS = frozenset({"info", "output_default", "outputs", "rotor_default", "rotors"})
_INFO_KEYS = frozenset({"key", "description"})


def _table(value: object, what: str) -> dict[str, object]:
    if not isinstance(value, dict):
        raise ValueError(f"{what} must be a table, got {value!r}")
    return value


def _array_of_tables(value: object, what: str) -> list[object]:
    if not isinstance(value, list):
        raise ValueError(f"{what} must be an array of tables ([[{what}]]), got {value!r}")
    return value


def _check_keys(table: Mapping[str, object], allowed: frozenset[str], what: str) -> None:
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise ValueError(
            f"unknown key{'s' if len(unknown) > 1 else ''} {', '.join(map(repr, unknown))} "
            f"in {what} (allowed: {', '.join(sorted(allowed))})"
        )


def _number(value: object, what: str) -> float:
    # bool is an int subclass in Python; a TOML 'true' where a number belongs is a mistake.
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"{what} must be a number, got {value!r}")
    return float(value)


def _string(value: object, what: str) -> str:
    if not isinstance(value, str) or not value:
        raise ValueError(f"{what} must be a non-empty string, got {value!r}")
    return value


def _boolean(value: object, what: str) -> bool:
    if not isinstance(value, bool):
        raise ValueError(f"{what} must be true or false, got {value!r}")
    return value


def _vector(value: object, length: int, what: str) -> tuple[float, ...]:
    if not isinstance(value, list) or len(value) != length:
        raise ValueError(f"{what} must be an array of {length} numbers, got {value!r}")
    return tuple(_number(x, f"{what}[{i}]") for i, x in enumerate(value))


def _weights(value: object) -> tuple[tuple[str, float], ...]:
    if isinstance(value, str):
        return ((value, 1.0),)
    if isinstance(value, dict):
        return tuple((name, _number(w, f"source weight of {name!r}")) for name, w in value.items())
    raise ValueError(
        'source must be an input name ("ch3") or a table of weights '
        f"({{ roll = -0.5, thrust = 1.0 }}), got {value!r}"
    )


def _shape_fields(entry: Mapping[str, object]) -> tuple[float, float, float]:
    """``max``, ``slew_up``, ``slew_down`` with defaults (rotors and outputs share these)."""
    return (
        _number(entry.get("max", 1.0), "max"),
        _number(entry.get("slew_up", 0.0), "slew_up"),
        _number(entry.get("slew_down", 0.0), "slew_down"),
    )


def _parse_output(entry: Mapping[str, object]) -> OutputSpec:
    if "source" not in entry:
        raise ValueError("missing key 'source'")
    minimum = _number(entry.get("min", 0.0), "min")
    low, high = _vector(entry.get("input_range", list(PWM_RANGE_US)), 2, "input_range")
    maximum, slew_up, slew_down = _shape_fields(entry)
    return OutputSpec(
        name=_string(entry["name"], "name"),
        weights=_weights(entry["source"]),
        offset=_number(entry.get("offset", 0.0), "offset"),
        input_range=(low, high),
        reversed=_boolean(entry.get("reversed", False), "reversed"),
        deadband=_number(entry.get("deadband", 0.0), "deadband"),
        minimum=minimum,
        # No floor unless asked for: a reversible output must be free to go below 0.
        idle=_number(entry.get("idle", minimum), "idle"),
        maximum=maximum,
        slew_up_per_s=slew_up,
        slew_down_per_s=slew_down,
    )


def _parse_rotor(entry: Mapping[str, object]) -> Rotor:
    if "direction" not in entry:
        raise ValueError("missing key 'direction' ('CW' or 'CCW', in the rotor or rotor_default)")
    direction = entry["direction"]
    if direction not in ("CW", "CCW"):
        raise ValueError(f"direction must be 'CW' or 'CCW', got {direction!r}")
    px, py, pz = _vector(entry["position"], 3, "position")
    ax, ay, az = _vector(entry.get("axis", [0.0, 0.0, -1.0]), 3, "axis")
    return Rotor(
        name=_string(entry["name"], "name"),
        position_m=(px, py, pz),
        direction="CW" if direction == "CW" else "CCW",
        axis=(ax, ay, az),
        ct=_number(entry.get("Ct", 1.0), "Ct"),
        cm=_number(entry.get("Cm", 0.05), "Cm"),
    )


def _entry_label(kind: str, number: int, entry: Mapping[str, object]) -> str:
    name = entry.get("name")
    return f"{kind} {number} ({name!r})" if isinstance(name, str) else f"{kind} {number}"


def _parse_definition(document: Mapping[str, object], source: str, stem: str) -> MixerDefinition:
    """Validate a parsed TOML document into a MixerDefinition; ConfigError names file and entry."""

    def fail(where: str, exc: Exception) -> ConfigError:
        return ConfigError(f"{source}: {where}: {exc}")

    try:
        _check_keys(document, _TOP_KEYS, "the top level")
    except ValueError as exc:
        raise fail("top level", exc) from exc
    try:
        info = _table(document.get("info"), "[info]")
        _check_keys(info, _INFO_KEYS, "[info]")
        description = _string(info.get("description"), "description")
        name = _string(info.get("key", stem), "key")
        if not _NAME_RE.match(name):
            raise ValueError(f"key {name!r}: use letters, digits, '.', '_', '-'")
    except ValueError as exc:
        raise fail("info", exc) from exc

    defaults: dict[str, dict[str, object]] = {}
    lists: dict[str, list[object]] = {}
    for table_key, list_key, allowed in (
        ("output_default", "outputs", _OUTPUT_DEFAULT_KEYS),
        ("rotor_default", "rotors", _ROTOR_DEFAULT_KEYS),
    ):
        try:
            defaults[list_key] = _table(document.get(table_key, {}), f"[{table_key}]")
            _check_keys(defaults[list_key], allowed, f"[{table_key}]")
        except ValueError as exc:
            raise fail(table_key, exc) from exc
        try:
            lists[list_key] = _array_of_tables(document.get(list_key, []), list_key)
        except ValueError as exc:
            raise fail(list_key, exc) from exc

    rotors: list[Rotor] = []
    # Per rotor: idle, max, slew_up, slew_down.
    rotor_fields: list[tuple[float, float, float, float]] = []
    for i, raw in enumerate(lists["rotors"], start=1):
        label = f"rotor {i}"
        try:
            entry = _table(raw, label)
            label = _entry_label("rotor", i, entry)
            _check_keys(entry, _ROTOR_KEYS, "a rotor (reversed, deadband and min are fixed)")
            for required in ("name", "position"):
                if required not in entry:
                    raise ValueError(f"missing key {required!r}")
            merged = {**defaults["rotors"], **entry}
            rotors.append(_parse_rotor(merged))
            rotor_fields.append((_number(merged.get("idle", 0.0), "idle"), *_shape_fields(merged)))
        except ValueError as exc:
            raise fail(label, exc) from exc

    outputs: list[OutputSpec] = []
    if rotors:
        try:
            matrix = mix_matrix(rotors)
        except ValueError as exc:
            raise fail("rotors", exc) from exc
        rows = zip(rotors, matrix, rotor_fields, strict=True)
        for i, (rotor, row, (idle, maximum, slew_up, slew_down)) in enumerate(rows, start=1):
            try:
                outputs.append(
                    OutputSpec(
                        name=rotor.name,
                        weights=tuple(zip(AXIS_NAMES, row, strict=True)),
                        idle=idle,
                        maximum=maximum,
                        slew_up_per_s=slew_up,
                        slew_down_per_s=slew_down,
                        rotor=rotor,
                    )
                )
            except ValueError as exc:
                raise fail(f"rotor {i} ({rotor.name!r})", exc) from exc

    for j, raw in enumerate(lists["outputs"], start=1):
        number = len(rotors) + j
        label = f"output {number}"
        try:
            entry = _table(raw, label)
            label = _entry_label("output", number, entry)
            _check_keys(entry, _OUTPUT_KEYS, "an output")
            if "name" not in entry:
                raise ValueError("missing key 'name'")
            outputs.append(_parse_output({**defaults["outputs"], **entry}))
        except ValueError as exc:
            raise fail(label, exc) from exc

    if not outputs:
        raise ConfigError(f"{source}: defines no outputs (add [[rotors]] or [[outputs]])")
    try:
        return MixerDefinition(
            name=name, description=description, outputs=tuple(outputs), path=source
        )
    except ValueError as exc:
        raise ConfigError(f"{source}: {exc}") from exc
