"""The ``fleetlink`` command: one entry point, a subcommand per job.

Subcommand modules are imported only when chosen, so ``fleetlink --help`` stays fast and a
missing optional dependency of one tool cannot break the others.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import logging
import signal
import sys
from collections.abc import Callable, Iterator, Sequence

# name -> (module, one-line help). Each module has add_arguments(parser) and run(args) -> int.
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "field": ("fleetlink.cli.field", "start the simulated field and watch it live (the demo)"),
    "board": ("fleetlink.cli.board", "serve a simulated control board, or probe a real one"),
    "agent": ("fleetlink.cli.agent", "run one robot's agent (board link, Zenoh + MQTT command links)"),
    "uwb": ("fleetlink.cli.uwb", "the UWB gateway: fixes from the field's true poses, over MQTT (PANS too)"),
    "map": (
        "fleetlink.cli.map",
        "maps: fetch a robot's map, read a map_server map, build one from a CARMEN log, score a trajectory's relation errors",
    ),
    "dose": (
        "fleetlink.cli.dose",
        "UV dose: fetch robots' dose layers and write the dose report (PGM, PNG, CSV, summary)",
    ),
    "console": ("fleetlink.cli.console", "the operator console: join a fleet over Zenoh (primary) and MQTT (fallback)"),
    "marks": ("fleetlink.cli.marks", "marks: export every console's marks (CSV, GeoJSON) for the incident report"),
    "vda5050": ("fleetlink.cli.vda5050", "VDA 5050 2.1 vehicle interface: every robot as a VDA 5050 vehicle on MQTT"),
    "record": ("fleetlink.cli.record", "the flight recorder: every fleet message on both links into an MCAP file"),
    "replay": ("fleetlink.cli.replay", "play a flight recording into a read-only console, at any speed"),
    "foxglove": ("fleetlink.cli.foxglove", "serve the live fleet to Foxglove over WebSocket (poses, maps, dose)"),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="fleetlink",
        description="fleetlink runs a fleet of small mobile robots and the people who drive them.",
    )
    parser.add_argument("--log-level", default="INFO", help="DEBUG, INFO, WARNING or ERROR (default INFO)")
    parser.add_argument("--version", action="store_true", help="print the version and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module, help_text) in SUBCOMMANDS.items():
        mod = importlib.import_module(module)
        p = sub.add_parser(name, help=help_text, description=mod.__doc__)
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.version:
        from importlib.metadata import version

        print(f"fleetlink {version('fleetlink')}")
        return 0
    if not getattr(args, "_run", None):
        parser.print_help()
        return 2
    logging.basicConfig(
        level=getattr(logging, str(args.log_level).upper(), logging.INFO),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    with _sigterm_as_interrupt():
        try:
            return int(args._run(args) or 0)
        except KeyboardInterrupt:
            return 130


@contextlib.contextmanager
def on_sigterm(handler: Callable[[int, object], None]) -> Iterator[None]:
    """``handler`` takes SIGTERM while the block runs, the previous one after it. Outside the
    main thread (a command run from a test's thread) signals cannot be handled: left be."""
    try:
        previous = signal.signal(signal.SIGTERM, handler)
    except ValueError:
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _sigterm_as_interrupt() -> contextlib.AbstractContextManager[None]:
    """SIGTERM (``systemctl stop``, ``kill``) takes Ctrl-C's way out while a command runs: its
    clean shutdown runs (the agent halts the robot and says OFFLINE, the field removes a secured
    site's secrets, the console sends stop). Python's default ends the process without unwinding."""

    def interrupt(signum: int, frame: object) -> None:
        raise KeyboardInterrupt(f"signal {signum}")

    return on_sigterm(interrupt)


if __name__ == "__main__":
    sys.exit(main())
