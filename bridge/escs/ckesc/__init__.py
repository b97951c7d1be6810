"""The CKESC family: UAVCAN v0 framing carrying the vendor's own message and service types.

The family behind :class:`~bridge.escs.family.EscFamily` is :mod:`bridge.escs.ckesc.family`.

The reference is ``docs/protocols.md`` §3 (the project's reading of the vendor's "CKESC UAVCAN
Protocol 2.1"); section numbers "seed 4.4.x" below point into the vendor document, and the
tables of §3.2 and §3.6 give each type's vendor section. The codec is pure (it imports only
the standard library, ``can`` for :class:`can.Message`, and the errors; no I/O, clock or
logging): :mod:`~bridge.escs.ckesc.records` (constants, enumerations, one record per type),
:mod:`~bridge.escs.ckesc.layout` (value ranges, field checks, a type's row in the table),
:mod:`~bridge.escs.ckesc.messages` and :mod:`~bridge.escs.ckesc.services` (each type's layout
and row), :mod:`~bridge.escs.ckesc.codec` (frames: :class:`~bridge.escs.ckesc.codec.CkescFrame`,
``decode``, ``encode``, the throttle hot path).

Wire format in one paragraph: 29-bit data frames only. A message (broadcast) frame's ID is
priority (5 bits) · type ID (16) · 0 · source node (7); a service frame's ID is priority ·
service type (8) · request flag · destination node (7) · 1 · source node. All multi-byte fields
are little-endian. Every frame but RawCommand_10b ends in a tail byte ``0xC0 | transfer_id``
(single-frame transfer); MSG_EXP12 uses its tail byte's transfer ID for a record kind. That
framing is UAVCAN v0's, shared with DroneCAN in :mod:`bridge.escs.uavcan_v0`: the ID helpers
``message_id``, ``service_id``, ``parse_id`` (→ ``CanId``), ``tail_byte``, ``TransferIds``
(one 0..31 counter per type ID), ``MAX_NODE_ID`` and the ``PRIORITY_*`` levels are there, not
here.

Public API: one frozen record class per payload (``records.CkescMessage`` is their union),
wrapped in a ``codec.CkescFrame`` envelope; ``codec.decode`` and ``codec.encode`` convert
envelopes; the throttle hot path is ``codec.encode_raw_12b``, ``encode_raw_14b`` and
``encode_raw_10b``.

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
