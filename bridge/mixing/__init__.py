"""Mixing: the autopilot's input vector in, one command fraction per ESC output out.

One job per module, in the order a mixer is made and used:

* :mod:`~bridge.mixing.definition`: the inputs (``ch1..ch32``, roll, pitch, yaw, thrust) and
  the validated definition of each output (frozen dataclasses);
* :mod:`~bridge.mixing.geometry`: a multirotor's rotors to its mix weights (pure maths);
* :mod:`~bridge.mixing.loader`: mixer files (``mixers/*.toml``, schema in its README) to
  definitions, by name or path;
* :mod:`~bridge.mixing.desaturation`: the rotor outputs desaturated airmode-style;
* :mod:`~bridge.mixing.mixer`: the mixer run on every input (shaping, validity).

Nothing here imports the output loop, the daemon, the CLI or the configuration, and nothing but
the loader touches a file.
"""
