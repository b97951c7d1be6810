"""esc-bridge: MAVLink autopilot motor outputs to CAN-bus ESCs, ESC telemetry back out."""

from bridge.errors import (
    BridgeError,
    CodecError,
    ConfigError,
    CrcError,
    DlcError,
    FrameError,
    LinkError,
    NotExtendedIdError,
    TailByteError,
    UnknownTypeError,
    ValueRangeError,
)

__version__ = "0.1.0"

__all__ = [
    "BridgeError",
    "CodecError",
    "ConfigError",
    "CrcError",
    "DlcError",
    "FrameError",
    "LinkError",
    "NotExtendedIdError",
    "TailByteError",
    "UnknownTypeError",
    "ValueRangeError",
    "__version__",
]
