"""The control loop's input side: the autopilot's link, read where the CAN frames are sent.

The control loop owns the autopilot's MAVLink transport (non-blocking,
:mod:`bridge.mavlink.transport`), so nothing in the main process (telemetry, Zenoh, logging, a
CAN reader under a flood, a garbage collection) can delay an input or make a fresh one look old.
For every chunk read it:

* finds the frames (:class:`~bridge.mavlink.frames.FrameScanner`: a few µs per frame, no
  pymavlink parser) and keeps those of the configured autopilot (system and component), signed
  with the configured key when there is one. A UDP datagram is scanned on its own: a frame cut
  short at its end is junk, never completed by the next datagram, which may come from anyone.
  On UDP the autopilot is also tied to one address
  (:class:`~bridge.mavlink.autopilot_address.AutopilotAddress`): frames claiming its IDs from
  any other are refused and counted. That costs one comparison per datagram from the
  autopilot's own address; only datagrams from elsewhere are looked at frame by frame;
* takes the arming state from its HEARTBEAT (and HIL_ACTUATOR_CONTROLS' mode), stamped with
  the kernel's receive time;
* decodes the configured motor-output message into the input vector, dates it by the
  autopilot's own clock (:class:`~bridge.mavlink.clock.AutopilotClock`: a packet that sat in a
  buffer is known to be old) and mixes it, refusing NaN, infinite and out-of-range channels;
* relays to the main process (:mod:`bridge.mavlink.relay`) the frames it acts on
  (``InputSetup.relay_msg_ids``: HEARTBEAT, commands, the autopilot's clock), so that it wakes
  for nothing else; every frame, the outputs too, when it records the link (it learns how many
  outputs arrived from the loop's counters).

It writes to the link what the main process relays the other way. Nothing here blocks or logs
per frame: counters go to :class:`~bridge.output.mailbox.LoopStats`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from bridge.config import BridgeConfig
from bridge.mavlink import load_dialect
from bridge.mavlink.actuators import (
    HEARTBEAT_ID,
    decoder_for,
    heartbeat_armed,
    heartbeat_autopilot,
)
from bridge.mavlink.autopilot_address import Address, AutopilotAddress, address_code
from bridge.mavlink.clock import AutopilotClock
from bridge.mavlink.endpoints import parse_url
from bridge.mavlink.frames import Frame, FrameScanner, ReplayGuard, signing_timestamp
from bridge.mavlink.relay import LoopEnd
from bridge.mavlink.transport import open_transport
from bridge.mavlink.transport.base import AutopilotTransport
from bridge.mixing.definition import AXIS_VALID_RANGE, PWM_RANGE_US, MixerDefinition
from bridge.mixing.mixer import AxisChannels, Mixer
from bridge.output.mailbox import InputSnapshot, LoopStats
from bridge.output.safety import ControlInputs

# Chunks read per wake-up at most: enough to empty the socket at every tick whatever the
# link carries (a queue that grew would make every input old), few enough that a flood on the
# link cannot hold a tick off for long.
MAX_READS_PER_WAKE = 256
MAX_RELAYED_FRAMES_PER_WAKE = 64


@dataclass(frozen=True)
class InputSetup:
    """What the input side needs besides the configuration, picklable."""

    mixer: MixerDefinition
    valid_range: tuple[float, float]
    channel_range: tuple[float, float] | None  # for axis_channels; None: the mixer's (PWM)
    relay_outputs: bool = False  # relay the autopilot's outputs too (the recording wants them)
    # The message IDs the main process acts on: only those are relayed (None: every frame).
    relay_msg_ids: frozenset[int] | None = None


class AutopilotInput:
    """Reads the autopilot's link and keeps :class:`~bridge.output.safety.ControlInputs` current.

    Use :meth:`open` once, then :meth:`on_readable` when :attr:`fd` polls readable,
    :meth:`on_relay` when the relay does, :meth:`service` every wake-up, :meth:`close` at the end.
    """

    def __init__(
        self,
        config: BridgeConfig,
        setup: InputSetup,
        inputs: ControlInputs,
        stats: LoopStats,
        snapshot: InputSnapshot,
        relay: LoopEnd | None,
    ) -> None:
        mavlink = config.mavlink
        self._endpoint = parse_url(mavlink.url)
        self._inputs = inputs
        self._stats = stats
        self._counters = stats.counters
        self._snapshot = snapshot
        self._relay = relay
        self._autopilot = (mavlink.autopilot_system_id, mavlink.autopilot_component_id)
        # A silent autopilot's place on a UDP link is taken only once its arming state has
        # timed out (the HEARTBEAT-lost failsafe already holds the motors stopped).
        self._move_after_ns = config.output.arming_timeout_ms * 1_000_000
        self._address: AutopilotAddress | None = None  # UDP only, from open()
        self._whole = False  # each read is a whole datagram: nothing carries to the next
        # With a key, only signed, fresh control messages count (the guard checks the
        # signature before it touches the replay state).
        self._guard = (
            ReplayGuard(bytes.fromhex(mavlink.signing_key), signing_timestamp(time.time_ns()))
            if mavlink.signing_key
            else None
        )
        self._decoder = decoder_for(
            mavlink.source, mavlink.autopilot_system_id, mavlink.component_id
        )
        # The main process gets every frame but the autopilot's outputs, which the loop acts on
        # and counts; all of them when it records the link.
        self._relay_outputs = setup.relay_outputs
        self._relay_msg_ids = setup.relay_msg_ids
        self._clock = AutopilotClock(time_bits=self._decoder.time_bits)
        self._scanner = FrameScanner.for_dialect(load_dialect())
        self._mixer = Mixer(setup.mixer, setup.valid_range, AXIS_VALID_RANGE)
        self._axes = (
            AxisChannels(mavlink_axes, setup.channel_range or PWM_RANGE_US)
            if (mavlink_axes := config.mixer.axis_channels)
            else None
        )
        self._transport: AutopilotTransport | None = None
        # What the autopilot said before it restarted, or before the link was reopened, is
        # forgotten: its arming state above all (a new boot is disarmed until it says so).
        self._reboots_seen = 0
        self._reconnects_seen = 0
        self._inputs_seen: list[float] | None = None  # the newest input vector, for reports
        self.fractions: list[float] | None = None
        """The mix of the newest input; None while there is none or it is invalid."""
        slot = stats.slot
        self._i_frames, self._i_outputs = slot("input_frames"), slot("input_outputs")
        self._i_heartbeats, self._i_foreign = slot("input_heartbeats"), slot("input_foreign")
        self._i_unsigned, self._i_order = slot("input_unsigned"), slot("input_out_of_order")
        self._i_invalid, self._i_mixer = slot("input_invalid"), slot("mixer_errors")
        self._i_relay_dropped, self._i_age = slot("relay_dropped"), slot("input_age_us")
        self._i_sent, self._i_dropped = slot("link_sent"), slot("link_dropped")
        self._i_bad_crc, self._i_junk = slot("input_bad_crc"), slot("input_junk_bytes")
        self._i_reconnects = slot("link_reconnects")
        self._i_other = slot("input_other_address")
        self._i_other_from = slot("input_other_address_from")
        self._i_address = slot("link_autopilot_address")
        self._i_moves = slot("link_autopilot_moves")

    def open(self) -> None:
        """Open the autopilot's transport.

        Raises:
            LinkError: the link cannot be opened and will not get better by waiting (an
                address in use, an unknown host).
        """
        transport = self._transport = open_transport(self._endpoint)
        self._whole = transport.datagrams
        if transport.datagrams:
            address = self._address = AutopilotAddress(
                transport.configured_peer, self._move_after_ns
            )
            if address.address is not None:
                self._counters[self._i_address] = address_code(address.address)

    @property
    def fd(self) -> int | None:
        """The descriptor to poll for input now; None while the link is down."""
        return None if self._transport is None else self._transport.fileno()

    @property
    def wants_write(self) -> bool:
        return self._transport is not None and self._transport.wants_write()

    def service(self, now_ns: int) -> None:
        """Progress connects and pending writes; cheap when there is nothing to do."""
        transport = self._transport
        if transport is not None:
            transport.service(now_ns)
            reconnects = transport.stats.reconnects
            if reconnects != self._reconnects_seen:
                self._reconnects_seen = reconnects
                self._counters[self._i_reconnects] = reconnects
                self._forget_autopilot(now_ns)

    def on_readable(self, now_ns: int) -> bool:
        """Read what is waiting; True when a new input was acted on."""
        transport = self._transport
        if transport is None:
            return False
        fresh = False
        address, whole = self._address, self._whole
        for _ in range(MAX_READS_PER_WAKE):
            chunk = transport.recv()
            if chunk is None:
                break
            data, received_ns = chunk
            frames = self._scanner.feed(data, whole=whole)
            if address is not None:
                sender = transport.sender
                if sender == address.address:
                    address.heard_ns = received_ns
                elif frames and sender is not None:
                    frames = self._screen(frames, address, sender, received_ns)
            relayed: list[bytes] = []
            for frame in frames:
                fresh |= self._on_frame(frame, received_ns, now_ns)
                if self._relays(frame):
                    relayed.append(frame.raw)
            relay = self._relay
            if relayed and relay is not None and not relay.forward(b"".join(relayed)):
                self._counters[self._i_relay_dropped] += 1
        scanner, counters = self._scanner, self._counters
        counters[self._i_frames] = scanner.frames
        counters[self._i_bad_crc] = scanner.bad_crc
        counters[self._i_junk] = scanner.junk_bytes
        return fresh

    def on_relay(self) -> None:
        """Write to the autopilot the frames the main process relayed.

        Raises:
            EOFError: the main process is gone.
        """
        relay, transport = self._relay, self._transport
        if relay is None:
            return
        counters = self._counters
        for _ in range(MAX_RELAYED_FRAMES_PER_WAKE):
            frame = relay.take()
            if frame is None:
                return
            if transport is not None and transport.send(frame):
                counters[self._i_sent] += 1
            else:
                counters[self._i_dropped] += 1

    def close(self) -> None:
        if self._transport is not None:
            self._transport.close()
            self._transport = None

    def _relays(self, frame: Frame) -> bool:
        """Whether the main process gets ``frame``: all of them when it records the link, else
        those it acts on (not the autopilot's outputs: the loop acts on them and counts them),
        so that it wakes for nothing else."""
        if self._relay_outputs:
            return True
        if self._relay_msg_ids is not None and frame.msg_id not in self._relay_msg_ids:
            return False
        return not self._is_autopilot_output(frame)

    def _screen(
        self, frames: list[Frame], address: AutopilotAddress, sender: Address, received_ns: int
    ) -> list[Frame]:
        """The frames of a datagram from ``sender``, which is not the autopilot's address, less
        those claiming the autopilot's IDs that are refused. While its place is held (its
        address spoke within the arming timeout, or is udpout's peer) every such frame is
        refused and counted. While the place is free (no address yet, or the old one silent for
        longer), the first control message (HEARTBEAT or motor output) makes ``sender`` the
        autopilot's address; any other frame passes, taking nothing (none is acted on)."""
        autopilot, control_ids = self._autopilot, self._decoder.msg_ids
        refused = address.refused
        kept: list[Frame] = []
        for frame in frames:
            if (frame.sys_id, frame.comp_id) == autopilot and sender != address.address:
                if not address.may_take(received_ns):
                    address.refuse(sender)
                    continue
                if frame.msg_id == HEARTBEAT_ID or frame.msg_id in control_ids:
                    self._take_address(address, sender, received_ns)
            kept.append(frame)
        if address.refused != refused:
            counters = self._counters
            counters[self._i_other] = address.refused
            counters[self._i_other_from] = address_code(sender)
        return kept

    def _take_address(self, address: AutopilotAddress, sender: Address, now_ns: int) -> None:
        """``sender`` is the autopilot's address from now on: replies go there, and one that
        took a silent address's place is a new autopilot as far as the loop knows."""
        moved = address.take(sender, now_ns)
        if self._transport is not None:
            self._transport.reply_to(sender)
        counters = self._counters
        counters[self._i_address] = address_code(sender)
        counters[self._i_moves] = address.moves
        if moved:
            self._forget_autopilot(now_ns)

    def _is_autopilot_output(self, frame: Frame) -> bool:
        return (
            frame.msg_id in self._decoder.msg_ids
            and (
                frame.sys_id,
                frame.comp_id,
            )
            == self._autopilot
        )

    def _on_frame(self, frame: Frame, received_ns: int, now_ns: int) -> bool:
        msg_id = frame.msg_id
        is_heartbeat = msg_id == HEARTBEAT_ID
        if not is_heartbeat and msg_id not in self._decoder.msg_ids:
            return False
        counters = self._counters
        if (frame.sys_id, frame.comp_id) != self._autopilot:
            counters[self._i_foreign] += 1
            return False
        if self._guard is not None and not self._guard.accept(frame):
            counters[self._i_unsigned] += 1
            return False
        inputs = self._inputs
        if is_heartbeat:
            armed = heartbeat_armed(frame)
            if armed is not None:
                counters[self._i_heartbeats] += 1
                self._decoder.identify(heartbeat_autopilot(frame) or 0)
                self._set_armed(armed, received_ns)
            return False
        decoded = self._decoder.decode(frame)
        if decoded is None:
            return False
        if decoded.armed is not None:
            self._set_armed(decoded.armed, received_ns)
        produced_ns = self._clock.produced_ns(decoded.time_us, received_ns)
        if self._clock.reboots != self._reboots_seen:
            self._reboots_seen = self._clock.reboots
            self._set_armed(False, received_ns)  # a new boot: disarmed until its HEARTBEAT
        if inputs.have_input and produced_ns < inputs.input_produced_ns:
            counters[self._i_order] += 1  # overtaken on the way: the newer one stands
            return False
        counters[self._i_outputs] += 1
        values = decoded.values
        if self._axes is not None:
            self._axes.fill(values)
        try:
            fractions = self._mixer.mix(values, inputs.armed)
        except Exception:  # noqa: BLE001 - any mixer fault must become safe values, never a crash
            counters[self._i_mixer] += 1
            fractions = None
        else:
            if fractions is None:
                counters[self._i_invalid] += 1
        self.fractions = fractions
        inputs.note_input(produced_ns, fractions is not None)
        counters[self._i_age] = (now_ns - produced_ns) // 1000
        self._inputs_seen = values
        self._snapshot.write(produced_ns, fractions, inputs.armed, inputs.armed_heard_ns, values)
        return True

    def _forget_autopilot(self, now_ns: int) -> None:
        """The link was reopened, or the autopilot speaks from a new UDP address: whoever
        answers now starts afresh (disarmed until its own HEARTBEAT says otherwise, its clock
        and its outputs unknown)."""
        self._decoder.reset()
        self._clock.reset()
        if self._inputs.armed:
            self._set_armed(False, now_ns)

    def _set_armed(self, armed: bool, heard_ns: int) -> None:
        inputs = self._inputs
        inputs.armed = armed
        inputs.armed_heard_ns = max(inputs.armed_heard_ns, heard_ns)
        # Each time (a HEARTBEAT a second): the main process judges the arming state's age too.
        self._snapshot.write(
            inputs.input_produced_ns,
            self.fractions,
            armed,
            inputs.armed_heard_ns,
            self._inputs_seen,
        )
