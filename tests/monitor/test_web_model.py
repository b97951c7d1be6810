"""The web page's messages (bridge/monitor/web/model.py): what each card, row and health item
says and how it stands out, the chart points and their last minute."""

from __future__ import annotations

import json
from dataclasses import replace
from typing import Any

import pytest

from bridge.monitor.view import COLUMNS, EscRow, VehicleState
from bridge.monitor.web.model import (
    MINOR_COLUMNS,
    RECENT_S,
    PageModel,
    chart_point,
    health_items,
    vehicle_card,
)
from bridge.telemetry.payload import (
    CanRxHealth,
    EscTelemetryPayload,
    HealthPayload,
    InputHealth,
    LinkHealth,
    MotorTestHealth,
    OutputHealth,
    Temperatures,
)

HEADERS = [name for name, _ in COLUMNS]


def esc(motor: int, **fields: Any) -> EscRow:
    telemetry = EscTelemetryPayload(
        motor=motor,
        node_id=motor + 10,
        online=True,
        age_ms=5.0,
        rpm=1000 * motor,
        voltage_v=24.25,
        current_a=2.5 * motor,
        motor_current_a=None,
        throttle=0.5,
        temperature_c=Temperatures(mos=40.0 + motor, capacitor=30.0, motor=None, mcu=35.0),
        status=None,
        failure_flags=0,
        consumed_mah=12.0,
        command=None,
        command_unit="",
    )
    return EscRow(replace(telemetry, **fields), frames=100, errors=0)


def health(**fields: Any) -> HealthPayload:
    value = HealthPayload(
        state="running",
        failsafe=False,
        armed=True,
        motor_test=None,
        output=OutputHealth(
            rate_hz=399.6,
            configured_rate_hz=400,
            ticks=4000,
            frames_sent=4000,
            send_errors=0,
            overruns=0,
            tick_errors=0,
            bus_reopens=0,
            realtime=True,
        ),
        input=InputHealth(
            rate_hz=50.2,
            outputs=500,
            messages=510,
            bad_data=0,
            invalid=0,
            mixer_errors=0,
            age_ms=-3.0,
            out_of_order=0,
            unsigned=0,
            other_address=0,
        ),
        link=LinkHealth(relay_dropped=0, sent=20, send_dropped=0, reconnects=0),
        escs_online=4,
        can_rx=CanRxHealth(
            frames=1000,
            telemetry=900,
            malformed=0,
            read_errors=0,
            kernel_drops=None,
            unknown_esc_frames=0,
        ),
    )
    return replace(value, **fields)


def cell(row: dict[str, object], column: str) -> object:
    cells = row["cells"]
    assert isinstance(cells, list)
    return cells[HEADERS.index(column)]


def test_a_healthy_vehicle_is_ok_and_its_cells_are_the_tables() -> None:
    vehicle = VehicleState("alpha", (esc(1), esc(2)), age_s=0.04, health=health(), alive=True)
    card = vehicle_card(vehicle)
    assert card["name"] == "alpha"
    assert card["level"] == "ok"
    assert card["summary"] == "2/2 ESCs online"
    assert card["alerts"] == []
    assert [row["level"] for row in card["escs"]] == ["ok", "ok"]
    first = card["escs"][0]
    assert first["motor"] == 1
    assert cell(first, "rpm") == "1000"
    assert cell(first, "V") == "24.25"
    assert cell(first, "A") == "2.50"
    assert cell(first, "MOS°C") == "41"
    assert cell(first, "motor°C") == "-"  # not reported
    assert cell(first, "state") == "online"
    assert cell(first, "flags") == ""
    json.dumps(card, allow_nan=False)  # what the server sends


def test_failure_flags_and_offline_escs_stand_out() -> None:
    failing = esc(2, failure_flags=4 | 64)
    offline = esc(3, online=False, rpm=0)
    card = vehicle_card(VehicleState("alpha", (esc(1), failing, offline), age_s=0.0))
    assert card["level"] == "bad"
    assert card["summary"] == "2/3 ESCs online"
    assert card["alerts"] == ["motor 2: overtemp generic", "motor 3: offline"]
    assert [row["level"] for row in card["escs"]] == ["ok", "failure", "offline"]
    assert cell(card["escs"][1], "flags") == "overtemp generic"
    # An offline ESC whose last word was a failure: both are said, the failure shows.
    both = vehicle_card(VehicleState("b", (esc(1, online=False, failure_flags=1),), age_s=0.0))
    assert both["alerts"] == ["motor 1: overcurrent", "motor 1: offline"]
    assert both["escs"][0]["level"] == "failure"


def test_a_stale_vehicle_says_why_and_for_how_long() -> None:
    quiet = VehicleState("alpha", (esc(1, failure_flags=4),), stale=True, age_s=12.34, alive=True)
    card = vehicle_card(quiet)
    assert card["level"] == "stale"
    assert card["summary"] == "STALE: no data for 12.3 s"
    assert card["age_s"] == 12.3
    assert card["alerts"] == []  # its last values are history, not alarms
    assert card["escs"][0]["level"] == "stale"
    assert cell(card["escs"][0], "state") == "stale"
    assert card["point"] is None
    gone = vehicle_card(replace(quiet, alive=False, age_s=0.5))
    assert gone["summary"] == "STALE: bridge gone for 0.5 s"
    never = vehicle_card(VehicleState("c", (), stale=True, age_s=None, alive=False))
    assert never["summary"] == "STALE: bridge gone"


def test_a_bridge_known_only_by_its_token_is_waiting() -> None:
    card = vehicle_card(VehicleState("alpha", (), alive=True))
    assert card["level"] == "warn"
    assert card["summary"] == "waiting for ESC telemetry"
    assert card["escs"] == [] and card["point"] == []


def test_health_items_say_state_arming_link_and_bus() -> None:
    items = {item["name"]: item for item in health_items(health())}
    assert list(items) == ["bridge", "autopilot", "link", "bus"]
    assert items["bridge"] == {"name": "bridge", "text": "running, 400/400 Hz out", "level": "ok"}
    # A negative age (the autopilot's clock estimated a little ahead) shows as 0.
    assert items["autopilot"]["text"] == "armed, 50 Hz, newest 0 ms old"
    assert items["link"]["text"] == "0 frames dropped, 0 reconnects"
    assert items["bus"]["text"] == "1000 frames in, 0 errors"
    assert {item["level"] for item in items.values()} == {"ok"}


def test_every_refused_frame_counts_on_the_autopilots_item() -> None:
    # Each counter of frames the bridge would not act on, those from another UDP address too.
    refused = replace(
        health().input,
        bad_data=1,
        invalid=2,
        mixer_errors=3,
        out_of_order=4,
        unsigned=5,
        other_address=6,
    )
    item = health_items(health(input=refused))[1]
    assert item["text"] == "armed, 50 Hz, newest 0 ms old, 21 refused"


@pytest.mark.parametrize(
    ("state", "text", "level"),
    [
        ("disarmed", "disarmed", "ok"),
        ("no_input", "no input, safe values", "warn"),
        ("heartbeat_lost", "heartbeat lost, safe values", "bad"),
        ("stale", "stale, safe values", "bad"),
        ("stopping", "stopping, safe values", "warn"),
    ],
)
def test_the_loops_state_sets_the_bridges_level(state: str, text: str, level: str) -> None:
    item = health_items(health(state=state, failsafe=state != "running", armed=False))[0]
    assert item["text"] == f"{text}, 400/400 Hz out"
    assert item["level"] == level


def test_a_motor_test_is_named() -> None:
    test = MotorTestHealth(motor=2, motors=(2,), throttle=0.15, remaining_s=3.2)
    item = health_items(health(state="motor_test", motor_test=test))[0]
    assert item["text"] == "motor test (motor 2, 15 %, 3 s left), 400/400 Hz out"
    assert item["level"] == "warn"


def test_a_counter_warns_while_it_grows_and_not_for_ever() -> None:
    model = PageModel("esc-bridge/*")
    errors = replace(health().can_rx, malformed=3)

    def bus_level(h: HealthPayload, t_s: float) -> str:
        card = model.snapshot([VehicleState("alpha", (esc(1),), age_s=0.0, health=h)], t_s)
        items = {item["name"]: item for item in card["vehicles"][0]["health"]}
        return str(items["bus"]["level"])

    # Errors counted before the monitor started are old news.
    assert bus_level(health(can_rx=errors), 0.0) == "ok"
    grown = replace(errors, malformed=5)
    assert bus_level(health(can_rx=grown), 1.0) == "warn"
    assert bus_level(health(can_rx=grown), 1.0 + RECENT_S - 0.1) == "warn"
    assert bus_level(health(can_rx=grown), 1.0 + RECENT_S + 0.1) == "ok"
    # A restarted bridge counts from 0 again: no warning for that.
    assert bus_level(health(), 20.0) == "ok"
    # Every counter of an item is followed, not only the first that grew.
    link = health().link
    model_link = PageModel("x")
    for t_s, dropped, reconnects, level in [
        (0.0, 0, 0, "ok"),
        (1.0, 1, 0, "warn"),
        (2.0, 1, 1, "warn"),
        (11.5, 1, 1, "warn"),  # the reconnect at 2.0 is recent
        (12.5, 1, 1, "ok"),
    ]:
        h = health(link=replace(link, relay_dropped=dropped, reconnects=reconnects))
        card = model_link.snapshot([VehicleState("a", (esc(1),), age_s=0.0, health=h)], t_s)
        assert card["vehicles"][0]["health"][2]["level"] == level, t_s


def test_chart_points_are_rpm_amps_and_the_hottest_temperature() -> None:
    vehicle = VehicleState(
        "alpha",
        (
            esc(1),
            esc(2, online=False),
            esc(
                3,
                current_a=None,
                temperature_c=Temperatures(mos=None, capacitor=None, motor=None, mcu=None),
            ),
        ),
        age_s=0.0,
    )
    assert chart_point(vehicle) == [
        [1000, 2.5, 41.0],
        [None, None, None],  # offline: a gap
        [3000, None, None],
    ]
    assert chart_point(replace(vehicle, stale=True)) is None


def test_the_history_keeps_the_last_minute_by_vehicle_as_columns() -> None:
    model = PageModel("esc-bridge/*", window_s=60.0)
    alpha = VehicleState("alpha", (esc(1), esc(2)), age_s=0.0)
    beta = VehicleState("beta", (esc(1),), age_s=0.0)
    for tick in range(100):
        t_s = tick * 1.0
        stale_beta = replace(beta, stale=True) if tick >= 50 else beta
        model.snapshot([replace(alpha, escs=(esc(1, rpm=tick), esc(2))), stale_beta], t_s)
    hello = model.hello(0.1)
    history = hello["history"]
    assert history["alpha"]["t"] == [float(t) for t in range(39, 100)]  # the last 60 s
    assert history["alpha"]["rpm"][0] == list(range(39, 100))
    assert history["alpha"]["rpm"][1] == [2000] * 61
    assert history["alpha"]["current_a"][1] == [5.0] * 61
    assert history["beta"]["t"] == [float(t) for t in range(39, 50)]  # nothing once stale
    assert hello["series"] == ["rpm", "current_a", "temp_c"]
    assert [c["name"] for c in hello["columns"]] == HEADERS
    assert {c["name"] for c in hello["columns"] if c["minor"]} == MINOR_COLUMNS
    assert hello["window_s"] == 60.0 and hello["period_s"] == 0.1
    json.dumps(hello, allow_nan=False)
