"""The bridge's configuration: TOML sections validated once into frozen, typed dataclasses.

Precedence: defaults < file < command line. The raw values are merged first and validated once,
so a mistake is reported the same way wherever it came from: the file (or "command line"), the
``[section] key``, what was expected and what was found. Unknown sections and keys are errors,
because a misspelt safety setting that is silently ignored is worse than a refused start.

Every key is documented in ``config/README.md``; a test keeps that page and this module in step.
The keys' validators are in :mod:`bridge.config_checks`, reading a file and laying the command
line over it in :mod:`bridge.config_file` (the subcommands' one merge: ``bridge.cli._common``).
The ESC family on the bus checks its own ``[escs]`` keys (:meth:`BridgeConfig.esc_setup`).

A little over 600 lines, one job: most of it is the table of every section's keys, with their
defaults and documentation, which reads best whole.
"""

from __future__ import annotations

import socket
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from typing import TYPE_CHECKING, Any, Literal

from bridge.bitrate import parse_bitrate
from bridge.config_checks import (
    bitrate_value,
    boolean,
    check,
    choice,
    float_range,
    int_list,
    int_range,
    is_number,
    key,
    optional,
    ordered_pair,
    range_pair,
    shown,
    string,
    string_list,
)
from bridge.errors import ConfigError
from bridge.escs import registry
from bridge.escs.family import EscFamily, EscSetup

if TYPE_CHECKING:
    from bridge.mixing.definition import MixerDefinition

MavlinkSource = Literal[
    "servo_output_raw", "actuator_output_status", "hil_actuator_controls", "actuator_control_target"
]
Latency = Literal["fixed", "immediate"]
LoopMode = Literal["auto", "process", "thread"]

# The system ID ground stations use unless told otherwise (QGroundControl, Mission Planner).
GCS_SYSTEM_ID = 255


def _options(v: Any) -> str | None:
    ok = isinstance(v, dict) and all(isinstance(k, str) for k in v)
    return None if ok else "a table of interface options"


def _is_hex32(v: Any) -> bool:
    if not isinstance(v, str) or len(v) != 64:
        return False
    try:
        bytes.fromhex(v)
    except ValueError:
        return False
    return True


def _is_axis_map(v: Any) -> bool:
    return isinstance(v, dict) and all(
        k in ("roll", "pitch", "yaw", "thrust")
        and isinstance(c, int)
        and not isinstance(c, bool)
        and 1 <= c <= 32
        for k, c in v.items()
    )


def _pole_pairs(v: Any) -> str | None:
    def ok(x: Any) -> bool:
        return isinstance(x, int) and not isinstance(x, bool) and 1 <= x <= 100

    if ok(v) or (isinstance(v, list) and v and all(ok(x) for x in v)):
        return None
    return "an integer 1..100, or a list of them (one per motor)"


def _key_segment(v: Any) -> str | None:
    # A Zenoh key segment: no separators or wildcards, so it names exactly one vehicle.
    ok = isinstance(v, str) and v != "" and all(c.isalnum() or c in "-_." for c in v)
    return None if ok else "a name of letters, digits, '-', '_' or '.'"


def _key_prefix(v: Any) -> str | None:
    ok = (
        isinstance(v, str)
        and v != ""
        and not v.startswith("/")
        and not v.endswith("/")
        and "//" not in v
        and not any(c in v for c in "*$?#")
    )
    return None if ok else "a Zenoh key expression without wildcards or leading/trailing '/'"


MESSAGE_FAMILIES = ("esc_status", "esc_info", "esc_telemetry")
"""The ESC telemetry families a MAVLink connection can carry (``bridge.mavlink.esc_messages``)."""
MAX_MESSAGE_HZ = 100.0
_MESSAGE_SET = "a table of esc_status, esc_info, esc_telemetry = rate in Hz 0..100 (0 = off)"


def _message_set(v: Any) -> str | None:
    """A connection's message set: ``{family = Hz}``; a family not listed is off."""
    if not isinstance(v, dict):
        return _MESSAGE_SET
    for family, rate in v.items():
        if family not in MESSAGE_FAMILIES:
            return f"{_MESSAGE_SET}; {family!r} is no message family"
        if not (is_number(rate) and 0 <= rate <= MAX_MESSAGE_HZ):
            return f"{_MESSAGE_SET}; {family} = {shown(rate)} is no rate 0..100"
    return None


def _output_message_sets(v: Any) -> str | None:
    what = 'a table of "output URL" = { esc_status = Hz, esc_info = Hz, esc_telemetry = Hz }'
    if not isinstance(v, dict):
        return what
    for url, rates in v.items():
        problem = _message_set(rates)
        if problem is not None:
            return f"{what}; for {url!r}: {problem}"
    return None


@dataclass(frozen=True)
class MavlinkConfig:
    url: str = key("udpin:0.0.0.0:14550", string, "pymavlink connection string of the autopilot")
    source: MavlinkSource = key(
        "servo_output_raw",
        choice(
            "servo_output_raw",
            "actuator_output_status",
            "hil_actuator_controls",
            "actuator_control_target",
        ),
        "which message carries the motor outputs",
    )
    autopilot_system_id: int = key(1, int_range(1, 255), "system ID whose outputs are obeyed")
    autopilot_component_id: int = key(
        1,
        int_range(1, 255),
        "component ID whose outputs are obeyed (1 = MAV_COMP_ID_AUTOPILOT1)",
    )
    component_id: int = key(
        191, int_range(1, 255), "the bridge's own component ID (191 = ONBOARD_COMPUTER)"
    )
    command_senders: tuple[int, ...] | None = key(
        None,
        optional(int_list(1, 255, non_empty=True)),
        "system IDs whose commands that move motors (MAV_CMD_DO_MOTOR_TEST) are obeyed "
        "(default: 255, a ground station, and the autopilot's system ID)",
    )
    stream_rate_hz: float = key(
        200.0,
        float_range(0, 1000),
        "output stream rate asked of the autopilot; 0 = do not ask",
    )
    autopilot_heartbeat_hz: float = key(
        20.0,
        float_range(0, 100),
        "HEARTBEAT rate asked of the autopilot, so an arming change is heard within 1/rate "
        "instead of up to a second; 0 = do not ask",
    )
    signing_key: str | None = key(
        None,
        optional(check(_is_hex32, "64 hex digits (a 32-byte key)")),
        "MAVLink 2 signing key; when set, unsigned or badly signed messages are rejected",
    )
    heartbeat_hz: float = key(1.0, float_range(0.1, 10), "rate of the bridge's own HEARTBEAT")
    outputs: tuple[str, ...] = key(
        (),
        string_list,
        "extra MAVLink connections (e.g. udpout:192.168.1.10:14550 to a GCS) that get the "
        "bridge's HEARTBEAT, STATUSTEXT and ESC telemetry",
    )
    esc_status_hz: float = key(
        10.0, float_range(0, 100), "ESC_STATUS rate on each output (ground station); 0 = off"
    )
    esc_info_hz: float = key(
        1.0, float_range(0, 100), "ESC_INFO rate on each output (ground station); 0 = off"
    )
    esc_telemetry_hz: float = key(
        10.0,
        float_range(0, 100),
        "ArduPilot ESC_TELEMETRY_x_TO_y rate on each output (ground station); 0 = off",
    )
    autopilot_messages: Mapping[str, float] | None = key(
        None,
        optional(_message_set),
        "ESC telemetry on the autopilot's link, e.g. { esc_telemetry = 2 } (Hz; a family not "
        "listed is off); default: chosen from the autopilot's HEARTBEAT (ArduPilot "
        "ESC_TELEMETRY_x_TO_y 2 Hz, PX4 ESC_STATUS 2 Hz and ESC_INFO 1 Hz, another stack all "
        "three, nothing before its first HEARTBEAT)",
    )
    output_messages: Mapping[str, Mapping[str, float]] | None = key(
        None,
        optional(_output_message_sets),
        "ESC telemetry on particular outputs, by URL as in outputs, e.g. "
        '{ "udpout:10.0.0.2:14550" = { esc_status = 5 } } (Hz; a family not listed is off); '
        "outputs not named get esc_status_hz, esc_info_hz and esc_telemetry_hz",
    )

    def output_rates(self, url: str) -> dict[str, float]:
        """The rates (Hz, 0 = off) of every family on the output ``url``."""
        configured = (self.output_messages or {}).get(url)
        if configured is not None:
            return {family: float(configured.get(family, 0.0)) for family in MESSAGE_FAMILIES}
        return {
            "esc_status": self.esc_status_hz,
            "esc_info": self.esc_info_hz,
            "esc_telemetry": self.esc_telemetry_hz,
        }


@dataclass(frozen=True)
class MixerConfig:
    name: str = key(
        "passthrough-4", string, "bundled mixer name (see mixers/) or path to a mixer .toml"
    )
    input_range: tuple[float, float] | None = key(
        None,
        optional(range_pair),
        "input range of every channel source, overriding the mixer's (default: the mixer's, "
        "PWM [1000, 2000] µs; [0, 1] for hil_actuator_controls)",
    )
    valid_range: tuple[float, float] | None = key(
        None,
        optional(ordered_pair),
        "channel inputs outside this are invalid: safe values, FAILSAFE invalid input (default "
        "[800, 2200] µs for the PWM sources servo_output_raw and actuator_output_status; "
        "[-1.5, 1.5] for the normalized sources hil_actuator_controls and "
        "actuator_control_target); it must contain the input range",
    )
    axis_channels: Mapping[str, int] | None = key(
        None,
        optional(check(_is_axis_map, "a table of roll, pitch, yaw, thrust = channel 1..32")),
        "geometry mixers: take roll, pitch, yaw and thrust from these channels, scaled from "
        "the channel input range",
    )


@dataclass(frozen=True)
class OutputConfig:
    protocol: str = key(registry.DEFAULT, choice(*registry.names()), "ESC protocol on the bus")
    rate_hz: int | None = key(
        None,
        optional(int_range(1, 1000)),
        "command rate per ESC (default: the ESC protocol's own, see config/README.md)",
    )
    latency: Latency = key(
        "fixed",
        choice("fixed", "immediate"),
        "fixed: send at the rate; immediate: send a fresh input at once and re-phase the tick",
    )
    require_armed: bool = key(True, boolean, "send safe values while disarmed (false: bench use)")
    input_timeout_ms: int = key(
        100,
        int_range(20, 1000),
        "an input produced (by the autopilot's clock) longer ago than this is stale: safe values",
    )
    arming_timeout_ms: int = key(
        3000,
        int_range(500, 60_000),
        "the autopilot's arming state (its HEARTBEAT) older than this counts as disarmed: "
        "safe values",
    )
    shutdown_flush_ms: int = key(
        200, int_range(0, 5000), "safe values sent this long on a stop signal or a death"
    )
    motor_test: bool = key(
        False,
        boolean,
        "obey MAV_CMD_DO_MOTOR_TEST from the allowed senders while disarmed; off: refused",
    )
    motor_test_max_s: float = key(
        10.0,
        float_range(0.1, 600),
        "longest motor test per motor (MAV_CMD_DO_MOTOR_TEST timeout), s; longer ones are cut",
    )
    loop: LoopMode = key(
        "auto",
        choice("auto", "process", "thread"),
        "where the control loop (autopilot link, mixer, CAN transmit) runs: its own process (free "
        "of the GIL), a thread, or auto "
        "(process for interfaces several processes can open: socketcan, udp_multicast)",
    )
    realtime_priority: int = key(
        50,
        int_range(0, 99),
        "SCHED_FIFO priority of the output loop when permitted; 0 = off",
    )
    bus_load_ceiling: float = key(
        0.70,
        float_range(0.05, 1.0),
        "refuse a config whose worst-case bus load exceeds this",
    )


@dataclass(frozen=True)
class CanConfig:
    interface: str = key("socketcan", string, "python-can interface name")
    channel: str = key("can0", string, "python-can channel (socketcan: the netdev, e.g. can0)")
    bitrate: int | None = key(
        None,
        optional(bitrate_value),
        'bus bit rate, bit/s: 500000, "500k" or "1M" (default: the ESC family\'s factory rate); '
        "checked against a SocketCAN interface's at start, used for the bus-load check, set by "
        "interfaces that can",
        convert=lambda v: None if v is None else parse_bitrate(v),
    )
    options: Mapping[str, Any] | None = key(
        None,
        optional(_options),
        "extra python-can arguments for the interface (e.g. port = 43113)",
    )


@dataclass(frozen=True)
class EscsConfig:
    ids: tuple[int, ...] = key(
        (),
        int_list(1, 125),
        "ID of the ESC on each mixer output, in output order (its family's node or ESC ID); "
        "default 1..N",
    )
    families: Mapping[str, Any] = field(default_factory=lambda: _family_keys({}))
    """Each ESC family's keys (its ``keys`` dataclass), by family name: the ``[escs]`` keys
    other than ``ids`` belong to the families (bridge/escs/<family>/keys.py)."""

    def keys(self, family: str) -> Any:
        """The keys of ``family`` (an instance of its ``keys`` dataclass)."""
        return self.families[family]


def _family_keys(values: Mapping[str, Any]) -> dict[str, Any]:
    """Every family's keys from ``values`` (checked already; other families' keys ignored)."""
    out = {}
    for family in registry.families():
        own = {f.name for f in fields(family.keys)}
        out[family.name] = family.keys(**{k: v for k, v in values.items() if k in own})
    return out


def _escs_fields() -> list[Any]:
    """The ``[escs]`` keys: ``ids``, then each family's."""
    common = [f for f in fields(EscsConfig) if f.name != "families"]
    return common + [f for family in registry.families() for f in fields(family.keys)]


@dataclass(frozen=True)
class TelemetryConfig:
    timeout_ms: int = key(
        500, int_range(20, 10_000), "an ESC is offline when no frame came for this long"
    )
    pole_pairs: int | tuple[int, ...] = key(
        7, _pole_pairs, "motor pole pairs (erpm / pole pairs = rpm): one, or one per motor"
    )
    max_temp_c: float | None = key(
        100.0,
        optional(float_range(0, 250)),
        "any reported temperature above this raises OVER_TEMPERATURE",
    )
    max_current_a: float | None = key(
        None,
        optional(float_range(0, 1000)),
        "|current| above this raises OVER_CURRENT",
    )
    max_rpm: int | None = key(
        None, optional(int_range(1, 1_000_000)), "|rpm| above this raises OVER_RPM"
    )
    error_burst: int = key(
        5, int_range(1, 10_000), "this many CRC/format errors within 1 s raise GENERIC"
    )
    learn_ids: bool = key(
        False,
        boolean,
        "ask the ESCs for their node IDs at start (for ESC families that can ask) and map them "
        "to motors by throttle channel, instead of trusting [escs] ids",
    )


@dataclass(frozen=True)
class ZenohConfig:
    enabled: bool = key(True, boolean, "publish telemetry over Zenoh")
    mode: Literal["peer", "client", "router"] = key(
        "peer", choice("peer", "client", "router"), "Zenoh session mode"
    )
    connect: tuple[str, ...] = key(
        (),
        string_list,
        "endpoints to connect to, e.g. tcp/192.168.1.2:7447 (a zenohd router)",
    )
    listen: tuple[str, ...] = key((), string_list, "endpoints to listen on, e.g. tcp/0.0.0.0:7447")
    multicast_scouting: bool = key(
        True, boolean, "find peers and routers on the LAN by multicast (Zenoh's default)"
    )
    vehicle: str | None = key(
        None,
        optional(_key_segment),
        "the vehicle's name in the keys (default: the host name)",
    )
    prefix: str | None = key(
        None, optional(_key_prefix), "key prefix (default esc-bridge/<vehicle>)"
    )
    telemetry_hz: float = key(10.0, float_range(0.1, 200), "cap on each esc/<n>/telemetry")
    status_hz: float = key(10.0, float_range(0.1, 200), "cap on esc/status")
    info_hz: float = key(1.0, float_range(0.1, 200), "cap on each esc/<n>/info")
    health_hz: float = key(2.0, float_range(0.1, 200), "cap on bridge/health")
    actuators_hz: float = key(
        10.0, float_range(0.1, 200), "cap on actuators/input and actuators/output"
    )

    def key_prefix(self) -> str:
        """The prefix every key is published under: ``prefix``, or esc-bridge/<vehicle>."""
        return self.prefix or f"esc-bridge/{self.vehicle or default_vehicle_name()}"


def default_vehicle_name() -> str:
    """The host name, made a valid key segment (other characters become '_')."""
    return (
        "".join(c if c.isalnum() or c in "-_." else "_" for c in socket.gethostname()) or "vehicle"
    )


@dataclass(frozen=True)
class BridgeConfig:
    """The whole validated configuration."""

    source: str = "defaults"  # where it came from, for messages
    mavlink: MavlinkConfig = field(default_factory=MavlinkConfig)
    mixer: MixerConfig = field(default_factory=MixerConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    can: CanConfig = field(default_factory=CanConfig)
    escs: EscsConfig = field(default_factory=EscsConfig)
    telemetry: TelemetryConfig = field(default_factory=TelemetryConfig)
    zenoh: ZenohConfig = field(default_factory=ZenohConfig)

    @property
    def rate_hz(self) -> int:
        return self.output.rate_hz or registry.family(self.output.protocol).default_rate_hz

    @property
    def bitrate(self) -> int:
        return self.can.bitrate or registry.family(self.output.protocol).default_bitrate

    @property
    def family(self) -> EscFamily:
        return registry.family(self.output.protocol)

    @property
    def esc_setup(self) -> EscSetup[Any]:
        """The family's keys and the ESC IDs, as its check (passed already) returns them."""
        return _checked_setup(self)

    @property
    def command_sender_ids(self) -> frozenset[int]:
        """The system IDs whose motor-moving commands are obeyed: ``[mavlink] command_senders``,
        or 255 (a ground station's usual ID) and the autopilot's system ID."""
        senders = self.mavlink.command_senders
        if senders is not None:
            return frozenset(senders)
        return frozenset({GCS_SYSTEM_ID, self.mavlink.autopilot_system_id})


SECTIONS: dict[str, type[Any]] = {
    "mavlink": MavlinkConfig,
    "mixer": MixerConfig,
    "output": OutputConfig,
    "can": CanConfig,
    "escs": EscsConfig,
    "telemetry": TelemetryConfig,
    "zenoh": ZenohConfig,
}


def build_config(raw: Mapping[str, Any], source: str) -> BridgeConfig:
    """Validate raw tables into a :class:`BridgeConfig`.

    Raises:
        ConfigError: naming ``source``, the section and key, what was expected and what was got.
    """
    sections: dict[str, Any] = {}
    for name, table in raw.items():
        if name not in SECTIONS:
            raise ConfigError(
                f"{source}: unknown section [{name}]; expected one of "
                + ", ".join(f"[{s}]" for s in SECTIONS)
            )
        if not isinstance(table, dict):
            raise ConfigError(f"{source}: [{name}] must be a table, got {shown(table)}")
        sections[name] = _build_section(SECTIONS[name], name, table, source)
    config = BridgeConfig(source=source, **sections)
    _check_cross_section(config)
    return config


def _section_fields(cls: type[Any]) -> list[Any]:
    return _escs_fields() if cls is EscsConfig else list(fields(cls))


def _build_section(cls: type[Any], name: str, table: Mapping[str, Any], source: str) -> Any:
    known = {f.name: f for f in _section_fields(cls)}
    values: dict[str, Any] = {}
    for k, value in table.items():
        if k not in known:
            raise ConfigError(
                f"{source}: [{name}] unknown key {k!r}; expected one of " + ", ".join(known)
            )
        problem = known[k].metadata["check"](value)
        if problem is not None:
            raise ConfigError(f"{source}: [{name}] {k}: expected {problem}, got {shown(value)}")
        convert = known[k].metadata.get("convert")
        if convert is not None:
            value = convert(value)
        if isinstance(value, list):
            value = tuple(value)
        values[k] = value
    if cls is EscsConfig:
        own = {f.name for f in fields(EscsConfig)}
        common = {k: v for k, v in values.items() if k in own}
        return EscsConfig(**common, families=_family_keys(values))
    return cls(**values)


def _check_cross_section(config: BridgeConfig) -> None:
    source = config.source
    for url in config.mavlink.output_messages or {}:
        if url not in config.mavlink.outputs:
            listed = ", ".join(repr(u) for u in config.mavlink.outputs) or "none"
            raise ConfigError(
                f"{source}: [mavlink] output_messages: {url!r} is not one of [mavlink] outputs "
                f"({listed}); expected an output URL written exactly as in outputs"
            )
    if ids := config.escs.ids:
        _per_esc_lists(config, len(ids), f"ids has {len(ids)}", "ESC")
    _checked_setup(config)


def _per_esc_lists(config: BridgeConfig, n: int, whose: str, each: str) -> dict[str, Any]:
    """The family's per-ESC lists (keys made with ``per_esc=True``), ``n`` entries each (1..n
    when not set).

    Raises:
        ConfigError: a list of another length (``whose`` is ``n`` entries long).
    """
    keys, lists = config.escs.keys(config.output.protocol), {}
    for name in (f.name for f in fields(keys) if f.metadata["per_esc"]):
        values = getattr(keys, name)
        if values and len(values) != n:
            raise ConfigError(
                f"{config.source}: [escs] {name} has {len(values)} entries but {whose}; "
                f"expected one per {each}"
            )
        lists[name] = values or tuple(range(1, n + 1))
    return lists


def _checked_setup(config: BridgeConfig) -> EscSetup[Any]:
    """The family's check of its keys: only the selected family's are checked against the
    rest (the others' for form only)."""
    family = config.family
    setup = EscSetup(config.escs.ids, config.escs.keys(family.name))
    try:
        return family.check(setup, config.rate_hz)
    except ConfigError as exc:
        raise ConfigError(f"{config.source}: {exc}") from None


def with_esc_count(config: BridgeConfig, n_outputs: int) -> BridgeConfig:
    """Fill the ESC lists' defaults (IDs and the family's per-ESC lists, 1..N) once the
    mixer's size is known, and check the family's keys against them.

    Raises:
        ConfigError: the configured lists do not have one entry per mixer output, or the
            family cannot drive these ESCs so.
    """
    escs = config.escs
    if escs.ids and len(escs.ids) != n_outputs:
        raise ConfigError(
            f"{config.source}: [escs] ids has {len(escs.ids)} entries but mixer "
            f"{config.mixer.name!r} has {n_outputs} outputs; expected one per output"
        )
    whose = f"mixer {config.mixer.name!r} has {n_outputs} outputs"
    sized = _per_esc_lists(config, n_outputs, whose, "output")
    name = config.output.protocol
    families = {**escs.families, name: replace(escs.keys(name), **sized)}
    ids = escs.ids or tuple(range(1, n_outputs + 1))
    config = replace(config, escs=replace(escs, ids=ids, families=families))
    _checked_setup(config)
    pole_pairs = config.telemetry.pole_pairs
    if isinstance(pole_pairs, tuple) and len(pole_pairs) != n_outputs:
        raise ConfigError(
            f"{config.source}: [telemetry] pole_pairs has {len(pole_pairs)} entries but mixer "
            f"{config.mixer.name!r} has {n_outputs} outputs; expected one number, or one per output"
        )
    return config


def with_mixer_esc_count(
    config: BridgeConfig, mixer: MixerDefinition | None = None
) -> BridgeConfig:
    """:func:`with_esc_count` for the configuration's mixer: ``mixer`` when the caller has it
    already, else the one ``[mixer] name`` names.

    Raises:
        ConfigError: the mixer cannot be loaded, or the ESC lists do not fit it.
    """
    if mixer is None:
        from bridge.mixing.loader import load_mixer

        mixer = load_mixer(config.mixer.name)
    return with_esc_count(config, len(mixer.outputs))
