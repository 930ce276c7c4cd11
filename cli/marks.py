"""Marks. ``export`` joins the fleet read-only, as ``fleetlink console --read-only`` would, collects
every console's marks -- the retained sets on MQTT (``fleetlink/v1/<robot>/marks/set/<login>``),
the answers to a Zenoh marks query, live marks heard meanwhile, and any console marks files given
with ``--include`` -- merges them (by markId, the newest version wins) and writes the live ones for
the incident report: CSV (markId, kind, label, x_m, y_m, sd_m, robot, by, time_utc) or GeoJSON
(a FeatureCollection of Points, ``[x, y]`` in metres in the site frame, ``"frame": "site"``).
It publishes nothing. See docs/console.md, "Marks".

Examples:
  fleetlink marks export --out incident/marks.csv --mqtt mqtt://10.0.0.5:1883 --zenoh-connect tcp/10.0.0.5:7447
  fleetlink marks export --out marks.geojson --config console.toml --wait 5
  fleetlink marks export --out marks.csv --include marks.json      # add a console's marks file
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import threading
from pathlib import Path

log = logging.getLogger(__name__)

ZENOH_ASK_AT_S = 0.5
"""When the export asks the consoles over Zenoh (peers take a moment to find each other)."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="marks_command", metavar="ACTION", required=True)
    ex = sub.add_parser("export", help="collect every console's marks and write them as CSV or GeoJSON")
    ex.add_argument("--out", required=True, type=Path, help="the file to write: .csv or .geojson")
    ex.add_argument("--wait", type=float, default=3.0, help="seconds to collect marks (default 3)")
    ex.add_argument(
        "--include", action="append", type=Path, default=[], metavar="FILE", help="a console's marks file too (repeat)"
    )
    ex.add_argument("--config", type=Path, help="a console TOML file (its links and login)")
    ex.add_argument("--operator", help="the login to join as (default operator-1; publishes nothing)")
    ex.add_argument("--zenoh-connect", action="append", default=None, help="Zenoh endpoint to connect to (repeat)")
    ex.add_argument("--zenoh-listen", action="append", default=None, help="Zenoh endpoint to listen on (repeat)")
    ex.add_argument("--mqtt", dest="mqtt_url", help="MQTT broker url (default mqtt://127.0.0.1:1883)")
    ex.add_argument("--user", help="log in to the router and the broker as this user (op-<name>)")
    ex.add_argument("--password-file", type=Path, help="the --user's password (one line)")
    ex.add_argument("--ca-file", help="the site CA for tls/ Zenoh endpoints and mqtts:// urls")
    ex.set_defaults(_run=run_export, read_only=True, marks_file=None)


def run(args: argparse.Namespace) -> int:  # pragma: no cover - argparse always sets a sub-action
    return int(args._run(args))


def run_export(args: argparse.Namespace) -> int:
    from fleetlink.cli.console import load_settings, open_link
    from fleetlink.operator.feed import attach
    from fleetlink.operator.fleet import FleetModel
    from fleetlink.operator.marks import MarksStore, export_marks
    from fleetlink.shared.clock import SystemClock
    from fleetlink.shared.config import ConfigError

    out: Path = args.out
    if out.suffix.lower() not in (".csv", ".geojson", ".json"):
        print(f"fleetlink marks export: --out must end in .csv or .geojson, not {out.name!r}", file=sys.stderr)
        return 2
    if not args.wait >= 0:
        print("fleetlink marks export: --wait must be >= 0", file=sys.stderr)
        return 2
    try:
        settings = load_settings(args)
    except (ConfigError, ValueError) as exc:
        print(f"fleetlink marks export: {exc}", file=sys.stderr)
        return 2
    clock = SystemClock()
    fleet = FleetModel(settings.operator)
    lock = threading.Lock()
    for path in args.include:
        loaded = MarksStore(path).load()
        if not loaded and not path.exists():
            print(f"fleetlink marks export: no marks file {str(path)!r}", file=sys.stderr)
            return 1
        with lock:
            for mark in loaded:
                fleet.apply(mark, "file", clock.now())
    try:
        # Its own client id: a console of the same login on this host keeps its broker session.
        link = open_link(settings, clock, client_id=f"{settings.operator}-marks-export-{os.getpid()}"[:64])
    except Exception as exc:  # zenoh raises its own ZError for bad endpoints
        print(f"fleetlink marks export: cannot join the fleet: {exc}", file=sys.stderr)
        return 1
    attach(link, fleet, lock)  # unbound: every mark heard is merged at once
    # The retained sets arrive as soon as the broker session is up; the Zenoh query is asked once
    # the peers have had a moment to find each other. Then whatever else comes within --wait.
    start, pause = clock.now(), threading.Event()
    try:
        pause.wait(min(ZENOH_ASK_AT_S, args.wait))
        link.fetch_marks(timeout=max(0.2, args.wait - (clock.now() - start)))
        pause.wait(max(0.0, args.wait - (clock.now() - start)))
    finally:
        link.close()
    with lock:
        marks = list(fleet.marks.values())
    try:
        n = export_marks(marks, out)
    except (OSError, ValueError) as exc:
        print(f"fleetlink marks export: {exc}", file=sys.stderr)
        return 1
    consoles = sorted({m.header.sender for m in marks if not m.removed})
    removed = sum(m.removed for m in marks)
    print(f"{out}: {n} marks by {', '.join(consoles) or 'nobody'} ({removed} removed ones left out)")
    return 0
