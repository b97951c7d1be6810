"""The autopilot side: everything MAVLink, in the order the data flows.

In the control loop: :mod:`~bridge.mavlink.endpoints` (connection strings),
:mod:`~bridge.mavlink.transport` (non-blocking bytes), :mod:`~bridge.mavlink.frames` (frame
scanner, signing check), :mod:`~bridge.mavlink.actuators` (motor-output decoders, pure),
:mod:`~bridge.mavlink.clock` (the autopilot's clock on ours). In the main process:
:mod:`~bridge.mavlink.link` (the link and its outputs) with :mod:`~bridge.mavlink.connection`,
:mod:`~bridge.mavlink.signing`, :mod:`~bridge.mavlink.tlog`, :mod:`~bridge.mavlink.stats`,
:mod:`~bridge.mavlink.heartbeat` (own HEARTBEAT, stream requests; the negotiation itself in
:mod:`~bridge.mavlink.streams`) and :mod:`~bridge.mavlink.commands` (command dispatch); and the
outgoing ESC telemetry, :mod:`~bridge.mavlink.esc_messages` (pure encoders) and
:mod:`~bridge.mavlink.telemetry_out` (the sender), which never imports the link. Imports go one
way: no module here imports one that imports it back.

This module itself is esc-bridge's own MAVLink dialect: pymavlink's ardupilotmega plus ESC_INFO
and ESC_STATUS.

pymavlink 2.4.50 bundles no ESC_INFO (290) or ESC_STATUS (291), so a stock receiver reports
them as ``UNKNOWN_290``/``UNKNOWN_291``. ``esc_bridge.xml`` (package data) adds them with the
upstream wire format; :func:`load_dialect` turns it into a Python module with pymavlink's mavgen
on first use and caches the result outside the source tree (see :mod:`bridge.mavlink._dialect`
for the cache layout). Use the returned module wherever ``pymavlink.dialects.v20.ardupilotmega``
would be used. For stock pymavlink, MAVProxy and mavlogdump, :func:`install_dialect` (``esc-bridge
mavlink-dialect``) puts the generated module among pymavlink's own as ``esc_bridge``.
"""

from bridge.mavlink._dialect import (
    CACHE_ENV,
    DIALECT_XML,
    DialectError,
    cache_root,
    dialect_key,
    generate_dialect,
    install_dialect,
    load_dialect,
    stock_ardupilotmega_xml,
    stock_dialects_dir,
)

__all__ = [
    "CACHE_ENV",
    "DIALECT_XML",
    "DialectError",
    "cache_root",
    "dialect_key",
    "generate_dialect",
    "install_dialect",
    "load_dialect",
    "stock_ardupilotmega_xml",
    "stock_dialects_dir",
]
