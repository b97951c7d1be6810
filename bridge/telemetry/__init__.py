"""ESC telemetry: CAN in -> decoders -> per-ESC state, read by the publishers.

``reader`` (the CAN reader thread), ``state`` (the per-ESC state, pure), ``for_config`` (the
state of a configuration), ``zenoh_out`` (the Zenoh publisher), ``recorder`` (``--record``),
``fanout`` (starts and stops the reader and the publishers beside the output loop).
"""
