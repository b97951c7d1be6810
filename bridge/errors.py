"""The exceptions esc-bridge raises, all rooted at :class:`BridgeError`.

::

    BridgeError
    ├── ConfigError (ValueError)          a configuration or CLI argument is wrong
    ├── LinkError (ConnectionError)       a CAN bus or MAVLink link cannot be opened or used
    │   └── NoAnswerError (TimeoutError)  an ESC did not answer a request within the timeout
    │       └── WrongNodeError            ... but another node answered it
    ├── PayloadError (ValueError)         a Zenoh payload that is not what its key carries
    ├── SetupError                        an ESC set-up step cannot be done as the bus stands
    │   └── RefusedError                  an ESC answered with values other than those asked
    └── CodecError (ValueError)           a CAN frame or a value cannot be coded
        ├── ValueRangeError               encode: a value outside the protocol's range
        └── FrameError                    decode: a frame that claims to be ours is malformed
            ├── NotExtendedIdError        an 11-bit (standard) ID, an RTR or an error frame
            ├── DlcError                  the wrong data length for its type
            ├── CrcError                  the CRC does not match
            ├── TailByteError             a UAVCAN v0 tail byte that is not a single-frame transfer
            └── UnknownTypeError          an ID in the protocol's range with no known type

Decoders return ``None`` for a frame of another protocol ("not ours"); they raise a
:class:`FrameError` only for a frame that is in their protocol's space but malformed, so a
caller on a mixed bus counts both and carries on.
"""

from __future__ import annotations


class BridgeError(Exception):
    """Root of every exception esc-bridge raises on purpose."""


class ConfigError(BridgeError, ValueError):
    """A configuration file, mixer definition or command-line argument is invalid."""


class LinkError(BridgeError, ConnectionError):
    """A CAN bus or MAVLink link could not be opened, or failed beyond recovery."""


class PayloadError(BridgeError, ValueError):
    """A Zenoh payload that is not the JSON its key carries: the message names the key and the
    field (:mod:`bridge.telemetry.payload`)."""


class NoAnswerError(LinkError, TimeoutError):
    """An ESC did not answer a request (or acknowledge a broadcast) within the timeout."""


class WrongNodeError(NoAnswerError):
    """The addressed ESC did not answer, but another node sent the answer to the request."""


class SetupError(BridgeError):
    """An ESC set-up step cannot be done as the bus stands (e.g. Set ID with several ESCs)."""


class RefusedError(SetupError):
    """An ESC answered a setting with the values in effect, which differ from those asked."""


class CodecError(BridgeError, ValueError):
    """A CAN frame could not be encoded or decoded."""


class ValueRangeError(CodecError):
    """A value to encode does not fit the protocol's field; it is never wrapped or clipped."""


class FrameError(CodecError):
    """A received frame is malformed for the protocol it claims to belong to."""


class NotExtendedIdError(FrameError):
    """Both ESC protocols use 29-bit data frames only."""


class DlcError(FrameError):
    """The data length does not match the frame type."""


class CrcError(FrameError):
    """The frame's CRC does not match its data."""


class TailByteError(FrameError):
    """A UAVCAN v0 tail byte without start=end=1, toggle=0 where the protocol allows only
    single-frame transfers."""


class UnknownTypeError(FrameError):
    """The ID lies in the protocol's range but names no type the protocol defines."""
