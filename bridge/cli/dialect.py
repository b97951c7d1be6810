"""``esc-bridge mavlink-dialect``: make stock pymavlink, MAVProxy and mavlogdump decode ESC_INFO
and ESC_STATUS, which pymavlink's bundled dialects lack (they show ``UNKNOWN_290``/``_291``)."""

from __future__ import annotations

import argparse
from pathlib import Path

from bridge.cli._common import EXIT_OK


def add_parser(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    dialect = commands.add_parser(
        "mavlink-dialect",
        help="install the bridge's MAVLink dialect (ESC_INFO, ESC_STATUS) where stock "
        "pymavlink, MAVProxy and mavlogdump find it",
        description="Generate esc-bridge's MAVLink dialect (pymavlink's ardupilotmega plus "
        "ESC_INFO and ESC_STATUS) and install it as esc_bridge.py among pymavlink's own "
        "dialects, then print how to use it: --dialect esc_bridge (MAVProxy, mavlogdump) or "
        "MAVLINK20=1 MAVLINK_DIALECT=esc_bridge (any pymavlink program). Reinstalling or "
        "upgrading pymavlink removes it: run this again.",
    )
    dialect.add_argument(
        "--into",
        type=Path,
        metavar="DIR",
        help="another pymavlink's dialects directory, e.g. that of MAVProxy's Python: "
        "…/site-packages/pymavlink/dialects/v20 (default: this Python's pymavlink)",
    )
    dialect.set_defaults(handler=_install)


def _install(args: argparse.Namespace) -> int:
    from bridge.mavlink import install_dialect

    path = install_dialect(args.into)
    print(f"installed the esc_bridge MAVLink dialect: {path}")
    print("decode ESC_INFO and ESC_STATUS with it:")
    print("  MAVProxy    mavproxy.py --dialect esc_bridge --master ...")
    print("  mavlogdump  mavlogdump.py --dialect esc_bridge flight.tlog")
    print("  pymavlink   MAVLINK20=1 MAVLINK_DIALECT=esc_bridge python3 your_script.py")
    print('              (or mavutil.mavlink_connection(url, dialect="esc_bridge"), MAVLINK20=1)')
    print("reinstalling or upgrading pymavlink removes it: run esc-bridge mavlink-dialect again")
    return EXIT_OK
