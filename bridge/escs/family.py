"""What an ESC family is to the rest of the bridge: its wire and its driver, behind one interface.

A family (CKESC, Flipsky FT, DroneCAN, ...) lives in a folder of its own, ``bridge/escs/<name>/``,
and the bridge's core knows it only through :class:`EscFamily` (found by name in
:mod:`bridge.escs.registry`), the way python-can's interfaces sit behind ``BusABC`` and
ArduPilot's ESC drivers behind ``AP_ESC_Telem_Backend``. Nothing outside ``bridge/escs/`` names
a family.

What the core needs of a family, and nothing else:

- its ID space: :attr:`~EscFamily.node_ids` and :meth:`~EscFamily.owns` (is a CAN ID the
  family's);
- a reader per stream of frames: :meth:`~EscFamily.decoder` makes an :class:`EscDecoder`
  (stateless for one-frame protocols, a reassembler for multi-frame transfers) that decodes a
  frame into the family's record and maps that record into the neutral :class:`EscTelemetry`,
  or the commands it carries into :class:`CommandSeen`;
- the kernel filters that pass its telemetry: :meth:`~EscFamily.reader_filters`;
- the driver: :meth:`~EscFamily.driver` makes an :class:`EscDriver` (command fractions to
  frames, safe frames, and what it sends in words);
- the worst-case bus load of its traffic: :meth:`~EscFamily.bus_figures`;
- its configuration: its ``[escs]`` keys (:attr:`~EscFamily.keys`), the defaults of the common
  keys it sets (:attr:`~EscFamily.default_rate_hz`, :attr:`~EscFamily.default_bitrate`), and
  their check (:meth:`~EscFamily.check`).

A family is given its own keys and the few common values it needs (:class:`EscSetup`: the ESC
IDs by mixer output; the command rate for its check), never the whole configuration: this
module and every family import nothing above ``bridge/escs/`` (type-only imports included)
but :mod:`bridge.errors`, :mod:`bridge.config_checks` (the key validators) and the simulated
motor of :mod:`bridge.sim` for their simulators.

Tools that only some commands need sit beside the family, not in the interface (as python-can's
``can.logger`` and ``can.viewer`` sit beside ``BusABC``). Whoever needs one finds it by the
family's package with :func:`bridge.escs.registry.tool`; a family without it has no module and
no stub:

- ``sim.py``: ``simulators(setup: EscSetup, motor_params: MotorParams | None) ->
  list[SimEsc]``, the family's simulated ESCs for ``esc-bridge sim``, the demo and the tests
  (``setup.ids`` checked by the caller against :attr:`~EscFamily.node_ids`); and, if the demo
  needs other settings than the defaults for this family, ``DEMO_SETTINGS``: configuration
  tables merged over the demo's own.
- ``setup.py``: ``learn_node_ids(bus: can.BusABC, setup: EscSetup) -> dict[int, int]``, for
  ``[telemetry] learn_ids``: the node ID of each mixer output (0-based) whose ESC answered.
- ``cli.py``: ``add_commands(esc_commands, bus_flags: BusFlags)``, the family's set-up commands
  under ``esc-bridge esc`` (:class:`bridge.escs.tools.BusFlags` is what the CLI hands them).

Adding a family: a folder ``bridge/escs/<name>/`` (listed in ``pyproject.toml``'s packages)
whose ``family.py`` has a class with the members of :class:`EscFamily` (``ft/`` is the small
example: ``records.py``, ``codec.py``, ``telemetry.py``, ``driver.py``, ``bus.py``, ``keys.py``,
``sim.py``; ``dronecan/`` one with multi-frame transfers), and one line in
:data:`bridge.escs.registry.FAMILIES`. Its ``[escs]`` keys (each named with the family's prefix,
so no two families' keys clash) are validated for form with every family's; ``[output]
protocol``, every ``--protocol`` choice and ``esc-bridge decode --protocol auto`` follow from the
registry.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Generic, Protocol, TypeVar

import can

if TYPE_CHECKING:
    from can.typechecking import CanFilter

# MAVLink ESC_FAILURE_FLAGS bits: what a family's status words map into.
FAILURE_NONE = 0
FAILURE_OVER_CURRENT = 1
FAILURE_OVER_VOLTAGE = 2
FAILURE_OVER_TEMPERATURE = 4
FAILURE_OVER_RPM = 8
FAILURE_INCONSISTENT_CMD = 16
FAILURE_MOTOR_STUCK = 32
FAILURE_GENERIC = 64


def frame_bits(data_bytes: int) -> int:
    """Worst-case bits on the wire for an extended data frame carrying ``data_bytes`` (0..8):
    ``67 + 8n + floor((54 + 8n - 1) / 4)``, bit stuffing and the 3-bit interframe space
    included (Davis, Burns, Bril, Lukkien 2007; docs/protocols.md §1.3).

    Raises:
        ValueError: ``data_bytes`` outside 0..8.
    """
    if not 0 <= data_bytes <= 8:
        raise ValueError(f"a classic CAN frame carries 0..8 data bytes, not {data_bytes}")
    return 67 + 8 * data_bytes + (54 + 8 * data_bytes - 1) // 4


KeysT = TypeVar("KeysT")


@dataclass(frozen=True)
class EscSetup(Generic[KeysT]):
    """What a family is given of the configuration: its own keys and the ESC IDs."""

    ids: tuple[int, ...]
    """The ESC ID on each mixer output, in output order (the family's node or ESC ID). Empty
    while the mixer's size is not known (the check when the configuration is read)."""
    keys: KeysT
    """The family's ``[escs]`` keys (an instance of :attr:`EscFamily.keys`); its per-ESC lists
    have one entry per ID once ``ids`` is filled."""
    channels: tuple[int, ...] | None = None
    """The throttle channel each output's ESC follows, for a family that addresses its ESCs by
    channel (:attr:`CommandSeen.channel`); set by the family's :meth:`EscFamily.check`."""


class EscFrame(Protocol):
    """A decoded frame of some family: the ESC it is from or to, and its payload record (a
    frozen dataclass, whose fields ``esc-bridge decode`` prints)."""

    @property
    def node_id(self) -> int: ...

    @property
    def message(self) -> Any: ...


@dataclass(frozen=True, slots=True)
class EscTelemetry:
    """What one telemetry frame said about one ESC, in no family's terms. ``None``: this frame
    does not carry it (the ESC state keeps what an earlier frame said)."""

    node_id: int
    """The ESC's ID on the bus (the family's node or ESC ID)."""
    rpm: int | None = None
    """Mechanical rpm, negative in reverse."""
    erpm: int | None = None
    """Electrical rpm, for families that report that: the state divides it by the motor's pole
    pairs into ``rpm``."""
    voltage_v: float | None = None
    current_a: float | None = None
    """Supply (battery) current; the state integrates it into mAh."""
    motor_current_a: float | None = None
    """Phase current."""
    throttle: float | None = None
    """The ESC's reported output, as a fraction (-1..1)."""
    mos_temp_c: float | None = None
    capacitor_temp_c: float | None = None
    motor_temp_c: float | None = None
    mcu_temp_c: float | None = None
    status: int | None = None
    """The ESC's raw status word, published as received."""
    status_failures: int | None = None
    """The ESC_FAILURE_FLAGS that ``status`` raises (the family's table)."""
    uncommanded_failures: int | None = None
    """The ESC_FAILURE_FLAGS that ``status`` raises only because no command reaches the ESC
    (its own "no throttle received" report): a failure while commands are being sent, an idle
    ESC's normal state when nothing commands it. Given with ``status``."""
    counters: Mapping[str, int] = field(default_factory=dict)
    """Slow information (counts, run times, fault codes), merged into the ESC's counters."""
    fault_counters: frozenset[str] = frozenset()
    """Which of ``counters`` are fault codes: while one is non-zero, the ESC reports a fault
    (GENERIC)."""


@dataclass(frozen=True, slots=True)
class CommandSeen:
    """A command a command frame carries (the driver's own frames for the ESC state, a
    capture's for the plot), for the ESC at ``node_id`` or, for families that address by
    throttle channel, the ESC following ``channel``."""

    value: float
    unit: str
    """What ``value`` is: throttle, current_a, current_fraction, duty, erpm, ..."""
    node_id: int | None = None
    channel: int | None = None


@dataclass(frozen=True, slots=True)
class BusFigures:
    """A family's worst-case periodic traffic at a command rate: frames and bits per second."""

    command_frames_per_s: float
    command_bits_per_s: float
    telemetry_frames_per_s: float
    telemetry_bits_per_s: float


class EscDecoder(Protocol):
    """The family's reader of one stream of frames (the CAN reader, one capture, one plot):
    frames to records, records to neutral telemetry. Pure: no I/O, clock or logging. A family
    whose transfers span frames keeps the partial transfers here, so each stream has its own."""

    def decode(self, msg: can.Message, esc_nodes: Collection[int] | None = None) -> EscFrame | None:
        """One frame decoded; ``None``: not the family's (or a transfer's frame before its
        last). ``esc_nodes`` (our ESCs' IDs, or None) lets a family whose IDs other protocols
        share refuse foreign nodes.

        Raises:
            bridge.errors.FrameError: the frame is in the family's space but malformed.
        """
        ...

    def node_of(self, msg: can.Message) -> int | None:
        """The ESC a (possibly malformed) frame's ID names, or None if it names none."""
        ...

    def telemetry(self, frame: EscFrame) -> EscTelemetry | None:
        """A decoded frame as neutral telemetry; ``None`` if it is no telemetry (commands,
        service traffic). A telemetry frame whose content is not state (debug data) still maps
        to a record, with nothing but ``node_id``: it keeps the ESC online."""
        ...

    def commands_seen(self, frame: EscFrame) -> Sequence[CommandSeen]:
        """The commands a decoded command frame carries (none for other frames)."""
        ...


class EscDriver(Protocol):
    """Turns one tick's command fractions into CAN frames, limited to the protocol's range,
    and says what it sends. The output loop ticks ``ticks_per_cycle`` times per cycle: a family
    that addresses every ESC in one tick has one tick per cycle, one that needs a frame per ESC
    spreads them across the cycle."""

    ticks_per_cycle: int
    """Ticks to address every ESC once (1: every tick addresses every ESC)."""
    kind: str
    """What the driver sends, in a word or two for the start-up log line."""

    def tick_frames(self, tick: int, fractions: Sequence[float]) -> list[can.Message]:
        """Frames for ``tick`` commanding ``fractions`` (one per mixer output, -1..1). They
        are the driver's until its next call, which may reuse them: send them before then."""
        ...

    def prepare(self, fractions: Sequence[float]) -> None:
        """Make now, between ticks, what :meth:`tick_frames` will need for ``fractions``: the
        loop calls this with each new input's commands, so that a tick only stamps and sends.
        A driver whose frames differ every tick whatever the input does nothing here. Raises
        what :meth:`tick_frames` would (the tick then makes them again and fails safe)."""
        ...

    def safe_frames(self, tick: int) -> list[can.Message]:
        """Frames for ``tick`` commanding the safe output (motors stopped)."""
        ...

    def describe_command(self, fraction: float) -> str:
        """What ``fraction`` (0..1) of the full range means on the wire."""
        ...

    def describe_esc(self, index: int) -> str:
        """The ESC on mixer output ``index`` (0-based), for the motor test's messages."""
        ...


class EscFamily(Protocol):
    """One ESC family: what the bridge's core needs of it. See the module docstring."""

    name: str
    """Its name in ``[output] protocol``, ``--protocol`` and the registry."""
    title: str
    """Its name in messages (e.g. "CKESC")."""
    node_ids: range
    """The ESC IDs the protocol can address."""
    default_rate_hz: int
    """``[output] rate_hz`` when not set."""
    default_bitrate: int
    """``[can] bitrate`` when not set."""
    keys: type
    """Its ``[escs]`` keys: a frozen dataclass whose fields are made with
    :func:`bridge.config_checks.key` (the key names carry the family's prefix, e.g.
    ``ft_mode``; a per-ESC list says so with ``per_esc=True`` and is sized with ``[escs] ids``
    by the configuration)."""

    def owns(self, arbitration_id: int) -> bool:
        """Whether a 29-bit CAN ID lies in the family's ID space (it may still not decode)."""
        ...

    def decoder(self) -> EscDecoder:
        """A decoder for one stream of frames (each reader, capture or plot makes its own)."""
        ...

    def reader_filters(self, esc_ids: Collection[int]) -> list[CanFilter]:
        """python-can filters passing the telemetry of ``esc_ids`` (the bridge's own commands
        are not read back: the output loop says what it sent).

        Raises:
            bridge.errors.ValueRangeError: an ESC ID the protocol cannot have.
        """
        ...

    def check(self, setup: EscSetup[Any], rate_hz: int) -> EscSetup[Any]:
        """Check the family's keys against the ESC IDs and the command rate ``rate_hz``, and
        return the setup the family runs with (``setup``, with its ``channels`` where the
        family addresses its ESCs by channel). Called for the selected family only: when the
        configuration is read (``setup.ids`` as configured, maybe empty) and again once the
        mixer has sized the ESC lists.

        Raises:
            bridge.errors.ConfigError: naming the section and key (``[escs] ...``; the caller
                puts the file in front).
        """
        ...

    def driver(self, setup: EscSetup[Any]) -> EscDriver:
        """The command driver for ``setup`` (checked, its ESC lists filled in)."""
        ...

    def bus_figures(self, setup: EscSetup[Any], rate_hz: float) -> BusFigures:
        """Worst-case traffic of ``setup``'s ESCs with commands sent at ``rate_hz``."""
        ...
