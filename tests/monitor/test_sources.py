"""The monitor's Zenoh source with a bridge's whole presence: its liveliness token (a vehicle known
before its first ESC data, and gone the moment the token goes) and its ``bridge/health``. Real
Zenoh sessions on loopback: this test plays the bridge."""

from __future__ import annotations

import json
import socket
import threading
import time
from collections.abc import Callable

import zenoh
from conftest import free_port

from bridge.config import ZenohConfig
from bridge.monitor import STALE_AFTER_S, VehicleState, ZenohSource, monitor_zenoh_config
from bridge.telemetry.payload import (
    CanRxHealth,
    HealthPayload,
    InputHealth,
    LinkHealth,
    OutputHealth,
)

HEALTH = HealthPayload(
    time_unix_ms=1,
    state="running",
    failsafe=False,
    armed=True,
    motor_test=None,
    output=OutputHealth(
        rate_hz=400.0,
        configured_rate_hz=400,
        ticks=1,
        frames_sent=1,
        send_errors=0,
        overruns=0,
        tick_errors=0,
        bus_reopens=0,
        realtime=False,
    ),
    input=InputHealth(
        rate_hz=50.0,
        outputs=1,
        messages=1,
        bad_data=0,
        invalid=0,
        mixer_errors=0,
        age_ms=3.0,
        out_of_order=0,
        unsigned=0,
        other_address=0,
    ),
    link=LinkHealth(relay_dropped=0, sent=0, send_dropped=0, reconnects=0),
    escs_online=1,
    can_rx=CanRxHealth(
        frames=1, telemetry=1, malformed=0, read_errors=0, kernel_drops=None, unknown_esc_frames=0
    ),
)
STATUS = json.dumps(
    {
        "time_unix_ms": 1,
        "count": 1,
        "online": 1,
        "escs": [
            {
                "motor": 1,
                "node_id": 1,
                "online": True,
                "age_ms": 4.0,
                "rpm": 1500,
                "voltage_v": 24.0,
                "current_a": 1.0,
                "motor_current_a": None,
                "throttle": 0.2,
                "temperature_c": {"mos": 30.0, "capacitor": None, "motor": None, "mcu": None},
                "status": None,
                "failure_flags": 0,
                "consumed_mah": 1.0,
                "command": None,
                "command_unit": "",
            }
        ],
    }
).encode()


def bridge_session(endpoint: str) -> zenoh.Session:
    config = zenoh.Config()
    config.insert_json5("listen/endpoints", json.dumps([endpoint]))
    config.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(config)


def source_of(endpoint: str) -> ZenohSource:
    bridge_side = ZenohConfig(listen=(endpoint,), multicast_scouting=False)
    return ZenohSource.open(monitor_zenoh_config(bridge_side))


def wait_for(
    source: ZenohSource, check: Callable[[list[VehicleState]], bool], timeout_s: float = 15.0
) -> list[VehicleState]:
    deadline = time.monotonic() + timeout_s
    vehicles: list[VehicleState] = []
    while time.monotonic() < deadline:
        vehicles = source.vehicles()
        if check(vehicles):
            return vehicles
        time.sleep(0.02)
    raise AssertionError(f"not within {timeout_s} s: {vehicles}")


class Statuses:
    """Puts ``esc/status`` and ``bridge/health`` ten times a second while :attr:`on` is set, in
    a thread (as a bridge publishes: a sample put once may come before the monitor's
    subscription reached this session)."""

    def __init__(self, session: zenoh.Session) -> None:
        self.session = session
        self.on = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="statuses", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.1):
            if self.on.is_set():
                self.session.put("esc-bridge/alpha/esc/status", STATUS)
                self.session.put("esc-bridge/alpha/bridge/health", HEALTH.encode())

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)


def test_a_bridge_is_known_by_its_token_and_gone_with_it() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"
    with bridge_session(endpoint) as bridge:
        token = bridge.liveliness().declare_token("esc-bridge/alpha/alive")
        statuses = Statuses(bridge)
        try:
            with source_of(endpoint) as source:
                # The token was there before the monitor: it comes with the subscription.
                (alpha,) = wait_for(source, lambda v: len(v) == 1)
                assert (alpha.name, alpha.alive, alpha.stale, alpha.escs, alpha.age_s) == (
                    "alpha",
                    True,
                    False,
                    (),
                    None,
                )
                statuses.on.set()
                (alpha,) = wait_for(source, lambda v: bool(v[0].escs) and v[0].health is not None)
                assert alpha.health == HEALTH
                assert alpha.escs[0].telemetry.rpm == 1500
                assert not alpha.stale
                # The bridge stops: its data and its token go. Stale at once, not when its
                # data is a second old.
                statuses.on.clear()
                token.undeclare()
                (alpha,) = wait_for(source, lambda v: v[0].stale)
                assert alpha.alive is False
                assert alpha.age_s is not None and alpha.age_s < STALE_AFTER_S
                assert alpha.health == HEALTH  # its last word stays
                # Data that flows again outweighs a token lost on the way...
                statuses.on.set()
                (alpha,) = wait_for(source, lambda v: not v[0].stale)
                assert alpha.alive is False
                # ... and a token that comes back is the bridge back.
                token = bridge.liveliness().declare_token("esc-bridge/alpha/alive")
                wait_for(source, lambda v: v[0].alive is True and not v[0].stale)
        finally:
            statuses.close()


def test_a_health_that_is_not_ours_is_counted_and_dropped() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"
    with bridge_session(endpoint) as bridge, source_of(endpoint) as source:
        deadline = time.monotonic() + 15
        while source.bad_messages == 0 and time.monotonic() < deadline:
            bridge.put("esc-bridge/alpha/bridge/health", b'{"state": 3}')
            time.sleep(0.05)
        assert source.bad_messages >= 1
        bridge.put("esc-bridge/alpha/esc/status", STATUS)
        (alpha,) = wait_for(source, lambda v: len(v) == 1)
        assert alpha.health is None
