"""MAVLink 2 signing on pymavlink's codec: sign what the link sends, refuse unsigned, badly
signed and replayed input, and build the parsers that share that state.

pymavlink records a signed packet's timestamp as the stream's newest *before* it checks the
signature, so a single forged packet with a far-future timestamp would make every genuine
packet of that (link, system, component) look like a replay from then on. The codec here checks
the signature first, which keeps forged packets from touching the replay state.
"""

from __future__ import annotations

import functools
import hashlib
import hmac
import logging
import time
from collections.abc import Callable
from types import ModuleType
from typing import Any, Final

from bridge.mavlink.stats import Counters, log_sparsely

__all__ = ["SIGNATURE_REJECTED", "codec_class", "new_parser", "setup_signing"]

log = logging.getLogger(__name__)

_SIGNATURE_LEN: Final = 6  # the truncated SHA-256 at the end of a signed MAVLink 2 frame
SIGNATURE_REJECTED: Final = "Invalid signature"
"""How pymavlink's parser (robust mode) reports a message refused by signing: a BAD_DATA whose
reason is this text. Those are counted as ``rejected_unsigned``, not as ``bad_data``."""
# MAVLink signing timestamps count 10 µs units since 2015-01-01T00:00:00Z.
_SIGNING_EPOCH_S: Final = 1_420_070_400
_SIGNING_TICKS_PER_S: Final = 100_000


@functools.cache
def codec_class(dialect: ModuleType) -> Any:
    """The dialect's MAVLink 2 codec, verifying a signature before trusting its timestamp."""

    class Codec(dialect.MAVLink):  # type: ignore[misc, name-defined]  # pymavlink is untyped
        counters: Counters | None = None
        """Where a parser counts refused signatures (set per connection)."""

        def check_signature(self, msgbuf: bytearray, src_system: int, src_component: int) -> bool:
            key: bytes = self.signing.secret_key
            digest = hashlib.sha256(key + bytes(msgbuf[:-_SIGNATURE_LEN])).digest()
            if not hmac.compare_digest(digest[:_SIGNATURE_LEN], bytes(msgbuf[-_SIGNATURE_LEN:])):
                return False
            return bool(super().check_signature(msgbuf, src_system, src_component))

    return Codec


def setup_signing(mav: Any, key: bytes, fallback: Counters) -> None:
    """Make ``mav`` sign what it packs with ``key`` and refuse unsigned input. Every parser made
    by :func:`new_parser` from ``mav`` shares this state, which outlives reconnects (so replay
    protection does too). A refusal is counted in the parser's counters, or in ``fallback``."""
    signing = mav.signing
    signing.secret_key = key
    signing.sign_outgoing = True
    signing.allow_unsigned_callback = _refuse_unsigned(fallback)
    signing.link_id = 0
    # Start at the wall clock: a receiver refuses timestamps older than the newest it saw.
    now_ticks = time.time_ns() * _SIGNING_TICKS_PER_S // 1_000_000_000
    signing.timestamp = max(0, now_ticks - _SIGNING_EPOCH_S * _SIGNING_TICKS_PER_S)


def _refuse_unsigned(fallback: Counters) -> Callable[[Any, int], bool]:
    """pymavlink's allow_unsigned_callback: called for each unsigned or badly signed message
    once a key is set; refusing makes the parser report it as BAD_DATA."""

    def refuse(parser: Any, msg_id: int) -> bool:
        counters: Counters = getattr(parser, "counters", None) or fallback
        counters.rejected_unsigned += 1
        log_sparsely(
            log,
            logging.WARNING,
            counters.rejected_unsigned,
            "refused an unsigned or badly signed MAVLink message (id %d)",
            msg_id,
        )
        return False

    return refuse


def new_parser(dialect: ModuleType, mav: Any, counters: Counters) -> Any:
    """A fresh parser for one connection (no half frame carried over), sharing ``mav``'s
    signing state and counting into ``counters``; robust: malformed input becomes BAD_DATA
    instead of raising."""
    parser = codec_class(dialect)(None, srcSystem=mav.srcSystem, srcComponent=mav.srcComponent)
    parser.robust_parsing = True
    parser.signing = mav.signing
    parser.counters = counters
    return parser
