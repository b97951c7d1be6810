"""``esc-bridge plot``: a recorded flight (``run --record``) drawn as PNG pictures and a page."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from bridge.cli._common import EXIT_FAILED, EXIT_OK, id_list, int_list
from bridge.errors import ConfigError
from bridge.escs import registry

SOURCES = ("auto", "capture", "mcap")  # as bridge.plot.flight.SOURCES, which imports more

INSTALL_HINT = (
    "esc-bridge plot draws with matplotlib, which is not installed; install the plot extra: "
    "pip install 'esc-bridge[plot]' (from a checkout: pip install -e '.[plot]')"
)


def add_parser(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    plot = commands.add_parser(
        "plot",
        help="draw a recorded flight (run --record DIR): PNG pictures and an HTML page",
        description="Draw a recording made with `esc-bridge run --record DIR` (or `demo "
        "--record DIR`): per ESC, its command against its rpm, current, voltage and "
        "temperatures over time, with the autopilot's arming, the bridge's failsafes and motor "
        "tests shaded and the ESC's failure flags marked, plus an overview of every ESC and an "
        "HTML page of them all, into RECORDING_DIR/<recording>-plot/ (or --out). It reads the "
        "recording's candump .log and .tlog, or its .mcap when they are not there (--source). "
        "Needs matplotlib (pip install 'esc-bridge[plot]').",
    )
    plot.add_argument(
        "directory", type=Path, metavar="RECORDING_DIR", help="the directory given to --record"
    )
    which = plot.add_mutually_exclusive_group()
    which.add_argument(
        "--recording",
        metavar="NAME",
        help="the recording to draw, e.g. esc-bridge-20240405-193012 (default: the newest)",
    )
    which.add_argument("--all", action="store_true", help="draw every recording in the directory")
    plot.add_argument(
        "--out",
        type=Path,
        metavar="DIR",
        help="write the pictures into DIR/<recording>-plot/ (default: RECORDING_DIR)",
    )
    plot.add_argument(
        "--source",
        choices=SOURCES,
        default="auto",
        help="what to draw from: the candump .log and the .tlog (capture), the .mcap, or "
        "(auto, the default) the capture where it is there, else the .mcap",
    )
    plot.add_argument(
        "--protocol",
        choices=("auto", *registry.names()),
        default="auto",
        help="the ESCs' protocol (default: the one that reads the capture)",
    )
    plot.add_argument(
        "--ids",
        type=id_list,
        metavar="ID,ID,...",
        help="the ESCs' IDs, motor 1 first, as [escs] ids (default: every ESC on the bus, "
        "by ID; no motor numbers)",
    )
    plot.add_argument(
        "--channels",
        type=_channels,
        metavar="C,C,...",
        help="for ESCs commanded by throttle channel: the channel of each ESC, in the order of "
        "--ids or of their IDs (default 1, 2, 3, ...)",
    )
    plot.add_argument(
        "--pole-pairs",
        type=_pole_pairs,
        default=7,
        metavar="P[,P,...]",
        help="motor pole pairs, one or one per ESC of --ids (rpm = erpm / P; default 7)",
    )
    plot.set_defaults(handler=_plot)


def _channels(text: str) -> list[int]:
    return int_list(text, "throttle channels", "1,2,3,4")


def _pole_pairs(text: str) -> int | list[int]:
    pairs = int_list(text, "pole pair counts", "7 or 7,7,14,14")
    if any(p < 1 for p in pairs):
        raise argparse.ArgumentTypeError(f"pole pairs must be 1 or more, got {text!r}")
    return pairs[0] if len(pairs) == 1 else pairs


def _plot(args: argparse.Namespace) -> int:
    from bridge.plot import recording

    recordings = recording.find_recordings(args.directory)  # first: a wrong directory says so
    if args.recording is not None:
        name = args.recording.removesuffix(".log").removesuffix(".tlog").removesuffix(".mcap")
        chosen = [r for r in recordings if r.name == name]
        if not chosen:
            raise ConfigError(
                f"{args.directory}: no recording {name}; it holds "
                + ", ".join(r.name for r in recordings)
            )
    else:
        chosen = list(recordings) if args.all else [recordings[-1]]
    if isinstance(args.pole_pairs, list) and args.ids is None:
        raise ConfigError("--pole-pairs: one per ESC needs --ids (which ESC is which)")
    try:
        from bridge.plot import draw
    except ImportError as exc:
        if not (exc.name or "").startswith("matplotlib"):
            raise
        print(f"esc-bridge: {INSTALL_HINT}", file=sys.stderr)
        return EXIT_FAILED
    from bridge.plot.flight import load_flight
    from bridge.plot.page import PAGE, page_html

    for files in chosen:
        flight = load_flight(
            files, args.protocol, args.ids, args.channels, args.pole_pairs, args.source
        )
        out = (args.out or args.directory) / f"{files.name}-plot"
        try:
            pictures = draw.write_pictures(flight, out)
            page = out / PAGE
            page.write_text(page_html(flight, [p.name for p in pictures]), encoding="utf-8")
        except OSError as exc:
            raise ConfigError(f"{out}: cannot write the pictures: {exc.strerror or exc}") from exc
        spans = ", ".join(
            f"{len(flight.spans_of(kind))} {kind}"
            for kind in sorted({span.kind for span in flight.spans})
        )
        print(
            f"{files.name}: {len(flight.escs)} ESCs ({flight.can.family}), "
            f"{flight.duration_s:.1f} s; spans: {spans or 'none'}"
        )
        print(f"  {page}")
        for picture in pictures:
            print(f"  {picture}")
    return EXIT_OK
