"""The Flipsky FT family: its CAN codec (docs/protocols.md §4; the vendor's document V1.4).

The codec is :mod:`~bridge.escs.ft.records` (constants, enumerations, records, CAN IDs) and
:mod:`~bridge.escs.ft.codec` (records to frames and back): pure functions between
:class:`can.Message` and frozen records, no I/O, clock or logging. The family behind
:class:`~bridge.escs.family.EscFamily` is :mod:`bridge.escs.ft.family`.

Wire format
-----------
29-bit data frames, ``id = (esc_id << 8) | command`` with bits 28..16 zero. Multi-byte
fields are big-endian. Where a frame carries a CRC it is CRC-16/MODBUS over every byte
before it, sent high byte first.

Commands (bridge → ESC; the ESC drops a command not repeated within 450 ms):

=====  ===============================  ======================  ======  ====  ===  ========
 ID     name                             record                  crc     gear  DLC  scale
=====  ===============================  ======================  ======  ====  ===  ========
 0x00   SET_CURRENT_GEAR_CRC16           SetCurrent              True    yes   7    1e-5 A
 0x01   SET_CURRENT_BRAKE_CRC16          SetCurrentBrake         True    --    6    1e-5 A
 0x02   SET_DUTY_GEAR_CRC16              SetDuty                 True    yes   7    1e-6
 0x03   SET_CURRENT_PERCENT_CRC16        SetCurrentPercent       True    None  6    1e-5
 0x04   SET_CURRENT_PERCENT_GEAR_CRC16   SetCurrentPercent       True    yes   7    1e-5
 0x05   SET_CURRENT_BRAKE_PERCENT_CRC16  SetCurrentBrakePercent  True    --    6    1e-5
 0x12   SET_ERPM_GEAR_CRC16              SetErpm                 True    yes   7    1 erpm
 0x13   SET_POSITION_GEAR_CRC16          SetPosition             True    yes   7    1e-5 deg
 0x14   SET_ID_CURRENT_CRC16             SetIdCurrent            always  --    6/7  1e-5 A
 0x15   SET_CURRENT_GEAR                 SetCurrent              False   yes   5    1e-5 A
 0x16   SET_CURRENT_PERCENT_GEAR         SetCurrentPercent       False   yes   5    1e-5
 0x17   SET_DUTY_GEAR                    SetDuty                 False   yes   5    1e-6
 0x18   SET_ERPM_GEAR                    SetErpm                 False   yes   5    1 erpm
 0x19   SET_POSITION_GEAR                SetPosition             False   yes   5    1e-5 deg
 0x1A   SET_CURRENT_BRAKE                SetCurrentBrake         False   --    4    1e-5 A
 0x1B   SET_CURRENT_BRAKE_PERCENT        SetCurrentBrakePercent  False   --    4    1e-5
=====  ===============================  ======================  ======  ====  ===  ========

"gear yes" means the record's ``gear`` is a :class:`Gear` (``Gear.NONE`` = no speed-gear
limiting); ``None`` means ``gear=None``; ``--`` means the record has no gear field. Every
(record class, crc, gear present) combination names exactly one command; the one left over,
``SetCurrentPercent(gear=None, crc=False)``, has no FT command and is refused by
:func:`encode`. :data:`COMMAND_RECORDS` holds this table as data.

Every command value is an i32 after scaling; duty and fractions must lie in -1..1 and
angles in -180..180 degrees. Brake, d-axis and plain currents and erpm are limited by i32
alone (the seed gives them no range).

Telemetry (ESC → bridge, every 10 ms, DLC 8, CRC over bytes 0..5):

=====  ===============  =============  ===============================================
 ID     name             record         bytes 0..5
=====  ===============  =============  ===============================================
 0x0B   REALTIME_DATA_0  RealtimeData0  motor current i24 mA, battery current i24 mA
 0x0C   REALTIME_DATA_1  RealtimeData1  erpm i24, duty i24 (x 1000)
 0x0D   REALTIME_DATA_2  RealtimeData2  MOSFET i16, motor i16 (0.01 degC), battery i16 (0.01 V)
=====  ===============  =============  ===============================================

Decisions where the spec is silent
----------------------------------
- The seed's enum lists 16 commands and 3 telemetry frames (19 sections in all), not 17
  commands.
- No ESC ID is reserved: the seed names none (its C example's ``esc_id == -2`` "free slot"
  sentinel is a host-side bug, not an ID), so 0..255 are all encodable. Stock VESC's 255
  broadcast is not part of FT.
- Values are rounded to nearest (ties to even, Python's :func:`round`), not truncated as the
  seed's C casts do: 0.57 x 100000 is 56999.99999999999 in binary floating point.
- Ranges are checked on the value before scaling: duty 1.0000004 is refused although it
  would round to 1000000.
- Decoding reports command values as sent, without range checks, so a capture of a bad
  sender can still be read; only a gear byte above 4 (which no record can hold) is a
  :class:`~bridge.errors.FrameError`.
- A DLC-7 0x14 frame (the seed's C example inserts a zero "gear" byte) decodes to the same
  :class:`SetIdCurrent`; the extra byte is covered by the CRC and otherwise ignored, and the
  encoder always sends the DLC-6 form.
- Telemetry is encoded (for the ESC simulator) with only the field widths as limits.
- Records are not checked when built: :func:`encode_command` is the one place values are
  checked, which keeps telemetry decoding cheap (about 2 us a frame).
- Only :class:`SetCurrentPercent` has ``gear: Gear | None``; the other geared records hold a
  :class:`Gear`, because each of their commands always sends a gear byte.
- :func:`parse_id` raises :class:`~bridge.errors.ValueRangeError` for an ID with bits above 15;
  :func:`decode` returns ``None`` for such a frame.
"""
