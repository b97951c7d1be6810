"""Sample records of every Zenoh key, with each field set (none left at its default), for the
payload and publisher tests."""

from __future__ import annotations

from dataclasses import replace

from bridge.telemetry.payload import (
    ActuatorsInputPayload,
    ActuatorsOutputPayload,
    CanBusHealth,
    CanRxHealth,
    CommandOut,
    EscInfoPayload,
    EscStatusPayload,
    EscTelemetryPayload,
    HealthPayload,
    InputHealth,
    LinkHealth,
    MotorTestHealth,
    OutputHealth,
    Payload,
    Temperatures,
    ZenohHealth,
)

TELEMETRY = EscTelemetryPayload(
    time_unix_ms=1_795_330_000_123,
    motor=1,
    node_id=5,
    online=True,
    age_ms=12.3,
    rpm=-1234,
    voltage_v=24.5,
    current_a=3.25,
    motor_current_a=None,
    throttle=0.5,
    temperature_c=Temperatures(mos=42.0, capacitor=30, motor=None, mcu=45.5),
    status=3,
    failure_flags=4,
    consumed_mah=1.234,
    command=1000,
    command_unit="throttle",
)
INFO = EscInfoPayload(
    time_unix_ms=1_795_330_000_124,
    motor=2,
    node_id=12,
    online=False,
    frames=17,
    errors=1,
    failure_flags=0,
    counters={"power_on_count": 17, "start_count": 230},
)
STATUS = EscStatusPayload(
    time_unix_ms=1_795_330_000_125,
    count=2,
    online=1,
    escs=(
        replace(TELEMETRY, time_unix_ms=None),  # inside esc/status: no time of its own
        EscTelemetryPayload(
            motor=2,
            node_id=12,
            online=False,
            age_ms=None,
            rpm=None,
            voltage_v=None,
            current_a=None,
            motor_current_a=None,
            throttle=None,
            temperature_c=Temperatures(mos=None, capacitor=None, motor=None, mcu=None),
            status=None,
            failure_flags=0,
            consumed_mah=0.0,
            command=None,
            command_unit="",
        ),
    ),
)
HEALTH = HealthPayload(
    time_unix_ms=1_795_330_000_126,
    state="motor_test",
    failsafe=False,
    armed=False,
    motor_test=MotorTestHealth(motor=None, motors=(1, 2, 3, 4), throttle=0.1, remaining_s=2.5),
    output=OutputHealth(
        rate_hz=399.9,
        configured_rate_hz=400,
        ticks=4000,
        frames_sent=4000,
        send_errors=1,
        overruns=2,
        tick_errors=0,
        bus_reopens=0,
        realtime=True,
    ),
    input=InputHealth(
        rate_hz=50.0,
        outputs=500,
        messages=510,
        bad_data=0,
        invalid=1,
        mixer_errors=0,
        age_ms=3.2,
        out_of_order=0,
        unsigned=0,
        other_address=0,
    ),
    link=LinkHealth(relay_dropped=0, sent=20, send_dropped=0, reconnects=1),
    escs_online=4,
    can_rx=CanRxHealth(
        frames=1000,
        telemetry=900,
        malformed=2,
        read_errors=0,
        kernel_drops=None,
        unknown_esc_frames=3,
    ),
    can_bus=CanBusHealth(
        tx_state="stuck",
        ticks_held=40,
        tx_probes=0,
        stuck=1,
        down=0,
        gone=0,
        controller_state="error_passive",
        error_frames=3,
        error_warning=1,
        error_passive=1,
        bus_off=0,
        restarts=0,
        receive_overflows=0,
        reader_reopens=0,
    ),
    zenoh=ZenohHealth(session_up=True, published=123, dropped=4),
)
ACTUATORS_INPUT = ActuatorsInputPayload(
    time_unix_ms=123,
    source="SERVO_OUTPUT_RAW",
    armed=True,
    age_ms=4.5,
    channels={"ch1": 1500, "ch2": 1510.0},
    mixed=(0.25, 0.5),
)
ACTUATORS_OUTPUT = ActuatorsOutputPayload(
    time_unix_ms=1_795_330_000_127,
    state="running",
    commands=(
        CommandOut(motor=1, node_id=5, value=1000, unit="throttle"),
        CommandOut(motor=2, node_id=12, value=None, unit=""),
    ),
)
EVERY_KEY: tuple[Payload, ...] = (
    TELEMETRY,
    INFO,
    STATUS,
    HEALTH,
    ACTUATORS_INPUT,
    ACTUATORS_OUTPUT,
)
"""One record per key, in :data:`bridge.telemetry.payload.RECORDS` order."""
