"""The CAN receive edge: one named thread drains the bus into the decoders and the ESC state.

The reader knows one ESC family (:class:`~bridge.escs.family.EscFamily`): it decodes each frame
with the family's decoder of its own and hands the neutral telemetry to the state. The bridge's
own commands are not read back for the state: the output loop says what it sent
(:mod:`bridge.daemon.commands_sent`), except while recording (below).

What reaches the reader depends on its handle (:func:`reader_filters`): with a recorder
attached, everything on the bus, including the bridge's own commands (on socketcan and
udp_multicast another handle of the same bus sees them), since the recording wants every
frame; otherwise only our ESCs' telemetry. :class:`~bridge.telemetry.state.EscTable` keeps only
telemetry from our ESCs either way. A malformed frame is counted against the ESC its ID names
and dropped; nothing that arrives stops the reader. Frames the kernel dropped because the reader
fell behind are counted too (:attr:`ReaderStats.kernel_drops`). An error frame (SocketCAN: what
the controller says about the bus) is read by :mod:`bridge.can_errors` into
:attr:`ReaderStats.controller`, the controller's state and fault counts. When its interface is
deleted (a USB adapter unplugged) the reader's socket can never receive again: given
``reopen``, the reader opens the bus again, with a backoff that grows while the interface stays
missing.

With a :class:`StateRecorder` (the MCAP recording), the reader also hands it, for each telemetry
frame, the ESC's state after it, and for each command frame every ESC's last command
(:func:`take_commands`): the recording reads every frame anyway, and so records each command as
it was on the bus, not the loop's newest ten times a second.
"""

from __future__ import annotations

import errno
import logging
import random
import threading
import time
from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import can
from can.typechecking import CanFilter

from bridge.backoff import Backoff
from bridge.can_errors import ControllerErrors, ControllerState, decode_error_frame
from bridge.can_io import receive_drops
from bridge.errors import BridgeError, CodecError
from bridge.escs.family import CommandSeen, EscFamily
from bridge.multicast_receive import MulticastReceiver, receives_multicast
from bridge.telemetry.state import EscSnapshot, EscTable, LastCommand

log = logging.getLogger(__name__)

RECV_TIMEOUT_S = 0.1  # how often the reader notices close()
# Wake-ups coalesced as a network card's interrupts are: after reading what was queued, the
# reader sleeps this long before it waits on the socket again, so a busy bus wakes it at most
# 1 / COALESCE_S times a second, whatever its frame rate. While it sleeps no reader waits on
# the socket, so a sender on the same host (on udp_multicast, the output loop: every handle sees
# every frame) only queues its frames and is not charged a wake-up for each. Telemetry is
# published at 10 Hz by default; its age grows by up to this much.
COALESCE_S = 0.02
DECIDED_IDS = 1024  # filter verdicts kept; past this (a flood of random IDs) they start again
MAX_FRAMES_PER_WAKE = 1000  # then close() and the drop count are looked at again
JOIN_TIMEOUT_S = 2.0
# The drop count costs a system call (and a /proc read on udp_multicast): at most this often.
DROPS_SAMPLE_PERIOD_NS = 1_000_000_000
# First and longest wait between attempts to reopen a bus whose interface is gone.
REOPEN_BACKOFF_S = (0.1, 2.0)
# Read errors that mean the handle's interface is gone: its socket is unbound for good.
GONE_ERRNOS = frozenset({errno.ENODEV, errno.ENXIO})
_BUS_OFF = ControllerState.BUS_OFF

Recorder = Callable[[can.Message], None]
"""Takes every frame read (the candump log)."""


class StateRecorder(Protocol):
    """Takes the ESC state's changes as they happen (the MCAP recording). Called on the thread
    that feeds the ESC state: keep it short (an append)."""

    def esc(self, snapshot: EscSnapshot, time_s: float) -> None:
        """An ESC's state right after a telemetry frame that arrived at ``time_s`` (wall)."""

    def commands(self, commands: Sequence[LastCommand], time_s: float) -> None:
        """Every ESC's last command, right after commands sent at ``time_s`` (wall) were taken."""


def take_commands(
    table: EscTable,
    commands: Sequence[CommandSeen],
    time_s: float,
    recorder: StateRecorder | None = None,
) -> None:
    """Commands into the ESC state and, when they changed, to ``recorder`` (the MCAP's
    ``/bridge/commands``) at ``time_s`` (wall)."""
    if table.note_commands(commands) and recorder is not None:
        recorder.commands(table.last_commands(), time_s)


@dataclass
class ReaderStats:
    """Counters of the CAN reader, updated live."""

    frames: int = 0
    """Every frame read (that the handle's filters let through)."""
    telemetry: int = 0
    """Frames that updated an ESC's state."""
    malformed: int = 0
    """Frames in our family's space that failed to decode (CRC, DLC, tail byte, ...)."""
    read_errors: int = 0
    """Failures of the bus itself while reading."""
    reopens: int = 0
    """Times the reader's own bus was opened again after its interface was gone."""
    controller: ControllerErrors = field(default_factory=ControllerErrors)
    """The controller's state and faults, from its error frames (SocketCAN)."""
    kernel_drops: int | None = None
    """Frames the kernel dropped because the reader's receive queue was full, since its handle
    was opened (the sum over handles, if a shared one was reopened). Sampled once a second,
    so up to a second behind; None while the interface has not told (it may never: see
    :func:`bridge.can_io.receive_drops`)."""


def reader_filters(
    family: EscFamily, esc_ids: Collection[int], *, recording: bool
) -> list[CanFilter] | None:
    """The filters for the reader's own bus handle: None (every frame) when ``recording``,
    since the recording wants every frame; else our ESCs' telemetry only (the bridge's own
    commands come from the output loop: :mod:`bridge.daemon.commands_sent`). See the family's
    :meth:`~bridge.escs.family.EscFamily.reader_filters`.

    Raises:
        ValueRangeError: an ESC ID the protocol cannot have.
    """
    if recording:
        return None
    return family.reader_filters(esc_ids)


class CanReader:
    """Reads a bus in a thread of its own and feeds ``table``; :meth:`close` stops it.

    ``bus`` is the bus, or a function returning the bus to read now (None: none at the moment),
    for an interface only one handle can open: the output loop's thread then owns the handle,
    reopens it when it fails, and the reader reads whichever handle is current.

    The reader reads whatever its handle lets through; whoever opens the handle chooses that
    (:func:`reader_filters`, used by :class:`~bridge.telemetry.fanout.Fanout`). On socketcan the
    kernel filters, so a flood of other traffic costs the reader nothing. On interfaces without
    kernel filtering (udp_multicast, virtual) the reader is given the filters and applies them
    itself: the frames they refuse never reach the recorder, the decoders or :attr:`stats`,
    but the reader still reads each one (on udp_multicast without unpacking it:
    :mod:`bridge.multicast_receive`), so a flood still costs it CPU, and when it cannot keep
    up the kernel drops frames (telemetry among them) and counts them in
    :attr:`ReaderStats.kernel_drops`.
    """

    def __init__(
        self,
        bus: can.BusABC | Callable[[], can.BusABC | None],
        table: EscTable,
        family: EscFamily,
        recorder: Recorder | None = None,
        states: StateRecorder | None = None,
        reopen: Callable[[], object] | None = None,
        filters: Sequence[CanFilter] | None = None,
    ) -> None:
        """``recorder`` takes every frame read, ``states`` the ESC state's changes;
        ``reopen`` opens the bus again (``bus`` then gives the new handle) after its interface
        was gone, and raises :class:`~bridge.errors.BridgeError` while it cannot. ``filters``:
        the reader drops what none of them passes, as python-can's own would (for a handle
        without kernel filters, whose ``recv(0)`` could not tell a refused frame from an empty
        queue: :data:`~bridge.can_io.KERNEL_FILTERING_INTERFACES`)."""
        self._bus_source = bus if callable(bus) else lambda: bus
        self._filters = (
            None
            if filters is None
            else tuple((f["can_id"], f["can_mask"], f.get("extended")) for f in filters)
        )
        # The filters' verdict by ID (bit 29: extended). A bus repeats a few IDs (the bridge's
        # own commands, 800 a second on an 8-ESC CKESC bus, read back where the kernel does not
        # filter), and a family's filters are many (16 for CKESC): working their verdict out for
        # each frame was a quarter of the reader's CPU (bench/cpu.py --profile).
        self._decided: dict[int, bool] = {}
        self._reopen = reopen
        self._table = table
        self._decoder = family.decoder()
        self._recorder = recorder
        self._states = states
        self.stats = ReaderStats()
        # Drops of handles the reader read before the current one (a reopened shared handle
        # starts counting from 0 again), and the current handle's last count.
        self._drops_bus: can.BusABC | None = None
        self._drops_before = 0
        self._drops_current = 0
        self._multicast: MulticastReceiver | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="can-reader", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def close(self) -> None:
        """Stop the thread (the bus stays open: whoever opened it shuts it down)."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(JOIN_TIMEOUT_S)

    def _run(self) -> None:
        try:
            self._read_until_closed()
        finally:
            if self._multicast is not None:
                self._multicast.close()

    def _read_until_closed(self) -> None:
        failures = 0
        next_sample_ns = 0
        while not self._stop.is_set():
            bus = self._bus_source()
            if bus is None:
                self._stop.wait(RECV_TIMEOUT_S)
                continue
            try:
                recv = self._recv_of(bus)
                dropped_before = self._dropped()
                msg = recv(RECV_TIMEOUT_S)
            except (can.CanError, OSError) as exc:
                self.stats.read_errors += 1
                failures += 1
                if failures == 1 or failures % 100 == 0:
                    log.warning("CAN read failed (%d in all): %s", self.stats.read_errors, exc)
                code = getattr(exc, "error_code", None) or getattr(exc, "errno", None)
                if code in GONE_ERRNOS and self._reopen is not None:
                    self._reopen_until_open()
                else:
                    self._stop.wait(RECV_TIMEOUT_S)  # a bus that is gone must not spin the CPU
                continue
            failures = 0
            now_ns = time.monotonic_ns()
            # A multicast receiver's read of refused frames only may have emptied the queue.
            emptied = msg is None and self._dropped() != dropped_before and self._drained()
            if msg is not None:
                self.handle(msg, now_ns)
                emptied = self._drain(recv)
            if now_ns >= next_sample_ns:
                next_sample_ns = now_ns + DROPS_SAMPLE_PERIOD_NS
                self._sample_drops(bus)
            if emptied:
                self._stop.wait(COALESCE_S)

    def _recv_of(self, bus: can.BusABC) -> Callable[[float | None], can.Message | None]:
        """What reads ``bus``: its own ``recv``, or where the reader filters a ``udp_multicast``
        handle itself, a :class:`~bridge.multicast_receive.MulticastReceiver` that drops the
        frames the filters refuse before unpacking them (the bridge's own commands).

        Raises:
            OSError: the handle was shut down.
        """
        if self._filters is None or not receives_multicast(bus):
            return bus.recv
        receiver = self._multicast
        if receiver is None or receiver.bus is not bus:
            if receiver is not None:
                receiver.close()
            receiver = self._multicast = MulticastReceiver(bus, self._wanted)
        return receiver.recv

    def _dropped(self) -> int:
        """Frames the multicast receiver read and dropped (0 without one)."""
        return 0 if self._multicast is None else self._multicast.dropped

    def _drained(self) -> bool:
        """Whether a read that found nothing emptied the queue: python-can's ``recv`` says
        nothing more; a multicast receiver tells an empty queue from a flood's many drops."""
        return self._multicast is None or self._multicast.drained

    def _drain(self, recv: Callable[[float | None], can.Message | None]) -> bool:
        """Handle what else is queued, without waiting; True when the queue was emptied (a
        read error is left to the next wait)."""
        handle = self.handle
        for _ in range(MAX_FRAMES_PER_WAKE):
            try:
                msg = recv(0)
            except (can.CanError, OSError):
                return False
            if msg is None:
                return self._drained()
            handle(msg, time.monotonic_ns())
        return False

    def _reopen_until_open(self) -> None:
        """Open the bus again, waiting longer between attempts while it cannot be (the
        interface is still missing), until it opens or the reader is closed."""
        assert self._reopen is not None
        backoff = Backoff(*REOPEN_BACKOFF_S)
        while not self._stop.wait(backoff.wait_s(random.random())):
            try:
                self._reopen()
            except BridgeError:
                continue
            self.stats.reopens += 1
            log.info("CAN reader: bus open again (%d reopens)", self.stats.reopens)
            return

    def _sample_drops(self, bus: can.BusABC) -> None:
        if bus is not self._drops_bus:
            # A new handle (the shared one was reopened): keep what the old one counted.
            self._drops_before += self._drops_current
            self._drops_bus, self._drops_current = bus, 0
        drops = receive_drops(bus)
        if drops is not None:
            self._drops_current = drops
            self.stats.kernel_drops = self._drops_before + drops

    def _passes(self, msg: can.Message) -> bool:
        """Whether one of the reader's filters passes ``msg`` (python-can's rule; error frames
        are the controller's, never filtered here)."""
        if msg.is_error_frame or self._filters is None:
            return True
        return self._wanted(msg.arbitration_id, msg.is_extended_id)

    def _wanted(self, can_id: int, extended: bool) -> bool:
        """Whether one of the reader's filters passes a frame of ``can_id`` (given filters)."""
        key = can_id | extended << 29
        passed = self._decided.get(key)
        if passed is None:
            passed = any(
                (want is None or want == extended) and (can_id ^ wanted_id) & mask == 0
                for wanted_id, mask, want in self._filters or ()
            )
            if len(self._decided) >= DECIDED_IDS:
                self._decided.clear()
            self._decided[key] = passed
        return passed

    def handle(self, msg: can.Message, now_ns: int) -> None:
        """Record, decode and apply one frame (the reader thread calls this for each)."""
        if self._filters is not None and not self._passes(msg):
            return
        stats = self.stats
        stats.frames += 1
        if self._recorder is not None:
            self._recorder(msg)
        if msg.is_error_frame:
            stats.controller.note(decode_error_frame(msg.arbitration_id, msg.data))
            return
        if stats.controller.state == _BUS_OFF:
            stats.controller.note_frame_received()
        decoder = self._decoder
        try:
            frame = decoder.decode(msg, self._table.node_set)
        except CodecError:
            stats.malformed += 1
            self._table.count_error(decoder.node_of(msg), now_ns)
            return
        if frame is None:
            return
        telemetry = decoder.telemetry(frame)
        states = self._states
        if telemetry is not None and self._table.ingest(telemetry, now_ns):
            stats.telemetry += 1
            if states is not None:
                snapshot = self._table.snapshot_of(telemetry.node_id, now_ns)
                if snapshot is not None:
                    states.esc(snapshot, msg.timestamp or time.time())
        elif states is not None:
            commands = decoder.commands_seen(frame)
            if commands:
                take_commands(self._table, commands, msg.timestamp or time.time(), states)
