"""``esc-bridge plot``: a recorded flight (``esc-bridge run --record``) drawn as pictures.

- :mod:`bridge.plot.recording`: a ``--record`` directory's recordings, and the autopilot's
  HEARTBEATs and the STATUSTEXTs of a tlog;
- :mod:`bridge.plot.series`: the CAN capture as per-ESC time series (commands, rpm, currents,
  voltage, temperatures, failure flags), decoded only through the
  :class:`~bridge.escs.family.EscFamily` interface, so every family plots alike;
- :mod:`bridge.plot.spans`: the autopilot armed, the bridge in failsafe or in a motor test,
  every ESC commanded to stop while armed;
- :mod:`bridge.plot.flight`: a recording ready to draw, both files on one time axis;
- :mod:`bridge.plot.page`: the HTML page that shows the pictures with the flight's summary
  (none of these imports matplotlib);
- :mod:`bridge.plot.draw`: the pictures, with matplotlib's Agg backend. Only ``esc-bridge plot``
  imports it: matplotlib is the optional extra ``plot``, which nothing else needs.
"""
