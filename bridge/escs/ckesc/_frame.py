"""The CKESC frame envelope and the frame type table that the codec modules fill in."""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Final, TypeAlias, TypeVar

from bridge.escs.ckesc._records import (
    CkescMessage,
)
from bridge.escs.ckesc._wire import (
    _Allowed,
    _Buf,
    _field,
)
from bridge.escs.uavcan_v0 import PRIORITY_HIGHEST, PRIORITY_LOW, PRIORITY_LOWEST, PRIORITY_MEDIUM


@dataclass(frozen=True, slots=True)
class CkescFrame:
    """One CKESC frame: the CAN ID's fields around a payload record.

    ``destination_node`` is ``None`` for message (broadcast) frames; ``transfer_id`` is
    ``None`` for RawCommand_10b (no tail byte) and MSG_EXP12 (whose tail holds the record kind).
    """

    priority: int
    source_node: int
    destination_node: int | None
    transfer_id: int | None
    message: CkescMessage

    @property
    def node_id(self) -> int:
        """The ESC this frame is from or to: a request's destination, else the source."""
        if self.destination_node is not None and _CODECS_BY_RECORD[type(self.message)].from_host:
            return self.destination_node
        return self.source_node


# --------------------------------------------------------------------------------------------
# The frame type table (docs/protocols.md §3.2, §3.6) and each type's payload layout, type by
# type. An ``unpack`` takes the whole CAN data (its length already checked) and returns the record;
# a ``pack`` checks the record and returns the payload before the tail byte (the whole data for
# the two types without a transfer ID). The registration rows are left unformatted so that each
# reads as a table row: record, type ID, sender, DLC (tail byte included), priority, codec.

_R = TypeVar("_R")
_Unpack: TypeAlias = Callable[[_Buf], CkescMessage]
_Pack: TypeAlias = Callable[[Any], bytes]


@dataclass(frozen=True, slots=True)
class _Codec:
    name: str
    """For error messages: the record and its type ID, e.g. "Msg1 (20050)"."""
    type_id: int
    service: bool
    from_host: bool
    """Message frame: sent by the host (RawCommand, requests). Service frame: a request."""
    dlc: int
    priority: int
    """The seed's priority for the type."""
    unpack: _Unpack
    pack: _Pack
    has_transfer_id: bool
    """False: no transfer ID in the tail byte, and ``pack`` returns the whole data."""


_CODECS_BY_RECORD: Final[dict[type, _Codec]] = {}
# Keyed by plain ints so that a look-up allocates nothing. Messages: ``type_id << 1 | (source
# != host)``; a type sent one way only answers both keys, a type sent both ways has a record
# per direction. Services: ``service_type << 1 | is_request``.
_MESSAGE_CODECS: Final[dict[int, _Codec]] = {}
_SERVICE_CODECS: Final[dict[int, _Codec]] = {}

_HOST, _ESC = True, False
_REQUEST, _RESPONSE = True, False
_HIGHEST, _MEDIUM, _LOW, _LOWEST = PRIORITY_HIGHEST, PRIORITY_MEDIUM, PRIORITY_LOW, PRIORITY_LOWEST


def _message(
    record: type[CkescMessage],
    type_id: int,
    from_host: bool,
    dlc: int,
    priority: int,
    unpack: _Unpack,
    pack: _Pack,
    has_transfer_id: bool = True,
) -> None:
    name = f"{record.__name__} ({type_id})"
    codec = _Codec(name, type_id, False, from_host, dlc, priority, unpack, pack, has_transfer_id)
    _CODECS_BY_RECORD[record] = codec
    _MESSAGE_CODECS[type_id << 1 | (not from_host)] = codec
    _MESSAGE_CODECS.setdefault(type_id << 1 | from_host, codec)


def _service(
    record: type[CkescMessage],
    service_type: int,
    request: bool,
    dlc: int,
    priority: int,
    unpack: _Unpack,
    pack: _Pack,
) -> None:
    name = f"{record.__name__} ({service_type})"
    codec = _Codec(name, service_type, True, request, dlc, priority, unpack, pack, True)
    _CODECS_BY_RECORD[record] = codec
    _SERVICE_CODECS.setdefault(service_type << 1 | request, codec)


def _plain(
    record: Callable[..., _R], fmt: str, **fields: _Allowed
) -> tuple[Callable[[_Buf], _R], _Pack]:
    """Codec for a record of int fields in wire order; ``fields`` gives each one's range."""
    layout = struct.Struct(fmt)
    checks = tuple(fields.items())

    def unpack(data: _Buf) -> _R:
        return record(*layout.unpack_from(data))

    def pack(message: Any) -> bytes:
        return layout.pack(*[_field(message, name, allowed) for name, allowed in checks])

    return unpack, pack
