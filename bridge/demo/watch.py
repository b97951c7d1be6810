"""What ``esc-bridge demo`` watches of the bridge: the monitor's Zenoh source, connected to the
demo's bridge, and the per-ESC record the summary at the end is made of."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Final

from bridge.config import ZenohConfig
from bridge.monitor import VehicleState, ZenohSource, monitor_zenoh_config

VEHICLE: Final = "demo"
PREFIX: Final = f"esc-bridge/{VEHICLE}"
LOOPBACK: Final = "127.0.0.1"


class DemoSource(ZenohSource):
    """The monitor's source, connected to the demo's bridge."""

    @classmethod
    def connect(cls, endpoint: str) -> DemoSource:
        """A peer session connected to the bridge's endpoint, scouting off, listening on
        loopback only.

        Raises:
            ConfigError: the endpoint is malformed.
            LinkError: the session cannot be opened.
        """
        # What the monitor makes of a bridge listening there, but listening on loopback only
        # itself (a peer otherwise listens on every interface).
        bridge_side = ZenohConfig(listen=(endpoint,), multicast_scouting=False, vehicle=VEHICLE)
        settings = replace(monitor_zenoh_config(bridge_side), listen=(f"tcp/{LOOPBACK}:0",))
        source = cls.open(settings, PREFIX)
        assert isinstance(source, DemoSource)
        return source

    @property
    def state(self) -> str | None:
        """The bridge's output loop state (``running``, ``disarmed``, ...), if heard."""
        health = next((v.health for v in self.vehicles() if v.health is not None), None)
        return None if health is None else health.state


@dataclass
class EscRecord:
    """One ESC over the whole demo, for the summary."""

    motor: int
    node_id: int | None = None
    max_rpm: int | None = None
    frames: int | None = None
    online: bool = False
    """Online at the last look before the bridge was stopped."""


@dataclass
class Record:
    """Everything the summary needs, updated at every redraw."""

    escs: dict[int, EscRecord] = field(default_factory=dict)

    def update(self, vehicles: Sequence[VehicleState]) -> None:
        for vehicle in vehicles:
            for row in vehicle.escs:
                esc = row.telemetry
                entry = self.escs.setdefault(esc.motor, EscRecord(esc.motor))
                entry.node_id = esc.node_id
                if esc.rpm is not None:
                    rpm = abs(esc.rpm)
                    entry.max_rpm = rpm if entry.max_rpm is None else max(entry.max_rpm, rpm)
                if row.frames is not None:
                    entry.frames = row.frames
                entry.online = esc.online and not vehicle.stale


def all_online(vehicles: Sequence[VehicleState], count: int) -> bool:
    """The demo vehicle reports ``count`` ESCs, all online."""
    return any(
        not v.stale and len(v.escs) == count and all(e.telemetry.online for e in v.escs)
        for v in vehicles
    )


def summary_text(record: Record, count: int) -> str:
    """Per ESC: max rpm seen, frames, online at the end."""
    lines = [f"{'motor':>5}  {'node':>4}  {'max rpm':>7}  {'frames':>7}  online"]
    for motor in range(1, count + 1):
        esc = record.escs.get(motor, EscRecord(motor))
        lines.append(
            f"{motor:>5}  {_or_dash(esc.node_id):>4}  {_or_dash(esc.max_rpm):>7}  "
            f"{_or_dash(esc.frames):>7}  {'yes' if esc.online else 'no'}"
        )
    return "\n".join(lines)


def _or_dash(value: int | None) -> str:
    return "-" if value is None else str(value)
