"""The CKESC family behind :class:`~bridge.escs.family.EscFamily`: its ID space, reader,
filters, driver, bus figures and keys, answered from this folder. Its tools sit beside it: the
simulator (:mod:`bridge.escs.ckesc.sim`), the set-up client and GET_ESC_ID learning
(:mod:`bridge.escs.ckesc.setup`), the set-up commands (:mod:`bridge.escs.ckesc.cli`)."""

from __future__ import annotations

from collections.abc import Collection
from typing import TYPE_CHECKING, Final

from bridge.errors import ConfigError
from bridge.escs import uavcan_v0
from bridge.escs.ckesc import bus
from bridge.escs.ckesc.driver import CkescDriver
from bridge.escs.ckesc.keys import COMMAND_CHANNELS, CkescKeys
from bridge.escs.ckesc.telemetry import CkescDecoder
from bridge.escs.family import BusFigures, EscSetup

if TYPE_CHECKING:
    from can.typechecking import CanFilter

_DECODER: Final = CkescDecoder()


class CkescFamily:
    """CKESC: UAVCAN v0 framing, the vendor's message and service types (docs/protocols.md §3)."""

    name = "ckesc"
    title = "CKESC"
    node_ids = range(1, uavcan_v0.MAX_NODE_ID + 1)
    default_rate_hz = 400
    # CKESC ships at 500 kbit/s (docs/protocols.md §1.2).
    default_bitrate = 500_000
    keys = CkescKeys

    def owns(self, arbitration_id: int) -> bool:
        # Every CKESC message type (20000..20999) and service type (210..242) sets some of
        # bits 28..16; an FT ID never does.
        return arbitration_id >> 16 != 0

    def decoder(self) -> CkescDecoder:
        return _DECODER

    def reader_filters(self, esc_ids: Collection[int]) -> list[CanFilter]:
        return bus.reader_filters(esc_ids)

    def check(self, setup: EscSetup[CkescKeys], rate_hz: int) -> EscSetup[CkescKeys]:
        keys = setup.keys
        channels = keys.ckesc_channels
        most = COMMAND_CHANNELS[keys.ckesc_command]
        if channels and max(channels) > most:
            raise ConfigError(
                f"[escs] ckesc_command {keys.ckesc_command!r} carries channels 1..{most}, but "
                f'the ESCs use channels {list(channels)}; expected ckesc_command = "12b" '
                f"(channels 1..20) or channels within 1..{most}"
            )
        return EscSetup(setup.ids, keys, channels or None)

    def driver(self, setup: EscSetup[CkescKeys]) -> CkescDriver:
        channels = setup.channels or range(1, len(setup.ids) + 1)
        return CkescDriver(setup.keys.ckesc_command, channels, setup.ids)

    def bus_figures(self, setup: EscSetup[CkescKeys], rate_hz: float) -> BusFigures:
        keys = setup.keys
        channels = setup.channels or tuple(range(1, len(setup.ids) + 1))
        return bus.bus_figures(
            len(setup.ids), channels, keys.ckesc_command, keys.ckesc_msg_hz, rate_hz
        )
