"""The VESC family behind :class:`~bridge.escs.family.EscFamily`: what the bridge's core asks of
VESCs, answered from this folder (codec, decoder and telemetry mapping, driver, bus figures,
keys). Its tools sit beside it: ``sim.py`` (simulated VESCs), ``cli.py`` (``esc-bridge esc
vesc-scan``) and ``setup.py`` (the PING scan)."""

from __future__ import annotations

import math
from collections.abc import Collection
from typing import TYPE_CHECKING, Final

from bridge.errors import ConfigError
from bridge.escs.family import BusFigures, EscSetup
from bridge.escs.vesc import bus
from bridge.escs.vesc.driver import VescDriver
from bridge.escs.vesc.keys import VescKeys
from bridge.escs.vesc.records import VESC_ID_MAX
from bridge.escs.vesc.telemetry import VescDecoder

if TYPE_CHECKING:
    from can.typechecking import CanFilter

NAME: Final = "vesc"
MIN_REFRESHES_PER_TIMEOUT: Final = 4
"""A command must reach each VESC at least this many times within its timeout, so that a few
lost frames or a stalled cycle never let it time out mid-flight."""

_DECODER: Final = VescDecoder()  # stateless: one serves every stream


class VescFamily:
    """VESC: ``id = packet << 8 | controller_id``, five motor commands, six status frames."""

    name = NAME
    title = "VESC"
    node_ids = bus.ESC_IDS
    # 200 commands per VESC per second and STATUS 1-5 at 50 Hz keep a quad at 51 % of 500 kbit/s
    # (docs/escs.md); the VESCs' 1 s timeout needs far less.
    default_rate_hz = 200
    default_bitrate = 500_000  # the firmware's default (APPCONF_CAN_BAUD_RATE)
    keys = VescKeys

    def owns(self, arbitration_id: int) -> bool:
        return 0 <= arbitration_id <= VESC_ID_MAX  # bits 28..16 are clear in every VESC ID

    def decoder(self) -> VescDecoder:
        return _DECODER

    def reader_filters(self, esc_ids: Collection[int]) -> list[CanFilter]:
        return bus.reader_filters(esc_ids)

    def check(self, setup: EscSetup[VescKeys], rate_hz: int) -> EscSetup[VescKeys]:
        period_ms = 1000 / rate_hz
        timeout_ms = setup.keys.vesc_timeout_ms
        if period_ms * MIN_REFRESHES_PER_TIMEOUT > timeout_ms:
            slowest = math.ceil(1000 * MIN_REFRESHES_PER_TIMEOUT / timeout_ms)
            raise ConfigError(
                f"[output] rate_hz: {rate_hz} Hz refreshes each VESC every {period_ms:.0f} ms; "
                f"the VESCs release the motor after {timeout_ms} ms without a command ([escs] "
                f"vesc_timeout_ms), so expected at least {slowest} Hz "
                f"({MIN_REFRESHES_PER_TIMEOUT} refreshes within the timeout)"
            )
        return setup

    def driver(self, setup: EscSetup[VescKeys]) -> VescDriver:
        return VescDriver(setup.ids, setup.keys)

    def bus_figures(self, setup: EscSetup[VescKeys], rate_hz: float) -> BusFigures:
        return bus.bus_figures(len(setup.ids), setup.keys.vesc_status_hz, rate_hz)
