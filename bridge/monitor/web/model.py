"""What the web page shows, as JSON: pure functions from the monitor's vehicles to the page's
messages, and the last minute of chart points.

The page only renders what it is sent. Every judgement (which ESC is failing, which counter is a
warning, what a cell says) is made here, where it is tested, and the cells are the terminal
table's own texts (:func:`bridge.monitor.view.row_cells`). :class:`PageModel` makes the two
messages:

- :meth:`~PageModel.hello`, once per browser when it connects: the columns, the chart window
  and the chart points of the last minute (:class:`ChartHistory`);
- :meth:`~PageModel.snapshot`, every push: every vehicle's card, and the one chart point this
  push adds.

The bridge's counters (dropped frames, bus errors, ...) count from its start, so a health item
is a warning while its counter grew within the last :data:`RECENT_S`, not for ever after one
error: the model remembers each counter's last value and when it last grew.

A chart point is ``[rpm, amps, °C]`` per motor: rpm and supply current as reported, and the
hottest of the ESC's temperatures; ``None`` (a gap) where the ESC is offline or the value was
not reported. A stale vehicle adds no point, so its charts show a gap from when it went quiet.
"""

from __future__ import annotations

import functools
import math
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Final

from bridge.monitor.view import COLUMNS, EscRow, VehicleState, failure_names, row_cells
from bridge.telemetry.payload import HealthPayload

WINDOW_S: Final = 60.0
"""The charts' time span: the last minute."""
SERIES: Final = ("rpm", "current_a", "temp_c")
"""A chart point's values per motor, in order; one chart each."""
MINOR_COLUMNS: Final = frozenset(("node", "cap°C", "MCU°C", "thr%", "frames", "errors", "age"))
"""Columns a phone's narrow screen leaves out (the table scrolls sideways to them)."""
RECENT_S: Final = 10.0
"""A health counter that grew within this long makes its item a warning."""

# Loop states (bridge/health ``state``) by how the page colours them: disarmed and running are
# the normal ones; waiting for the autopilot or stopping, a warning; the rest, a fault.
_STATE_LEVELS: Final = {
    "disarmed": "ok",
    "running": "ok",
    "motor_test": "warn",
    "no_input": "warn",
    "stopping": "warn",
}

Json = dict[str, Any]
Point = list[list[float | None]]
Grew = Callable[[str, int], bool]
"""``grew(counter, value)``: did this counter grow within :data:`RECENT_S`?"""


class PageModel:
    """The page's messages for one source; it keeps the charts' last minute and the health
    counters' history, so one instance serves every browser."""

    def __init__(self, where: str, window_s: float = WINDOW_S) -> None:
        self.where = where
        self.history = ChartHistory(window_s)
        self._counters: dict[tuple[str, str], tuple[int, float]] = {}  # -> (value, when grew)

    def hello(self, period_s: float) -> Json:
        """The first message to a browser: the table's columns, how often snapshots come,
        and the charts' last minute."""
        return {
            "source": self.where,
            "period_s": period_s,
            "window_s": self.history.window_s,
            "series": list(SERIES),
            "columns": [
                {"name": name, "align": align, "minor": name in MINOR_COLUMNS}
                for name, align in COLUMNS
            ],
            "history": self.history.as_json(),
        }

    def snapshot(self, vehicles: Sequence[VehicleState], t_s: float) -> Json:
        """Every vehicle's card at ``t_s`` (seconds since the monitor started: the charts'
        clock); the chart points go into the history too."""
        cards = [
            vehicle_card(vehicle, functools.partial(self._grew, vehicle.name, t_s=t_s))
            for vehicle in vehicles
        ]
        self.history.add(t_s, cards)
        return {"source": self.where, "t": round(t_s, 2), "vehicles": cards}

    def _grew(self, vehicle: str, counter: str, value: int, t_s: float) -> bool:
        key = (vehicle, counter)
        last = self._counters.get(key)
        if last is None:  # first seen: what it counted before the monitor started is old news
            self._counters[key] = (value, -math.inf)
            return False
        if value > last[0]:
            self._counters[key] = (value, t_s)
            return True
        if value < last[0]:  # the bridge restarted: its counters too
            self._counters[key] = (value, last[1])
        return t_s - last[1] <= RECENT_S


def vehicle_card(vehicle: VehicleState, grew: Grew = lambda counter, value: False) -> Json:
    """One vehicle: its state, its alerts, its health items, its ESC rows, its chart point."""
    alerts = esc_alerts(vehicle.escs) if not vehicle.stale else []
    health = health_items(vehicle.health, grew) if vehicle.health is not None else []
    if vehicle.stale:
        level = "stale"
    elif alerts or any(item["level"] == "bad" for item in health):
        level = "bad"
    elif any(item["level"] == "warn" for item in health) or not vehicle.escs:
        level = "warn"
    else:
        level = "ok"
    online = sum(1 for esc in vehicle.escs if esc.telemetry.online)
    return {
        "name": vehicle.name,
        "level": level,
        "stale": vehicle.stale,
        "alive": vehicle.alive,
        "age_s": None if vehicle.age_s is None else round(vehicle.age_s, 1),
        "summary": _summary(vehicle, online),
        "alerts": alerts,
        "health": health,
        "note": vehicle.note,
        "escs": [
            {
                "motor": esc.telemetry.motor,
                "level": esc_level(esc, vehicle.stale),
                "cells": [text for _, text in row_cells(esc, vehicle.stale)],
            }
            for esc in vehicle.escs
        ],
        "point": chart_point(vehicle),
    }


def esc_level(esc: EscRow, stale: bool) -> str:
    """How a row stands out: ``stale`` (its vehicle), ``failure`` (a flag is set), ``offline``
    or ``ok``. A failure outranks offline: an offline ESC's last flags are still its last word."""
    if stale:
        return "stale"
    if esc.telemetry.failure_flags:
        return "failure"
    return "ok" if esc.telemetry.online else "offline"


def esc_alerts(escs: Sequence[EscRow]) -> list[str]:
    """One line per ESC that is failing or offline, for the card's banner."""
    alerts = []
    for esc in escs:
        t = esc.telemetry
        if t.failure_flags:
            alerts.append(f"motor {t.motor}: {failure_names(t.failure_flags)}")
        if not t.online:
            alerts.append(f"motor {t.motor}: offline")
    return alerts


def health_items(health: HealthPayload, grew: Grew = lambda counter, value: False) -> list[Json]:
    """The card's health line: the bridge (its loop's state and output rate), the autopilot
    (armed, its outputs' rate and age), its link and the CAN bus, each a short text and a level
    (``ok``, ``warn``, ``bad``). The loop's state sets the bridge's level; a counter that
    ``grew`` lately makes its item a warning."""
    out = health.output
    bridge = health.state.replace("_", " ")
    if health.motor_test is not None:
        test = health.motor_test
        spinning = "-" if test.motor is None else str(test.motor)
        bridge += f" (motor {spinning}, {test.throttle * 100:.0f} %, {test.remaining_s:.0f} s left)"
    elif health.failsafe and health.state != "disarmed":
        bridge += ", safe values"
    bridge += f", {out.rate_hz:.0f}/{out.configured_rate_hz} Hz out"
    i = health.input
    autopilot = f"{'armed' if health.armed else 'disarmed'}, {i.rate_hz:.0f} Hz"
    if i.outputs:  # (the bridge's estimate of the autopilot's clock may put it a little ahead)
        autopilot += f", newest {max(i.age_ms, 0.0):.0f} ms old"
    refused = (
        i.bad_data + i.invalid + i.mixer_errors + i.out_of_order + i.unsigned + i.other_address
    )
    if refused:
        autopilot += f", {refused} refused"
    link = health.link
    lost = link.relay_dropped + link.send_dropped
    rx = health.can_rx
    bus_errors = rx.malformed + rx.read_errors + (rx.kernel_drops or 0) + out.send_errors
    bus = f"{rx.frames} frames in, {bus_errors} errors"
    if out.bus_reopens:
        bus += f", {out.bus_reopens} reopens"
    return [
        {"name": "bridge", "text": bridge, "level": _STATE_LEVELS.get(health.state, "bad")},
        {"name": "autopilot", "text": autopilot, "level": _warn(grew("refused", refused))},
        {
            "name": "link",
            "text": f"{lost} frames dropped, {link.reconnects} reconnects",
            # | and not "or": both counters are followed on every snapshot.
            "level": _warn(grew("link lost", lost) | grew("reconnects", link.reconnects)),
        },
        {
            "name": "bus",
            "text": bus,
            "level": _warn(grew("bus errors", bus_errors) | grew("reopens", out.bus_reopens)),
        },
    ]


def _warn(recent: bool) -> str:
    return "warn" if recent else "ok"


def chart_point(vehicle: VehicleState) -> Point | None:
    """``[rpm, amps, hottest °C]`` per motor now; None for a stale vehicle (no point)."""
    if vehicle.stale:
        return None
    return [_esc_point(esc) for esc in vehicle.escs]


@dataclass
class ChartHistory:
    """The chart points of the last :attr:`window_s` per vehicle, oldest first."""

    window_s: float = WINDOW_S
    _points: dict[str, deque[tuple[float, Point]]] = field(default_factory=dict)

    def add(self, t_s: float, cards: Sequence[Json]) -> None:
        """Keep each card's point (a :func:`vehicle_card`) at ``t_s``; forget what is older
        than the window."""
        for card in cards:
            point = card["point"]
            if point is not None:
                self._points.setdefault(card["name"], deque()).append((round(t_s, 2), point))
        for points in self._points.values():
            while points and points[0][0] < t_s - self.window_s:
                points.popleft()

    def as_json(self) -> Json:
        """Per vehicle, ``{"t": [...], "<series>": [per motor: [...]]}`` (columns, as the page
        draws them)."""
        result: Json = {}
        for name, points in self._points.items():
            motors = max((len(point) for _, point in points), default=0)
            entry: Json = {"t": [t for t, _ in points]}
            for index, series in enumerate(SERIES):
                entry[series] = [
                    [point[m][index] if m < len(point) else None for _, point in points]
                    for m in range(motors)
                ]
            result[name] = entry
        return result


def _summary(vehicle: VehicleState, online: int) -> str:
    if vehicle.stale:
        why = "bridge gone" if vehicle.alive is False else "no data"
        age = "" if vehicle.age_s is None else f" for {vehicle.age_s:.1f} s"
        return f"STALE: {why}{age}"
    if not vehicle.escs:
        return "waiting for ESC telemetry"
    return f"{online}/{len(vehicle.escs)} ESCs online"


def _esc_point(esc: EscRow) -> list[float | None]:
    t = esc.telemetry
    if not t.online:
        return [None, None, None]
    temps = [
        value
        for value in (
            t.temperature_c.mos,
            t.temperature_c.motor,
            t.temperature_c.capacitor,
            t.temperature_c.mcu,
        )
        if value is not None and math.isfinite(value)
    ]
    current = t.current_a if t.current_a is not None and math.isfinite(t.current_a) else None
    return [
        t.rpm,
        None if current is None else round(current, 2),
        max(temps) if temps else None,
    ]
