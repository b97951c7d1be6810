"""``esc-bridge run``'s main process: the best-effort side around the control loop.

* :mod:`~bridge.daemon.preflight`: the start-up plan, everything ``run`` (and ``--check``)
  refuses before a CAN frame is sent;
* :mod:`~bridge.daemon.supervisor`: starts the parts in order, reports state changes, stops
  cleanly;
* :mod:`~bridge.daemon.loop_runner`: where the control loop runs (its own process, or a
  thread), and the safe values sent from here if it died;
* :mod:`~bridge.daemon.motor_test_control`: a ground station's MAV_CMD_DO_MOTOR_TEST on this
  side (who may ask, handing it to the loop, reporting it);
* :mod:`~bridge.daemon.health`, :mod:`~bridge.daemon.severity`: what the loop's states are
  called (STATUSTEXT, log) and the health records the publishers send.

Nothing here runs in the control loop's process (``tests/test_architecture.py``).
"""
