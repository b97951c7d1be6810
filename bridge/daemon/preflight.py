"""Start-up checks: everything ``esc-bridge run`` refuses, found before it sends a CAN frame.

:func:`plan` is the one place that validates a :class:`~bridge.config.BridgeConfig` against
everything that can be known without opening a bus or a link: the mixer and the ESC lists, the
input and valid ranges, the bus load, the CAN interface name, the Zenoh endpoints, every
MAVLink URL (and an output that repeats one), whether the mixer's inputs are ones the MAVLink
source carries at all, the recording directory, and the MAVLink dialect. ``run`` calls it
before it opens anything and ``run --check`` calls it and stops, so the two can never disagree
about a configuration.

Why a separate module: the checks are a pure function of the configuration (plus the file
system for the recording directory and the dialect cache), and keeping them out of the daemon
means one list of what "valid" means. :func:`plan` opens no socket, bus or device and leaves no
file behind; the one thing it may write is the MAVLink dialect cache, because generating the
dialect is the only way to know it loads. What it cannot know without opening (is the CAN
device up, is the UDP port free, is there a serial device at that path) fails at start as a
:class:`~bridge.errors.LinkError`, still before any frame is sent.

Every error is a :class:`~bridge.errors.ConfigError` whose message starts with the config's
source (the file, or "command line") and names the ``[section] key`` or flag, what was wrong and
what was expected. The :class:`Plan` carries what the checks worked out (the mixer with its
ranges, the ESC lists filled in, the parsed endpoints, the effective valid range), so nothing
needs to be worked out twice.
"""

from __future__ import annotations

import contextlib
import os
import stat
import tempfile
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Final

from bridge.can_interface import Assessment, assess, read_link
from bridge.can_io import check_interface
from bridge.config import BridgeConfig, with_mixer_esc_count
from bridge.errors import ConfigError
from bridge.mavlink import CACHE_ENV, DialectError, load_dialect
from bridge.mavlink.endpoints import Endpoint, check_endpoints
from bridge.mavlink.esc_messages import describe_sets
from bridge.mixing.definition import AXIS_NAMES, CHANNEL_COUNT, PWM_RANGE_US, MixerDefinition
from bridge.mixing.loader import load_mixer
from bridge.output.busload import check_bus_load
from bridge.telemetry.zenoh_out import session_config

__all__ = [
    "SOURCE_CHANNELS",
    "SOURCE_INPUT_RANGES",
    "SOURCE_VALID_RANGES",
    "Plan",
    "plan",
]

# Default input range of channel sources by MAVLink source, unless [mixer] input_range is set:
# SERVO_OUTPUT_RAW and PX4's ACTUATOR_OUTPUT_STATUS (from actuator_outputs) carry PWM µs,
# HIL_ACTUATOR_CONTROLS carries normalized 0..1 motor commands.
SOURCE_INPUT_RANGES: dict[str, tuple[float, float] | None] = {
    "servo_output_raw": None,  # the mixer's own (PWM 1000..2000 µs unless it says otherwise)
    "actuator_output_status": None,
    "hil_actuator_controls": (0.0, 1.0),
    "actuator_control_target": None,
}

# Default [mixer] valid_range by MAVLink source: a PWM value outside 800..2200 µs or a normalized
# one outside -1.5..1.5 is no motor command but a fault (a disconnected output, a unit mix-up).
SOURCE_VALID_RANGES: dict[str, tuple[float, float]] = {
    "servo_output_raw": (800.0, 2200.0),
    "actuator_output_status": (800.0, 2200.0),
    "hil_actuator_controls": (-1.5, 1.5),
    "actuator_control_target": (-1.5, 1.5),
}

# Channels each source fills (bridge.mavlink.actuators): SERVO_OUTPUT_RAW ports 0 and 1 of
# 16 and ACTUATOR_OUTPUT_STATUS's 32 actuators fill ch1..ch32, HIL_ACTUATOR_CONTROLS ch1..ch16;
# ACTUATOR_CONTROL_TARGET fills no channel but roll, pitch, yaw and thrust.
SOURCE_CHANNELS: dict[str, int] = {
    "servo_output_raw": CHANNEL_COUNT,
    "actuator_output_status": CHANNEL_COUNT,
    "hil_actuator_controls": 16,
    "actuator_control_target": 0,
}
_AXIS_SOURCE: Final = "actuator_control_target"
_AXIS_INPUT_RANGE: Final = (-1.0, 1.0)  # ACTUATOR_CONTROL_TARGET's roll, pitch, yaw (thrust 0..1)


@dataclass(frozen=True)
class Plan:
    """A validated start-up plan: nothing is opened or sent until
    :func:`bridge.daemon.supervisor.run` executes it."""

    config: BridgeConfig
    """The configuration, its ESC lists filled in (one entry per mixer output)."""
    mixer: MixerDefinition
    """The mixer, its channel outputs set to ``input_range`` when that is not None."""
    load_text: str
    """The worst-case bus load, described."""
    input_range: tuple[float, float] | None
    """The channel range: ``[mixer] input_range`` or the source's; None: the mixer's own."""
    valid_range: tuple[float, float]
    """``[mixer] valid_range`` or the source's default: inputs outside it are invalid."""
    autopilot: Endpoint
    """``[mavlink] url``, parsed."""
    outputs: tuple[Endpoint, ...]
    """``[mavlink] outputs``, parsed, in order; no two are the same connection."""
    record_dir: Path | None
    """The recording directory (``--record``), checked writable, or None."""
    passed: tuple[str, ...]
    """What each check beyond the mixer and the bus load found, one line each (for --check)."""
    interface_refusal: str | None = None
    """Why ``run`` must not start on the CAN interface as the system has it (missing, down,
    bus-off), with what to do; None: it may. ``run`` and ``--check`` both refuse with it (exit
    1), ``--check`` after printing what every other check found."""


def plan(config: BridgeConfig, record_dir: str | Path | None = None) -> Plan:
    """Validate ``config`` (and the recording directory ``record_dir``, if any) completely.

    Opens nothing and writes nothing but the MAVLink dialect cache (see the module docstring).

    Raises:
        ConfigError: anything wrong, named by file, key, flag or mixer entry.
    """
    source = config.source
    check_interface(config.can, source)
    _check_mixer_file(config)
    with _located(source, "[mixer] name: "):
        definition = load_mixer(config.mixer.name)
    input_range = config.mixer.input_range or SOURCE_INPUT_RANGES[config.mavlink.source]
    if input_range is not None:
        with _located(source, "[mixer] input_range: "):
            definition = definition.with_input_range(*input_range)
    config = with_mixer_esc_count(config, definition)
    if config.zenoh.enabled:
        with _located(source):
            session_config(config.zenoh)  # a malformed endpoint is a config error, found now
    load = check_bus_load(config)
    with _located(source):
        autopilot, outputs = check_endpoints(config.mavlink)
    passed = [
        _describe_links(autopilot, outputs),
        _check_inputs(config, definition),
    ]
    valid_range, valid_text = _check_valid_range(config, definition, input_range)
    passed += [
        valid_text,
        _describe_commands(config),
        describe_sets(config.mavlink, len(config.escs.ids)),
        _check_dialect(),
    ]
    interface = _check_can_interface(config)
    if interface is not None:
        passed.append(interface.text)
    directory = None
    if record_dir:  # as the daemon reads it: an empty --record means no recording
        directory = Path(record_dir)
        passed.append(_check_record_dir(directory))
    return Plan(
        config,
        definition,
        load.describe(),
        input_range,
        valid_range,
        autopilot,
        tuple(outputs),
        directory,
        tuple(passed),
        None if interface is None else interface.refusal,
    )


def _check_can_interface(config: BridgeConfig) -> Assessment | None:
    """A SocketCAN interface's state and bit rate against ``[can] bitrate`` (None for other
    interfaces: they have no system configuration to read).

    Raises:
        ConfigError: the interface runs at another bit rate.
    """
    if config.can.interface != "socketcan":
        return None
    channel = config.can.channel
    found = assess(read_link(channel), channel, config.bitrate)
    if found.mismatch:
        raise ConfigError(f"{config.source}: {found.refusal}")
    return found


@contextlib.contextmanager
def _located(source: str, key: str = "") -> Iterator[None]:
    """Start a ConfigError raised inside with ``source: key`` unless it names the source."""
    try:
        yield
    except ConfigError as exc:
        text = str(exc)
        if text.startswith(f"{source}: "):
            raise
        raise ConfigError(f"{source}: {key}{text}") from exc


def _check_mixer_file(config: BridgeConfig) -> None:
    """Refuse a mixer path that names a device before :func:`load_mixer` reads it: reading a
    serial port waits for its carrier forever, and /dev/zero never ends."""
    name = config.mixer.name
    if not (name.endswith(".toml") or "/" in name or "\\" in name):
        return  # a bundled mixer's name (load_mixer's rule)
    try:
        mode = Path(name).stat().st_mode
    except OSError:
        return  # load_mixer names what is wrong with it
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        raise ConfigError(
            f"{config.source}: [mixer] name {name!r}: a device, not a file; expected a bundled "
            "mixer's name or a mixer .toml file"
        )


def _describe_links(autopilot: Endpoint, outputs: Iterable[Endpoint]) -> str:
    def where(endpoint: Endpoint) -> str:
        if endpoint.kind == "serial":
            return f"serial {endpoint.address} at {endpoint.baud} baud"
        return f"{endpoint.kind} {endpoint.address}"

    extra = ", ".join(where(output) for output in outputs) or "none"
    return f"MAVLink: autopilot on {where(autopilot)}; outputs: {extra}"


def _input_list(names: Iterable[str]) -> str:
    """``ch1..ch4, ch7, roll, thrust``: runs of three or more channels shortened."""
    channels = sorted(int(n[2:]) for n in names if n.startswith("ch"))
    axes = [n for n in AXIS_NAMES if n in set(names)]
    parts: list[str] = []
    start = 0
    for i in range(1, len(channels) + 1):
        if i == len(channels) or channels[i] != channels[i - 1] + 1:
            run = channels[start:i]
            if len(run) >= 3:
                parts.append(f"ch{run[0]}..ch{run[-1]}")
            else:
                parts += [f"ch{c}" for c in run]
            start = i
    return ", ".join(parts + axes)


def _carried(source: str) -> set[str]:
    """The inputs a MAVLink source fills (the others stay NaN: absent)."""
    carried = {f"ch{i}" for i in range(1, SOURCE_CHANNELS[source] + 1)}
    return carried | set(AXIS_NAMES) if source == _AXIS_SOURCE else carried


def _check_inputs(config: BridgeConfig, definition: MixerDefinition) -> str:
    """Refuse a mixer that reads an input the source never fills.

    The mixer treats an absent (NaN) input that any output reads as invalid and the daemon
    sends safe values instead: a geometry mixer fed SERVO_OUTPUT_RAW without ``[mixer]
    axis_channels`` would start, report FAILSAFE invalid input, and never spin a motor.
    """
    where = config.source
    src = config.mavlink.source
    carried = _carried(src)
    carries = f"[mavlink] source {src!r} carries {_input_list(carried) or 'no channels'}"
    axis_channels: Mapping[str, int] = config.mixer.axis_channels or {}
    absent = {axis: ch for axis, ch in axis_channels.items() if f"ch{ch}" not in carried}
    if absent:
        taken = ", ".join(f"{axis} from channel {ch}" for axis, ch in absent.items())
        instead = " (or none: it carries the axes itself)" if src == _AXIS_SOURCE else ""
        raise ConfigError(
            f"{where}: [mixer] axis_channels takes {taken}, but {carries}; expected channels the "
            f"source carries{instead}"
        )
    carried |= set(axis_channels)
    used = {name for output in definition.outputs for name, _ in output.weights}
    missing = used - carried
    if missing:
        hints = []
        if missing & set(AXIS_NAMES):
            hints.append(
                "[mixer] axis_channels to take the axes from channels (e.g. { roll = 1, "
                f'pitch = 2, thrust = 3, yaw = 4 }}), or [mavlink] source = "{_AXIS_SOURCE}"'
            )
        if missing - set(AXIS_NAMES):
            hints.append(
                "a source that carries channels, or a geometry mixer such as quad-x"
                if src == _AXIS_SOURCE
                else "a source that carries those channels, or a mixer that reads fewer"
            )
        raise ConfigError(
            f"{where}: [mixer] name {config.mixer.name!r} reads {_input_list(missing)}, but "
            f"{carries}"
            + (f" and [mixer] axis_channels {_input_list(axis_channels)}" if axis_channels else "")
            + ": every input would be invalid and no motor would ever spin; expected "
            + "; or ".join(hints)
        )
    via = f" ({_input_list(axis_channels)} by [mixer] axis_channels)" if axis_channels else ""
    return f"mixer inputs {_input_list(used)}: all carried by {src}{via}"


def _range_text(bounds: tuple[float, float]) -> str:
    return f"[{bounds[0]:g}, {bounds[1]:g}]"


def _check_valid_range(
    config: BridgeConfig, definition: MixerDefinition, input_range: tuple[float, float] | None
) -> tuple[tuple[float, float], str]:
    """The effective valid range, which must contain every input range the mixer maps from:
    a valid input would otherwise be refused as invalid (motors stopped in flight)."""
    src = config.mavlink.source
    given = config.mixer.valid_range
    valid = (float(given[0]), float(given[1])) if given else SOURCE_VALID_RANGES[src]
    valid_name = "[mixer] valid_range" if given else f"[mixer] valid_range (default for {src})"
    if config.mixer.input_range is not None:
        override = "[mixer] input_range"
    else:
        override = f"the input range of [mavlink] source {src!r}"
    ranges: dict[tuple[float, float], str] = {}  # each range once, with who set it first
    for output in definition.outputs:
        if output.uses_channels:
            what = (
                override
                if input_range is not None
                else f"mixer {config.mixer.name!r} output {output.name!r} input_range"
            )
            ranges.setdefault(output.input_range, what)
    if config.mixer.axis_channels:
        # The axes are read from channels over input_range, or PWM (as the daemon maps them).
        what = override if input_range is not None else "the PWM range [mixer] axis_channels read"
        ranges.setdefault(input_range or PWM_RANGE_US, what)
    if src == _AXIS_SOURCE:
        ranges.setdefault(_AXIS_INPUT_RANGE, "the ACTUATOR_CONTROL_TARGET axis range")
    for bounds, what in ranges.items():
        low, high = min(bounds), max(bounds)
        if not valid[0] <= low <= high <= valid[1]:
            raise ConfigError(
                f"{config.source}: {valid_name} {_range_text(valid)} does not contain {what} "
                f"{_range_text(bounds)}; expected a valid range that contains the input range, "
                "or valid inputs would be refused as invalid"
            )
    inside = ", ".join(_range_text(bounds) for bounds in ranges)
    return valid, f"valid range {_range_text(valid)} contains the input range {inside}"


def _describe_commands(config: BridgeConfig) -> str:
    output = config.output
    if output.motor_test:
        senders = ", ".join(str(s) for s in sorted(config.command_sender_ids))
        test = f"motor test on, from system IDs {senders}"
    else:
        test = "motor test off (MAV_CMD_DO_MOTOR_TEST refused)"
    return f"arming state older than {output.arming_timeout_ms} ms counts as disarmed; {test}"


def _check_dialect() -> str:
    """Load (and on first use generate) the MAVLink dialect the link will speak."""
    try:
        dialect = load_dialect()
    except DialectError as exc:
        raise ConfigError(
            f"MAVLink dialect: {exc}; expected a dialect esc-bridge can generate and load "
            f"(${CACHE_ENV} names its cache directory)"
        ) from exc
    where = getattr(dialect, "__file__", None) or "generated in memory: no writable cache"
    return f"MAVLink dialect loads ({where})"


def _check_record_dir(directory: Path) -> str:
    """The recording directory exists or can be created, is a directory, and is writable.

    Checked by creating an unnamed temporary file (removed on close) in the directory, or in
    its nearest existing ancestor when it is yet to be created: nothing is left behind.
    """
    where = f"command line: --record {str(directory)!r}"
    expected = "expected a writable directory, or a path where one can be created"
    probe = directory
    try:
        if directory.exists():
            if not directory.is_dir():
                raise ConfigError(f"{where}: not a directory; {expected}")
            probe, status = directory, "exists"
        elif os.path.lexists(directory):
            raise ConfigError(f"{where}: a broken symbolic link; {expected}")
        else:
            probe = directory.absolute().parent
            while not probe.exists():
                probe = probe.parent
            if not probe.is_dir():
                raise ConfigError(
                    f"{where}: cannot be created: {probe} is not a directory; {expected}"
                )
            status = f"to be created in {probe}"
        with tempfile.TemporaryFile(dir=probe):
            pass
    except OSError as exc:
        raise ConfigError(
            f"{where}: cannot write in {probe}: {exc.strerror or exc}; {expected}"
        ) from exc
    return f"recording into {directory} ({status}, writable)"
