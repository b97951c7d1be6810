"""The CKESC family: UAVCAN v0 framing carrying the vendor's own message and service types.

This package re-exports its codec's public names (``from bridge.escs import ckesc``); the
family behind :class:`~bridge.escs.family.EscFamily` is :mod:`bridge.escs.ckesc.family`.

The reference is ``docs/protocols.md`` §3 (the project's reading of the vendor's "CKESC UAVCAN
Protocol 2.1"); section numbers "seed 4.4.x" below point into the vendor document, and the
tables of §3.2 and §3.6 give each type's vendor section. The codec
(``_wire``, ``_records``, ``_frame``, ``_messages``, ``_services``, ``_codec``) is pure: it imports
only the standard library and ``can`` (for :class:`can.Message`), and has no I/O, clock or
logging.

Wire format in one paragraph: 29-bit data frames only. A message (broadcast) frame's ID is
priority (5 bits) · type ID (16) · 0 · source node (7); a service frame's ID is priority ·
service type (8) · request flag · destination node (7) · 1 · source node. All multi-byte fields
are little-endian. Every frame but RawCommand_10b ends in a tail byte ``0xC0 | transfer_id``
(single-frame transfer); MSG_EXP12 uses its tail byte's transfer ID for a record kind. That
framing is UAVCAN v0's, shared with DroneCAN in :mod:`bridge.escs.uavcan_v0`: the ID helpers
``message_id``, ``service_id``, ``parse_id`` (→ ``CanId``), ``tail_byte``, ``TransferIds``
(one 0..31 counter per type ID), ``MAX_NODE_ID`` and the ``PRIORITY_*`` levels are there, not
here.

Public API:

- One frozen record class per payload (:data:`CkescMessage` is their union), wrapped in a
  :class:`CkescFrame` envelope; :func:`decode` and :func:`encode` convert envelopes.
- Throttle hot path: :func:`encode_raw_12b`, :func:`encode_raw_14b`, :func:`encode_raw_10b`
  and :func:`raw_12b_groups`.

Decisions where the seed is silent or ambiguous (each also noted where it is coded):

- Three message types go both ways (CANTest, MSGControl, GET_ESC_ID). A frame from the host
  (source node 0) is the host's request; from any other node it is the ESC's answer. So
  :func:`encode` requires source 0 for those requests and a non-zero source for the answers.
- Maintenance Information (241) responses do not say which option they answer; the seed shows
  the option in byte 6 only for option 2. We read byte 6 as the option for all three and write
  it so (the only way a response can be decoded without remembering the request); a byte 6
  outside 0..2 raises :class:`~bridge.errors.FrameError`. Needs checking on hardware.
- Expand Set (222) has no response (the motor beeps), so a 222 response frame, like Get/Clear
  temperature record (223/224, payloads unspecified), raises ``UnknownTypeError``.
- Reserved bytes and nibbles are ignored on decode and sent as zero. Option bytes the seed fixes
  at 0 are still fields (default 0) so that a frame decodes and re-encodes unchanged.
- Report intervals are in milliseconds (the wire counts 2 ms units): writes accept 20..500 ms
  in steps of 2, reads and reports any byte (0..510 ms).
- ``MajorConfigResponse.led_blink_hz``: the seed calls bits 7..3 "LED blink state"; we take it
  to be the Set LED blink setting (0 off, 1/2/5 Hz) and keep whatever value arrives.
- ``EscInfoResponse.firmware_year`` is the byte as sent (the seed does not give its epoch).
- Values that arrive outside their documented range (a throttle of 3000, group 6) decode as
  sent: decoding reports what is on the bus; only :func:`encode` refuses such values.
- Node IDs for encoding are 0..0x7D (0x7E and 0x7F are reserved, seed 4.1.2), also for the
  Set ID destination, which the ESC ignores.
- ``esc_nodes`` (see :func:`decode`) filters services as well as messages: vendor service IDs
  200..255 are as shared as vendor message IDs. A service frame is ours if its host side is
  node 0 and its ESC side is in ``esc_nodes``; Set ID is exempt from the second test, since its
  destination is ignored and the answering ESC's ID is the one being set.
- Flag bytes become ``bool``: Set LED ``save`` and Set/Get Freq ``write`` are true for any
  non-zero byte, Self Test ``passed`` only for status 0 (the seed defines 0 pass, 1 fail).
- The throttle encoders take 1..n values and send the missing channels as 0 (stopped): the only
  value that is safe for an ESC that happens to follow one of them.
"""

from __future__ import annotations

from bridge.escs.ckesc._codec import (
    decode,
    default_priority,
    encode,
    encode_raw_10b,
    encode_raw_12b,
    encode_raw_14b,
    raw_12b_groups,
    type_id_of,
)
from bridge.escs.ckesc._frame import (
    CkescFrame,
)
from bridge.escs.ckesc._records import (
    CanTestReport,
    CanTestRequest,
    CkescMessage,
    EscInfoRequest,
    EscInfoResponse,
    ExpandSetRequest,
    GetEscIdAnswer,
    GetEscIdRequest,
    Maintenance0Response,
    Maintenance1Response,
    Maintenance2Response,
    MaintenanceRequest,
    MajorConfigRequest,
    MajorConfigResponse,
    Msg1,
    Msg2,
    Msg3,
    MsgControlAck,
    MsgControlRequest,
    MsgExp1,
    MsgExp2,
    MsgExp3,
    MsgExp4,
    MsgExp5,
    MsgExp6,
    MsgExp7,
    MsgExp8,
    MsgExp9,
    MsgExp10,
    MsgExp11,
    MsgExp12,
    RawCommand10b,
    RawCommand12b,
    RawCommand14b,
    SelfTestRequest,
    SelfTestResponse,
    SetBaudRequest,
    SetBaudResponse,
    SetFreqRequest,
    SetFreqResponse,
    SetIdRequest,
    SetIdResponse,
    SetLedRequest,
    SetLedResponse,
    SetRotationRequest,
    SetRotationResponse,
    ThrottleSelectRequest,
    ThrottleSelectResponse,
)
from bridge.escs.ckesc._wire import (
    BAUD_RATES_BPS,
    CHANNELS_PER_GROUP,
    FACTORY_NODE_ID,
    HOST_NODE_ID,
    MAX_CHANNELS,
    MAX_GROUP,
    MESSAGE_TYPE_RANGE,
    SERVICE_CLEAR_TEMP_RECORD,
    SERVICE_ESC_INFO,
    SERVICE_EXPAND_SET,
    SERVICE_GET_TEMP_RECORD,
    SERVICE_MAINTENANCE,
    SERVICE_MAJOR_CONFIG,
    SERVICE_SELF_TEST,
    SERVICE_SET_BAUD,
    SERVICE_SET_FREQ,
    SERVICE_SET_ID,
    SERVICE_SET_LED,
    SERVICE_SET_ROTATION,
    SERVICE_THROTTLE_SELECT,
    SERVICE_TYPE_RANGE,
    THROTTLE_10B_MAX,
    THROTTLE_MAX,
    TYPE_CAN_TEST,
    TYPE_GET_ESC_ID,
    TYPE_MSG1,
    TYPE_MSG2,
    TYPE_MSG3,
    TYPE_MSG_CONTROL,
    TYPE_MSG_EXP1,
    TYPE_MSG_EXP2,
    TYPE_MSG_EXP3,
    TYPE_MSG_EXP4,
    TYPE_MSG_EXP5,
    TYPE_MSG_EXP6,
    TYPE_MSG_EXP7,
    TYPE_MSG_EXP8,
    TYPE_MSG_EXP9,
    TYPE_MSG_EXP10,
    TYPE_MSG_EXP11,
    TYPE_MSG_EXP12,
    TYPE_RAW_COMMAND_10B,
    TYPE_RAW_COMMAND_12B,
    TYPE_RAW_COMMAND_14B,
    CanTestOption,
    ExpandSetCommand,
    LedColor,
    Msg1Status,
    MsgControlCommand,
    Rotation,
    SelfTestFault,
    TempRecordKind,
    ThrottleSource,
)

__all__ = [
    "BAUD_RATES_BPS",
    "CHANNELS_PER_GROUP",
    "FACTORY_NODE_ID",
    "HOST_NODE_ID",
    "MAX_CHANNELS",
    "MAX_GROUP",
    "MESSAGE_TYPE_RANGE",
    "SERVICE_CLEAR_TEMP_RECORD",
    "SERVICE_ESC_INFO",
    "SERVICE_EXPAND_SET",
    "SERVICE_GET_TEMP_RECORD",
    "SERVICE_MAINTENANCE",
    "SERVICE_MAJOR_CONFIG",
    "SERVICE_SELF_TEST",
    "SERVICE_SET_BAUD",
    "SERVICE_SET_FREQ",
    "SERVICE_SET_ID",
    "SERVICE_SET_LED",
    "SERVICE_SET_ROTATION",
    "SERVICE_THROTTLE_SELECT",
    "SERVICE_TYPE_RANGE",
    "THROTTLE_10B_MAX",
    "THROTTLE_MAX",
    "TYPE_CAN_TEST",
    "TYPE_GET_ESC_ID",
    "TYPE_MSG1",
    "TYPE_MSG2",
    "TYPE_MSG3",
    "TYPE_MSG_CONTROL",
    "TYPE_MSG_EXP1",
    "TYPE_MSG_EXP2",
    "TYPE_MSG_EXP3",
    "TYPE_MSG_EXP4",
    "TYPE_MSG_EXP5",
    "TYPE_MSG_EXP6",
    "TYPE_MSG_EXP7",
    "TYPE_MSG_EXP8",
    "TYPE_MSG_EXP9",
    "TYPE_MSG_EXP10",
    "TYPE_MSG_EXP11",
    "TYPE_MSG_EXP12",
    "TYPE_RAW_COMMAND_10B",
    "TYPE_RAW_COMMAND_12B",
    "TYPE_RAW_COMMAND_14B",
    "CanTestOption",
    "CanTestReport",
    "CanTestRequest",
    "CkescFrame",
    "CkescMessage",
    "EscInfoRequest",
    "EscInfoResponse",
    "ExpandSetCommand",
    "ExpandSetRequest",
    "GetEscIdAnswer",
    "GetEscIdRequest",
    "LedColor",
    "Maintenance0Response",
    "Maintenance1Response",
    "Maintenance2Response",
    "MaintenanceRequest",
    "MajorConfigRequest",
    "MajorConfigResponse",
    "Msg1",
    "Msg1Status",
    "Msg2",
    "Msg3",
    "MsgControlAck",
    "MsgControlCommand",
    "MsgControlRequest",
    "MsgExp1",
    "MsgExp2",
    "MsgExp3",
    "MsgExp4",
    "MsgExp5",
    "MsgExp6",
    "MsgExp7",
    "MsgExp8",
    "MsgExp9",
    "MsgExp10",
    "MsgExp11",
    "MsgExp12",
    "RawCommand10b",
    "RawCommand12b",
    "RawCommand14b",
    "Rotation",
    "SelfTestFault",
    "SelfTestRequest",
    "SelfTestResponse",
    "SetBaudRequest",
    "SetBaudResponse",
    "SetFreqRequest",
    "SetFreqResponse",
    "SetIdRequest",
    "SetIdResponse",
    "SetLedRequest",
    "SetLedResponse",
    "SetRotationRequest",
    "SetRotationResponse",
    "TempRecordKind",
    "ThrottleSelectRequest",
    "ThrottleSelectResponse",
    "ThrottleSource",
    "decode",
    "default_priority",
    "encode",
    "encode_raw_10b",
    "encode_raw_12b",
    "encode_raw_14b",
    "raw_12b_groups",
    "type_id_of",
]
