"""The VESC family: stock VESC firmware's own CAN protocol (docs/protocols.md §6).

``records`` holds the constants, packet IDs and frozen records, ``codec`` the pure encoding
and decoding between them and :class:`can.Message`. The family behind
:class:`~bridge.escs.family.EscFamily` is :mod:`bridge.escs.vesc.family`.

Wire format: 29-bit data frames, ``id = packet << 8 | controller_id`` with bits 28..16 zero,
big-endian two's-complement values, no CRC; controller ID 255 addresses every VESC. The bridge
sends the motor commands (SET_DUTY, SET_CURRENT, SET_CURRENT_BRAKE, SET_RPM, SET_CURRENT_REL)
and PING; the VESCs send status frames (when VESC Tool turns them on), PONG and NOTIFY_BOOT.
"""
