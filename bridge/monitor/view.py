"""The monitor's table: pure functions from ESC telemetry records to a rich table or plain text.

An ESC is one :class:`EscRow`: the record the bridge publishes in ``esc/status`` (decoded, so
every value has its type), with ``frames`` and ``errors`` from its ``esc/<n>/info`` once heard.
A value not reported, or a number that is not finite, shows as ``-``.
"""

from __future__ import annotations

import io
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from rich import box
from rich.console import Console, RenderableType
from rich.table import Table
from rich.text import Text

from bridge.escs.family import (
    FAILURE_GENERIC,
    FAILURE_INCONSISTENT_CMD,
    FAILURE_MOTOR_STUCK,
    FAILURE_OVER_CURRENT,
    FAILURE_OVER_RPM,
    FAILURE_OVER_TEMPERATURE,
    FAILURE_OVER_VOLTAGE,
)
from bridge.telemetry.payload import EscTelemetryPayload, HealthPayload

# MAVLink ESC_FAILURE_FLAGS bits -> the short names the table shows.
FAILURE_NAMES: tuple[tuple[int, str], ...] = (
    (FAILURE_OVER_CURRENT, "overcurrent"),
    (FAILURE_OVER_VOLTAGE, "overvolt"),
    (FAILURE_OVER_TEMPERATURE, "overtemp"),
    (FAILURE_OVER_RPM, "overrpm"),
    (FAILURE_INCONSISTENT_CMD, "badcmd"),
    (FAILURE_MOTOR_STUCK, "stuck"),
    (FAILURE_GENERIC, "generic"),
)
PLAIN_WIDTH = 250  # wide enough that no plain-text table ever wraps a cell
MISSING = "-"


@dataclass(frozen=True)
class EscRow:
    """One ESC as the monitor shows it."""

    telemetry: EscTelemetryPayload
    frames: int | None = None
    """Telemetry frames received, from ``esc/<n>/info`` (None: not heard yet)."""
    errors: int | None = None
    """CRC and format errors, from ``esc/<n>/info`` (None: not heard yet)."""


@dataclass(frozen=True)
class VehicleState:
    """What the monitor knows about one bridge (vehicle) at one moment."""

    name: str
    """The vehicle's name (its key prefix, without a leading ``esc-bridge/``) or the bus."""
    escs: tuple[EscRow, ...]
    """One row per ESC, in motor order."""
    stale: bool = False
    """No message from this vehicle within the stale limit (Zenoh only)."""
    age_s: float | None = None
    """Time since the last message from this vehicle; None when read directly from the bus."""
    note: str = ""
    """A line shown under the table (reader counters, malformed messages)."""
    health: HealthPayload | None = None
    """The bridge's last ``bridge/health`` (Zenoh only; None until heard)."""
    alive: bool | None = None
    """The bridge's liveliness token ``<prefix>/alive``: True while it exists, False once it
    went away (the bridge stopped or lost the network), None when never seen (the bus)."""


def failure_names(flags: int | None) -> str:
    """ESC_FAILURE_FLAGS as short names joined by spaces, unnamed bits as hex; ``""`` for no
    failure, ``-`` when the flags are missing."""
    if flags is None:
        return MISSING
    value = int(flags)
    names = [name for bit, name in FAILURE_NAMES if value & bit]
    unnamed = value & ~sum(bit for bit, _ in FAILURE_NAMES)
    if unnamed:
        names.append(hex(unnamed))
    return " ".join(names)


def render_table(vehicles: Sequence[VehicleState], *, plain: bool = False) -> Table:
    """One table of every ESC of every vehicle; a vehicle column when there are several.

    ``plain``: ASCII borders and no colours, for pipes and logs.
    """
    several = len(vehicles) > 1
    table = Table(
        title=_title(vehicles),
        caption=" | ".join(v.note for v in vehicles if v.note) or None,
        box=box.ASCII if plain else box.SIMPLE_HEAVY,
        title_justify="left",
        caption_justify="left",
        # Live: as narrow as readable, to fit 120 columns; plain: one space around each cell.
        pad_edge=plain,
        collapse_padding=not plain,
    )
    if several:
        table.add_column("vehicle")
    for header, justify in COLUMNS:
        # Numbers keep their width (never "12…"); the flags column wraps when space is short.
        wraps = header == "flags"
        table.add_column(
            header,
            justify=justify,
            no_wrap=not wraps,
            min_width=_MIN_WIDTHS.get(header, len(header)),
        )
    for vehicle in vehicles:
        for esc in vehicle.escs:
            cells = row_cells(esc, vehicle.stale)
            style = "dim" if vehicle.stale else ""
            row: list[RenderableType] = []
            if several:
                label = f"{vehicle.name} (stale)" if vehicle.stale else vehicle.name
                row.append(Text(label, style=style))
            row += [Text(text, style=_style(column, text) or style) for column, text in cells]
            table.add_row(*row)
    return table


def waiting_text(where: str) -> str:
    """What the monitor shows before any data came."""
    return f"waiting for esc-bridge on {where}"


def plain_text(vehicles: Sequence[VehicleState]) -> str:
    """The table as plain text (ASCII borders, no colour, trailing spaces stripped)."""
    buffer = io.StringIO()
    console = Console(
        file=buffer,
        width=PLAIN_WIDTH,
        color_system=None,
        force_terminal=False,
        highlight=False,
        emoji=False,
        legacy_windows=False,
    )
    console.print(render_table(vehicles, plain=True))
    return "\n".join(line.rstrip() for line in buffer.getvalue().splitlines())


def _title(vehicles: Sequence[VehicleState]) -> str:
    if len(vehicles) == 1:
        vehicle = vehicles[0]
        if vehicle.stale:
            return (
                f"{vehicle.name}: STALE, no data for {_age_s(vehicle.age_s)} "
                f"(last heard: {_online_count(vehicle)})"
            )
        return f"{vehicle.name}: {_online_count(vehicle)}"
    stale = sum(1 for v in vehicles if v.stale)
    title = f"{len(vehicles)} vehicles: " + ", ".join(
        f"{v.name} {_online_count(v)}" for v in vehicles
    )
    return title + (f"; {stale} stale" if stale else "")


def _online_count(vehicle: VehicleState) -> str:
    online = sum(1 for esc in vehicle.escs if esc.telemetry.online)
    return f"{online}/{len(vehicle.escs)} ESCs online"


def _age_s(age_s: float | None) -> str:
    return MISSING if age_s is None else f"{age_s:.1f} s"


def _number(value: float | None, digits: int, scale: float = 1.0) -> str:
    if value is None or not math.isfinite(value):
        return MISSING
    return f"{float(value) * scale:.{digits}f}"


def _integer(value: int | None) -> str:
    return MISSING if value is None else str(value)


def _state(esc: EscRow, stale: bool) -> str:
    if stale:
        return "stale"
    return "online" if esc.telemetry.online else "offline"


def _age_ms(value: float | None) -> str:
    if value is None or not math.isfinite(value):
        return MISSING
    return f"{value:.0f} ms" if value < 1000 else f"{value / 1000:.1f} s"


# (header, justify) of every column, and how each cell is made from an ESC's row.
_CELLS: tuple[tuple[str, str, Callable[[EscRow, bool], str]], ...] = (
    ("motor", "right", lambda e, s: _integer(e.telemetry.motor)),
    ("node", "right", lambda e, s: _integer(e.telemetry.node_id)),
    ("state", "left", _state),
    ("rpm", "right", lambda e, s: _integer(e.telemetry.rpm)),
    ("V", "right", lambda e, s: _number(e.telemetry.voltage_v, 2)),
    ("A", "right", lambda e, s: _number(e.telemetry.current_a, 2)),
    ("mAh", "right", lambda e, s: _number(e.telemetry.consumed_mah, 0)),
    ("MOS°C", "right", lambda e, s: _number(e.telemetry.temperature_c.mos, 0)),
    ("motor°C", "right", lambda e, s: _number(e.telemetry.temperature_c.motor, 0)),
    ("cap°C", "right", lambda e, s: _number(e.telemetry.temperature_c.capacitor, 0)),
    ("MCU°C", "right", lambda e, s: _number(e.telemetry.temperature_c.mcu, 0)),
    ("thr%", "right", lambda e, s: _number(e.telemetry.throttle, 0, 100.0)),
    ("flags", "left", lambda e, s: failure_names(e.telemetry.failure_flags)),
    ("frames", "right", lambda e, s: _integer(e.frames)),
    ("errors", "right", lambda e, s: _integer(e.errors)),
    ("age", "right", lambda e, s: _age_ms(e.telemetry.age_ms)),
)
_MIN_WIDTHS = {
    "state": len("offline"),
    "flags": 8,
    "age": len("999 ms"),
    "V": len("99.99"),
    "rpm": len("99999"),
}
COLUMNS: tuple[tuple[str, Any], ...] = tuple((header, justify) for header, justify, _ in _CELLS)
"""The table's columns after the optional vehicle column: (header, justification)."""


def row_cells(esc: EscRow, stale: bool) -> list[tuple[str, str]]:
    """One ESC's row as (column header, text), in :data:`COLUMNS` order: the terminal's table
    and the web page show the same texts."""
    return [(header, cell(esc, stale)) for header, _, cell in _CELLS]


def _style(column: str, text: str) -> str:
    if column == "state":
        return {"online": "green", "offline": "bold red", "stale": "yellow"}.get(text, "")
    if column == "flags" and text not in ("", MISSING):
        return "bold red"
    if column == "errors" and text not in ("0", MISSING):
        return "yellow"
    return ""
