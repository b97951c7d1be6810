"""ESC protocol codecs: pure functions on ``can.Message``, one module per vendor protocol.

The two protocols' CAN ID spaces do not overlap: an FT ID has bits 28..16 clear (ESC ID and
command in the low 16 bits), while every CKESC message type (20000..20999) and service type
(210..242) sets some of them. :func:`protocol_of` uses that to tell them apart on a mixed bus.
"""

from __future__ import annotations

from collections.abc import Container
from typing import Literal

import can

from bridge.escs import ckesc, ft

Protocol = Literal["ckesc", "ft"]
PROTOCOLS: tuple[Protocol, ...] = ("ckesc", "ft")

AnyFrame = ckesc.CkescFrame | ft.FtFrame


def protocol_of(msg: can.Message) -> Protocol:
    """The protocol whose ID space holds this frame's ID (it may still be neither's)."""
    return "ft" if msg.arbitration_id >> 16 == 0 else "ckesc"


def decode(
    msg: can.Message,
    protocol: Protocol | Literal["auto"] = "auto",
    esc_nodes: Container[int] | None = None,
) -> AnyFrame | None:
    """Decode one frame of ``protocol`` (or of whichever protocol its ID belongs to).

    ``esc_nodes`` (CKESC node IDs of our ESCs) keeps other vendors' DroneCAN frames that reuse
    CKESC type IDs out; see :func:`bridge.escs.ckesc.decode`.

    Returns:
        The decoded frame, or ``None`` when the frame belongs to no protocol we speak.

    Raises:
        bridge.errors.FrameError: the frame is in the protocol's space but malformed.
    """
    if protocol == "auto":
        protocol = protocol_of(msg)
    if protocol == "ckesc":
        return ckesc.decode(msg, esc_nodes)
    return ft.decode(msg)


__all__ = ["PROTOCOLS", "AnyFrame", "Protocol", "ckesc", "decode", "ft", "protocol_of"]
