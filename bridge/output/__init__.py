"""The output side: from the mixed input to CAN frames at a fixed rate, safe whenever it must be.

In the order a tick uses them:

* :mod:`~bridge.output.mailbox`: the hand-over between the main process and the loop
  (CRC-checked shared memory: a motor test in, the input acted on and the counters out);
* :mod:`~bridge.output.safety`: the pure safety decision, what a tick may send and why. It is
  here, not beside the mixer, because it decides about the loop's ticks (its states are the
  loop's states, read by the daemon from the mailbox) and nothing but the loop runs it;
* :mod:`~bridge.output.motor_test`: the motor-test decisions (MAV_CMD_DO_MOTOR_TEST to a plan)
  and a test tick's frames;
* :mod:`~bridge.output.slew`: the slew limiter applied to each tick's commands;
* :mod:`~bridge.output.output_loop`: the loop itself (when to tick, and one tick);
* :mod:`~bridge.output.busload`: the worst-case bus load, checked before anything is sent;
* :mod:`~bridge.output.spin`: ``esc spin``, one motor test from a process of its own.

The loop imports none of ``spin``, the CLI or the daemon.
"""
