"""esc-bridge's own MAVLink dialect: pymavlink's ardupilotmega plus ESC_INFO and ESC_STATUS.

pymavlink 2.4.50 bundles no ESC_INFO (290) or ESC_STATUS (291), so a stock receiver reports
them as ``UNKNOWN_290``/``UNKNOWN_291``. ``esc_bridge.xml`` (package data) adds them with the
upstream wire format; :func:`load_dialect` turns it into a Python module with pymavlink's mavgen
on first use and caches the result outside the source tree (see :mod:`bridge.mavlink._dialect`
for the cache layout). Use the returned module wherever ``pymavlink.dialects.v20.ardupilotmega``
would be used.
"""

from bridge.mavlink._dialect import (
    CACHE_ENV,
    DIALECT_XML,
    DialectError,
    cache_root,
    dialect_key,
    generate_dialect,
    load_dialect,
    stock_ardupilotmega_xml,
)

__all__ = [
    "CACHE_ENV",
    "DIALECT_XML",
    "DialectError",
    "cache_root",
    "dialect_key",
    "generate_dialect",
    "load_dialect",
    "stock_ardupilotmega_xml",
]
