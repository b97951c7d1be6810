"""Standard DroneCAN (UAVCAN v0) ESCs: ``uavcan.equipment.esc.RawCommand`` out,
``uavcan.equipment.esc.Status`` and ``uavcan.protocol.NodeStatus`` in.

- :mod:`bridge.escs.uavcan_v0` (shared with CKESC, not in this folder): the CAN ID, transfer
  IDs and the transfer layer (tail bytes, transfer CRC, multi-frame split and reassembly), pure;
- :mod:`~bridge.escs.dronecan.wire`: what the bridge sends, encoded by hand for the output loop
  (RawCommand, our NodeStatus), pure and free of the ``dronecan`` package;
- :mod:`~bridge.escs.dronecan.codec`: frames to records and back with ``dronecan``;
- :mod:`~bridge.escs.dronecan.driver`: command fractions to RawCommand transfers per tick;
- :mod:`~bridge.escs.dronecan.sim`: simulated DroneCAN ESC nodes.

Nothing is imported here, so the output loop's import of the driver does not pull in
``dronecan``.
"""
