"""The ESC families, one folder each (``ckesc/``, ``ft/``), behind one interface.

:mod:`bridge.escs.family` is the interface (:class:`~bridge.escs.family.EscFamily`) and the
family-neutral telemetry record; :mod:`bridge.escs.registry` finds a family by name and imports
it when it is first used. :mod:`bridge.escs.drivers` and :mod:`bridge.escs.filters` hold what
the families' drivers and kernel filters share. Each family's codec is pure functions on
``can.Message``; its package re-exports the codec's public names (``from bridge.escs import
ckesc``).
"""
