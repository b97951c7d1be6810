"""ESC telemetry: CAN in -> decoders -> per-ESC state, read by the publishers."""
