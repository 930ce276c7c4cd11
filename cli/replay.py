"""Play a flight recording into a read-only console, at any speed, from any point.

    fleetlink replay mission.mcap
    fleetlink replay mission.mcap --speed 4 --start 120

The console shows the fleet as the operator's console saw it: every recorded message arrives with
the link it came on, at the recorded time scaled by ``--speed``; ``--start S`` begins S seconds into
the recording (what came before is applied at once, so the fleet table is as it was then). The
console is read-only: it sends no command and says so. ``--headless`` plays without a terminal
and prints the fleet table at the end. See docs/recording.md.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from pathlib import Path
from typing import Any


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", type=Path, help="an MCAP file made by fleetlink record")
    parser.add_argument("--speed", type=float, default=1.0, help="times real time (default 1)")
    parser.add_argument("--start", type=float, default=0.0, help="seconds into the recording to start at")
    parser.add_argument("--headless", action="store_true", help="no console: play, then print the fleet table")


def run(args: argparse.Namespace) -> int:
    from fleetlink.site.recorder import RecordingError
    from fleetlink.site.replay import ReplaySource

    try:
        source = ReplaySource(args.file, speed=args.speed, start_s=args.start)
    except (RecordingError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if source.problem is not None:
        print(f"note: {args.file}: {source.problem}; replaying what came before", file=sys.stderr)
    if args.headless:
        return run_headless(source)
    import logging

    logging.getLogger().handlers.clear()
    logging.basicConfig(filename="console.log", level=logging.INFO)
    return run_replay_console(source)


def console_parts(source: Any) -> tuple[Any, Any, Any, Any]:
    """The fleet model, its lock and the map and dose followers, fed from ``source``."""
    from fleetlink.operator.console import attach
    from fleetlink.operator.dose import DoseFollower
    from fleetlink.operator.fleet import FleetModel
    from fleetlink.operator.maps import MapFollower

    fleet = FleetModel(source.sender)
    lock = threading.Lock()
    maps = MapFollower(fleet)
    doses = DoseFollower(fleet)
    attach(source, fleet, lock, maps, doses)
    return fleet, lock, maps, doses


def replay_app(source: Any) -> tuple[Any, list[Any]]:
    """A read-only ``ConsoleApp`` on ``source`` and the snapshot fetchers it needs (started)."""
    from fleetlink.operator.console import ConsoleApp
    from fleetlink.operator.dose import DoseFetcher
    from fleetlink.operator.maps import MapFetcher

    fleet, lock, maps, doses = console_parts(source)
    app = ConsoleApp(source, fleet, source.clock, lock=lock, maps=maps, doses=doses, read_only=True)
    fetchers = [
        MapFetcher(maps, source.fetch_map, source.clock, lock).start(),
        DoseFetcher(doses, source.fetch_dose, source.clock, lock).start(),
    ]
    return app, fetchers


def run_replay_console(source: Any) -> int:
    app, fetchers = replay_app(source)
    source.start()
    try:
        app.run()
    finally:
        source.close()
        for fetcher in fetchers:
            fetcher.stop()
    return 0


def run_headless(source: Any) -> int:
    from fleetlink.operator.fleet_table import fleet_rows

    fleet, lock, _maps, _doses = console_parts(source)
    source.start()
    try:
        while not source.done:
            time.sleep(0.05)
    except KeyboardInterrupt:
        pass
    finally:
        source.close()
    now = source.clock.now()
    with lock:
        rows = fleet_rows(fleet, source.active, source.health, source.sender, now)
    print("robot  mode  battery  link  health  age  uwb  lease")
    for row in rows.values():
        print("  ".join(str(c) for c in row))
    print(f"{len(rows)} robots, {source.delivered} messages replayed", file=sys.stderr)
    return 0
