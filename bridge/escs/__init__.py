"""The ESC families, one folder each (``ckesc/``, ``ft/``, ``dronecan/``), behind one interface.

:mod:`bridge.escs.family` is the interface (:class:`~bridge.escs.family.EscFamily`: a family's
wire and its driver) and the family-neutral telemetry record; :mod:`bridge.escs.registry` finds
a family, and its tool modules, by name and imports it when it is first used.
:mod:`bridge.escs.drivers`, :mod:`bridge.escs.filters`, :mod:`bridge.escs.tools` and
:mod:`bridge.escs.uavcan_v0` hold what the families share. Each family's codec is public
modules of pure functions on ``can.Message``; no package re-exports them.
"""
