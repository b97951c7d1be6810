"""``esc-bridge demo``: the whole system on one machine, no hardware, no configuration file.

* :mod:`~bridge.demo.system`: the parts (bridge, simulated ESCs and autopilot, monitor), started
  and stopped in order, and the flight;
* :mod:`~bridge.demo.child`: a child process (the bridge, the simulator) and its output;
* :mod:`~bridge.demo.watch`: what the demo watches of the bridge over Zenoh.
"""
