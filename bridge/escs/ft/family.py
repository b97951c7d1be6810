"""The Flipsky FT family behind :class:`~bridge.escs.family.EscFamily`: its ID space, reader,
filters, driver, bus figures and keys, answered from this folder. Its simulator is
:mod:`bridge.escs.ft.sim`; FT has no set-up commands and no ID discovery."""

from __future__ import annotations

import math
from collections.abc import Collection
from typing import TYPE_CHECKING, Final

from bridge.errors import ConfigError
from bridge.escs.family import BusFigures, EscSetup
from bridge.escs.ft import bus, records
from bridge.escs.ft.driver import FtDriver
from bridge.escs.ft.keys import FtKeys
from bridge.escs.ft.telemetry import FtDecoder

if TYPE_CHECKING:
    from can.typechecking import CanFilter

COMMAND_TIMEOUT_MS: Final = 450
"""The ESC drops a command not repeated within this (docs/protocols.md §4.4)."""
MIN_REFRESHES_PER_TIMEOUT: Final = 4
"""A command must reach each ESC at least this many times within its timeout, so that a few
lost frames or a stalled cycle never let the ESC time out mid-flight."""

_DECODER: Final = FtDecoder()


class FtFamily:
    """Flipsky FT: ``id = esc_id << 8 | command``, 16 commands, three telemetry frames."""

    name = "ft"
    title = "FT"
    node_ids = range(records.ESC_ID_MIN, records.ESC_ID_MAX + 1)
    default_rate_hz = 100
    # FT has no factory rate; VESC firmware uses 500k.
    default_bitrate = 500_000
    keys = FtKeys

    def owns(self, arbitration_id: int) -> bool:
        return arbitration_id >> 16 == 0  # bits 28..16 are clear in every FT ID

    def decoder(self) -> FtDecoder:
        return _DECODER

    def reader_filters(self, esc_ids: Collection[int]) -> list[CanFilter]:
        return bus.reader_filters(esc_ids)

    def check(self, setup: EscSetup[FtKeys], rate_hz: int) -> EscSetup[FtKeys]:
        period_ms = 1000 / rate_hz
        if period_ms * MIN_REFRESHES_PER_TIMEOUT > COMMAND_TIMEOUT_MS:
            slowest = math.ceil(1000 * MIN_REFRESHES_PER_TIMEOUT / COMMAND_TIMEOUT_MS)
            raise ConfigError(
                f"[output] rate_hz: {rate_hz} Hz refreshes each FT ESC every {period_ms:.0f} ms; "
                f"the ESC drops a command after {COMMAND_TIMEOUT_MS} ms, so expected at least "
                f"{slowest} Hz ({MIN_REFRESHES_PER_TIMEOUT} refreshes within the timeout)"
            )
        return setup

    def driver(self, setup: EscSetup[FtKeys]) -> FtDriver:
        return FtDriver(setup.ids, setup.keys)

    def bus_figures(self, setup: EscSetup[FtKeys], rate_hz: float) -> BusFigures:
        keys = setup.keys
        return bus.bus_figures(len(setup.ids), keys.ft_crc, keys.ft_telemetry_hz, rate_hz)
