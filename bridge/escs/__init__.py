"""ESC protocol codecs: pure functions on ``can.Message``, one module per vendor protocol."""
