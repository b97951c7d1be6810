"""ESC telemetry fan-out: CAN in -> decoders -> ESC state -> MAVLink and Zenoh publishers.

Everything here runs in the main process, in threads of its own, and never touches the output
loop: the loop is in another process (or, with an interface only one handle can open, shares
its bus handle with the reader here and nothing else). A publisher that stalls (a slow Zenoh
peer, a dead GCS link) delays only itself.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import can
from can.typechecking import CanFilter

from bridge.can_io import (
    KERNEL_FILTERING_INTERFACES,
    apply_filters,
    enlarge_receive_buffer,
    open_bus,
)
from bridge.config import BridgeConfig
from bridge.errors import ValueRangeError
from bridge.escs import registry
from bridge.escs.family import EscSetup
from bridge.mavlink.link import MavlinkLink
from bridge.mavlink.telemetry_out import MavlinkTelemetry
from bridge.telemetry.payload import (
    ActuatorsInputPayload,
    ActuatorsOutputPayload,
    CanRxHealth,
    HealthPayload,
    ZenohHealth,
)
from bridge.telemetry.reader import CanReader, Recorder, StateRecorder, reader_filters
from bridge.telemetry.state import EscTable
from bridge.telemetry.zenoh_out import TelemetrySources, ZenohOut

log = logging.getLogger(__name__)

LearnNodeIds = Callable[[can.BusABC, EscSetup[Any]], dict[int, int]]
"""A family's ``setup.learn_node_ids`` (see :mod:`bridge.escs.family`)."""

# The reader's socket buffer: ~0.8 s of a saturated 1 Mbit/s bus at ~800 B per queued frame (the
# kernel caps it at net.core.rmem_max; raise that to use all of it).
RECEIVE_BUFFER_BYTES = 4 * 1024 * 1024


class Fanout:
    """The CAN reader and the publishers, started after the output loop, closed before exit."""

    def __init__(
        self,
        config: BridgeConfig,
        table: EscTable,
        link: MavlinkLink,
        *,
        health: Callable[[], HealthPayload],
        actuators_input: Callable[[], ActuatorsInputPayload | None],
        actuators_output: Callable[[], ActuatorsOutputPayload | None],
        shared_bus: Callable[[], can.BusABC | None] | None = None,
        recorder: Recorder | None = None,
        states: StateRecorder | None = None,
    ) -> None:
        """``shared_bus``: read the output loop's handle instead of opening one of our own.

        Our own handle receives only our ESCs' telemetry
        (:func:`~bridge.telemetry.reader.reader_filters`), unless ``recorder`` is given (the
        recording wants every frame). A shared handle belongs to the output loop and is read as it
        was opened.
        """
        self._config = config
        self._family = registry.family(config.output.protocol)
        self.table = table
        self._shared_bus = shared_bus
        self._recorder = recorder
        self._states = states
        self._own_bus: can.BusABC | None = None
        self._kernel_filters = config.can.interface in KERNEL_FILTERING_INTERFACES
        self.reader: CanReader | None = None
        self.mavlink = MavlinkTelemetry(config.mavlink, link, table)
        self.zenoh: ZenohOut | None = None
        if config.zenoh.enabled:
            sources = TelemetrySources(table, health, actuators_input, actuators_output)
            self.zenoh = ZenohOut(config.zenoh, sources)

    def start(self) -> None:
        """Open the reader's bus, learn the ESCs' node IDs if asked (and the family can), start
        every thread.

        Raises:
            LinkError: the bus cannot be opened, or the ESCs' answers are inconsistent.
        """
        config = self._config
        # The family's ID learning, if it has any (its set-up tools, imported only to learn).
        learning = (
            registry.tool(config.output.protocol, "setup") if config.telemetry.learn_ids else None
        )
        learn_node_ids: LearnNodeIds | None = getattr(learning, "learn_node_ids", None)
        learn = learn_node_ids is not None
        filters = self._filters()
        reopen = None
        if self._shared_bus is None:
            # The ESCs' answers are not telemetry: learn on an unfiltered handle, then filter by
            # the node IDs learnt.
            self._open_own_bus(None if learn else filters)
            bus: Any = self._current_own_bus  # the current handle, after a reopen too
            reopen = self._reopen_own_bus
        else:
            bus = self._shared_bus
        if learn_node_ids is not None:
            self._learn_ids(
                learn_node_ids, self._own_bus if self._shared_bus is None else self._shared_bus()
            )
            filters = self._filters()
            if self._own_bus is not None and filters and self._kernel_filters:
                apply_filters(self._own_bus, filters)
        if self._own_bus is not None:
            log.debug(
                "CAN reader receives %s",
                "every frame" if filters is None else f"what {len(filters)} filters pass",
            )
        self.reader = CanReader(
            bus,
            self.table,
            self._family,
            self._recorder,
            self._states,
            reopen=reopen,
            filters=None if self._own_bus is None or self._kernel_filters else filters,
        )
        self.reader.start()
        self.mavlink.start()
        if self.zenoh is not None:
            self.zenoh.start()

    def _open_own_bus(self, filters: list[CanFilter] | None, explain: bool = True) -> None:
        """Open the reader's own handle: every frame, or what ``filters`` pass.

        Raises:
            LinkError: the bus cannot be opened.
        """
        config = self._config
        if filters is None or (filters and not self._kernel_filters):
            # Without kernel filters the reader filters itself (CanReader's ``filters``).
            self._own_bus = open_bus(config.can, config.bitrate, explain=explain)
        else:
            self._own_bus = open_bus(
                config.can, config.bitrate, receive="telemetry", filters=filters, explain=explain
            )
        granted = enlarge_receive_buffer(self._own_bus, RECEIVE_BUFFER_BYTES)
        if granted is not None:
            log.debug("CAN reader receive buffer: %d bytes", granted)

    def _current_own_bus(self) -> can.BusABC | None:
        return self._own_bus

    def _reopen_own_bus(self) -> None:
        """The reader's handle again, after its interface was gone (from the reader's thread).

        Raises:
            LinkError: the bus cannot be opened (yet).
        """
        old, self._own_bus = self._own_bus, None
        if old is not None:
            old.shutdown()
        # No `ip` run per attempt: the interface is known to be missing.
        self._open_own_bus(self._filters(), explain=False)

    def _filters(self) -> list[CanFilter] | None:
        try:
            return reader_filters(
                self._family,
                self.table.node_ids,
                recording=self._recorder is not None,
            )
        except ValueRangeError as exc:  # a node ID learnt from an ESC that no filter can name
            log.warning("CAN reader receives every frame: %s", exc)
            return None

    def _learn_ids(self, learn_node_ids: LearnNodeIds, bus: can.BusABC | None) -> None:
        title = self._family.title
        if bus is None:
            log.warning("cannot learn %s node IDs: the bus is not open", title)
            return
        found = learn_node_ids(bus, self._config.esc_setup)
        configured = self.table.node_ids
        ids = [found.get(i, node) for i, node in enumerate(configured)]
        missing = [i + 1 for i in range(len(configured)) if i not in found]
        if len(set(ids)) != len(ids):
            log.warning(
                "%s node IDs learnt by motor %s clash with the configured IDs; keeping [escs] "
                "ids %s",
                title,
                {i + 1: node for i, node in found.items()},
                list(configured),
            )
            return
        self.table.remap(ids)
        log.info(
            "%s node IDs by motor (asked on the bus): %s%s",
            title,
            ids,
            f"; motors {missing} did not answer, configured IDs kept" if missing else "",
        )

    def close(self) -> None:
        """Stop the publishers and the reader; close our bus handle."""
        if self.zenoh is not None:
            self.zenoh.close()
        self.mavlink.close()
        if self.reader is not None:
            self.reader.close()
        if self._own_bus is not None:
            self._own_bus.shutdown()
            self._own_bus = None

    def can_rx(self) -> CanRxHealth:
        """The reader's counters, for the bridge's health."""
        reader = self.reader.stats if self.reader is not None else None
        return CanRxHealth(
            frames=reader.frames if reader else 0,
            telemetry=reader.telemetry if reader else 0,
            malformed=reader.malformed if reader else 0,
            read_errors=reader.read_errors if reader else 0,
            kernel_drops=reader.kernel_drops if reader else None,
            unknown_esc_frames=self.table.unknown_frames,
        )

    def zenoh_health(self) -> ZenohHealth | None:
        """Zenoh's counters, for the bridge's health; None when Zenoh is off."""
        if self.zenoh is None:
            return None
        stats = self.zenoh.stats
        return ZenohHealth(
            session_up=stats.session_up, published=stats.published, dropped=stats.dropped
        )
