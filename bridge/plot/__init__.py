"""``esc-bridge plot``: a recorded flight (``esc-bridge run --record``) drawn as pictures.

- :mod:`bridge.plot.series`: the recording's files found and read, and turned into per-ESC time
  series (commands, rpm, currents, voltage, temperatures, failure flags) and the spans of the
  flight (autopilot armed, bridge failsafe, motor test, every ESC commanded to stop while
  armed). Typed records, no matplotlib; the CAN capture is decoded only through the
  :class:`~bridge.escs.family.EscFamily` interface, so every family plots alike.
- :mod:`bridge.plot.page`: the HTML page that shows the pictures with the flight's summary
  (no matplotlib either).
- :mod:`bridge.plot.draw`: the pictures, with matplotlib's Agg backend. Only ``esc-bridge plot``
  imports it: matplotlib is the optional extra ``plot``, which nothing else needs.
"""
