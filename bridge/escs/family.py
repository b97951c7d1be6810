"""What an ESC family is to the rest of the bridge: one interface, one neutral telemetry record.

A family (CKESC, Flipsky FT, ...) lives in a folder of its own under ``bridge/escs/<name>/`` and
is known to the rest of the bridge only through :class:`EscFamily` (found by name in
:mod:`bridge.escs.registry`), the way python-can's interfaces sit behind ``BusABC`` and
ArduPilot's ESC drivers behind ``AP_ESC_Telem_Backend``. Nothing outside ``bridge/escs/``
names a family: the daemon, the output loop, the CAN reader, the ESC state, the publishers,
the simulator runner and the CLI ask the family for what they need.

What a family provides, by who needs it:

- the CAN reader and ``esc-bridge decode``: :meth:`EscFamily.owns` (is an ID in its space),
  :meth:`EscFamily.decode` (pure: a frame to an :class:`EscFrame` record, or ``None``),
  :meth:`EscFamily.node_of` (which ESC a malformed frame names), :meth:`EscFamily.reader_filters`
  (the kernel filters passing its telemetry);
- the ESC state (and through it MAVLink, Zenoh and the monitor):
  :meth:`EscFamily.telemetry` maps a decoded frame into the neutral :class:`EscTelemetry`, and
  :meth:`EscFamily.commands_seen` reads the bridge's own commands back as :class:`CommandSeen`;
- the output loop: :meth:`EscFamily.driver`, an :class:`~bridge.escs.drivers.EscDriver` (command
  fractions -1..1 to frames, safe frames, ticks per cycle);
- the start-up checks: :attr:`EscFamily.keys` (its ``[escs]`` keys), the defaults that depend on
  the family, :meth:`EscFamily.check_config`, :meth:`EscFamily.with_esc_count`, and
  :meth:`EscFamily.bus_figures` (the worst-case bus load of its commands and telemetry);
- the simulator and the demo: :meth:`EscFamily.simulators`, :meth:`EscFamily.demo_settings`;
- the CLI: :meth:`EscFamily.add_cli_commands` (set-up commands under ``esc-bridge esc``, may add
  none), :meth:`EscFamily.describe_command` and :meth:`EscFamily.describe_esc` (for ``esc
  spin`` and the motor test), :meth:`EscFamily.learn_node_ids` (may learn none).

Where the interface is thin, and how the families live with it (not yet hooks of its own):

- :meth:`EscFamily.decode` takes one frame and returns one record, as if a frame were a
  message. DroneCAN's transfers span several frames, so its family keeps one stateful decoder
  per thread (each thread reads one stream: the CAN reader, ``decode``, the plot) and returns a
  ``TransferPart`` for each frame before a transfer's last. A per-stream ``decoder()`` (created
  once per stream by each caller, stateless for CKESC and FT) would say so in the interface.
- Frames a family must send on a clock of its own rather than per command: DroneCAN's own
  NodeStatus, once a second, which its driver appends to a tick's frames by its own clock. A
  periodic-frames hook beside :meth:`EscFamily.driver` would let the output loop schedule them.
- The UAVCAN v0 framing CKESC and DroneCAN share is :mod:`bridge.escs.uavcan_v0`, beside this
  module: no family imports another.

A family module imports no part of the bridge outside ``bridge/escs/`` at import time except
:mod:`bridge.errors` and, for its keys, :mod:`bridge.config`; its simulator, set-up client and
CLI commands are imported only when asked for.

Adding a family: a folder ``bridge/escs/<name>/`` (listed in ``pyproject.toml``'s packages)
whose ``family.py`` has a class with every member of :class:`EscFamily` (``ckesc/`` and ``ft/``
are the examples: ``driver.py``, ``telemetry.py``, ``bus.py``, ``keys.py``, ``sim.py``), and
one line in :data:`bridge.escs.registry.FAMILIES`. Its ``[escs]`` keys (each named with the
family's prefix, so no two families' keys clash) are validated with the others' and read back
as ``config.escs.keys(name)``; ``[output] protocol``, every ``--protocol`` choice and
``esc-bridge decode --protocol auto`` follow from the registry.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

import can

if TYPE_CHECKING:
    import argparse

    from can.typechecking import CanFilter

    from bridge.config import BridgeConfig
    from bridge.escs.drivers import EscDriver
    from bridge.sim.base import SimEsc
    from bridge.sim.motor import MotorParams

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
    """A command read back from the bus, for the ESC at ``node_id`` or, for families that
    address by throttle channel, the ESC following ``channel``."""

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


class EscFamily(Protocol):
    """One ESC family: everything the bridge needs from it. See the module docstring."""

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
    :func:`bridge.config.key` (the key names carry the family's prefix, e.g. ``ft_mode``). The
    validated instance is ``config.escs.keys(name)``; :meth:`with_esc_count` returns it
    filled for the mixer's size."""
    learns_node_ids: bool
    """Whether :meth:`learn_node_ids` can ask the ESCs for their IDs (``[telemetry]
    learn_ids``)."""

    # -- frames ------------------------------------------------------------------------------

    def owns(self, arbitration_id: int) -> bool:
        """Whether a 29-bit CAN ID lies in the family's ID space (it may still not decode)."""
        ...

    def decode(self, msg: can.Message, esc_nodes: Collection[int] | None = None) -> EscFrame | None:
        """One frame decoded (pure: no I/O, clock or logging); ``None``: not the family's.
        ``esc_nodes`` (our ESCs' IDs, or None) lets a family whose IDs other
        protocols share refuse foreign nodes.

        Raises:
            bridge.errors.FrameError: the frame is in the family's space but malformed.
        """
        ...

    def node_of(self, msg: can.Message) -> int | None:
        """The ESC a (possibly malformed) frame's ID names, or None if it names none."""
        ...

    def reader_filters(self, esc_ids: Collection[int], read_back_commands: bool) -> list[CanFilter]:
        """python-can filters passing the telemetry of ``esc_ids`` and, with
        ``read_back_commands``, the bridge's own commands.

        Raises:
            bridge.errors.ValueRangeError: an ESC ID the protocol cannot have.
        """
        ...

    # -- telemetry ---------------------------------------------------------------------------

    def telemetry(self, frame: EscFrame) -> EscTelemetry | None:
        """A decoded frame as neutral telemetry; ``None`` if it is no telemetry (commands,
        service traffic). A telemetry frame whose content is not state (debug data) still maps
        to a record, with nothing but ``node_id``: it keeps the ESC online."""
        ...

    def commands_seen(self, frame: EscFrame) -> Sequence[CommandSeen]:
        """The commands a decoded command frame carries (none for other frames)."""
        ...

    # -- output ------------------------------------------------------------------------------

    def driver(self, config: BridgeConfig) -> EscDriver:
        """The command driver for ``config`` (its ESC lists already filled in)."""
        ...

    def bus_figures(self, config: BridgeConfig, rate_hz: float) -> BusFigures:
        """Worst-case traffic of ``config``'s ESCs with commands sent at ``rate_hz``."""
        ...

    def command_kind(self, config: BridgeConfig) -> str:
        """What the driver sends, in a word or two for the start-up log line."""
        ...

    def describe_command(self, config: BridgeConfig, fraction: float) -> str:
        """What ``fraction`` (0..1) of the full range means on the wire."""
        ...

    def describe_esc(self, config: BridgeConfig, index: int) -> str:
        """The ESC on mixer output ``index`` (0-based), for the motor test's messages."""
        ...

    # -- configuration -----------------------------------------------------------------------

    def check_config(self, config: BridgeConfig) -> None:
        """Checks of the family's keys against the other sections once ``config`` is built.
        Called for every family, selected or not (a check that only matters for the selected
        family tests ``config.output.protocol == self.name``).

        Raises:
            bridge.errors.ConfigError: naming the file, the section and key.
        """
        ...

    def with_esc_count(self, config: BridgeConfig, n_outputs: int) -> Any:
        """The family's keys with their per-ESC lists filled for ``n_outputs`` (``[escs] ids``
        already filled). Called for every family, selected or not, as :meth:`check_config`.

        Raises:
            bridge.errors.ConfigError: a list without one entry per output, or a value the
                family cannot send to so many ESCs.
        """
        ...

    def channels(self, config: BridgeConfig) -> Sequence[int] | None:
        """The throttle channel of each motor for a family that addresses ESCs by channel
        (:attr:`CommandSeen.channel`), else None."""
        ...

    def learn_node_ids(self, bus: can.BusABC, config: BridgeConfig) -> dict[int, int] | None:
        """Ask the ESCs on ``bus`` for their IDs: ``{motor index: node ID}`` for each that
        answered, or None if the family cannot ask.

        Raises:
            bridge.errors.LinkError: the answers are inconsistent.
        """
        ...

    # -- simulation, demo, CLI ---------------------------------------------------------------

    def simulators(
        self,
        ids: Sequence[int],
        channels: Sequence[int] | None,
        motor_params: MotorParams | None,
    ) -> list[SimEsc]:
        """Simulated ESCs with these IDs (checked by the caller against :attr:`node_ids`).

        Raises:
            ValueError: ``channels`` given to a family without them, or of the wrong length.
        """
        ...

    def demo_settings(self, n_escs: int) -> dict[str, dict[str, Any]]:
        """Configuration tables the demo adds for this family (merged over its own)."""
        ...

    def add_cli_commands(self, esc_commands: argparse._SubParsersAction[Any]) -> None:
        """Add the family's set-up commands to the ``esc-bridge esc`` group (maybe none)."""
        ...
