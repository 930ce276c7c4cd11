"""Maps. ``save`` fetches a robot's map over Zenoh (the queryable ``fleetlink/v1/<robot>/map``) and
writes it as a ROS map_server map (PGM + YAML); ``load`` reads a map_server map and prints a summary
(``fleetlink field`` takes the same file as a floor plan); ``replay`` builds a map offline from a
CARMEN log (FLASER, ROBOTLASER1, ODOM lines; .gz accepted), writing DIR/map.pgm, DIR/map.yaml and
DIR/trajectory.txt (``ipc_timestamp x y theta`` per scan, the timestamp copied from the log).

Examples:
  fleetlink map save --robot r1 --out maps/r1 --connect tcp/127.0.0.1:7447
  fleetlink map load maps/r1/map.yaml
  fleetlink map replay ../shared/data/intel-corrected.log.gz --out out/intel
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="map_command", metavar="ACTION", required=True)

    save = sub.add_parser("save", help="fetch a robot's map over Zenoh and write PGM + YAML")
    save.add_argument("--robot", required=True, help="robot id")
    save.add_argument("--out", required=True, help="folder (or base path) for map.pgm + map.yaml")
    save.add_argument(
        "--connect", action="append", default=[], metavar="ENDPOINT", help="zenoh endpoint to connect to (repeatable)"
    )
    save.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for the map (default 5)")
    save.set_defaults(_run=run_save)

    load = sub.add_parser("load", help="read a map_server map (YAML) and print a summary")
    load.add_argument("yaml", help="the map's YAML file")
    load.set_defaults(_run=run_load)

    rep = sub.add_parser("replay", help="build a map from a CARMEN log")
    rep.add_argument("log", help="CARMEN log (plain or .gz)")
    rep.add_argument("--out", required=True, help="output folder: map.pgm, map.yaml, trajectory.txt")
    rep.add_argument("--resolution", type=float, default=0.05, help="metres per cell (default 0.05)")
    rep.add_argument("--no-matching", action="store_true", help="map at the odometry poses (no scan matching)")
    rep.set_defaults(_run=run_replay)


def run(args: argparse.Namespace) -> int:  # pragma: no cover - argparse always sets a sub-action
    return int(args._run(args))


def run_save(args: argparse.Namespace) -> int:
    from fleetlink.agent.mapping.share import fetch_map
    from fleetlink.field.mapserver import write_map
    from fleetlink.links.zenoh import ZenohEndpoint
    from fleetlink.shared import keys
    from fleetlink.shared.map_codec import decode_cells

    try:
        keys.check_robot_id(args.robot)
    except ValueError as exc:
        print(f"fleetlink map save: {exc}", file=sys.stderr)
        return 2
    with ZenohEndpoint(connect=args.connect, label="zenoh-map-save") as link:
        snap = fetch_map(link, args.robot, timeout=args.timeout)
    if snap is None:
        print(f"fleetlink map save: no map from robot {args.robot!r} within {args.timeout:g} s", file=sys.stderr)
        return 1
    cells = decode_cells(snap.cells, snap.width, snap.height)
    out = Path(args.out)
    if out.suffix not in (".yaml", ".yml", ".pgm"):
        out.mkdir(parents=True, exist_ok=True)  # a folder: out/map.pgm + out/map.yaml
    yaml = write_map(cells, snap.resolution, (snap.origin_x, snap.origin_y, 0.0), out, "map")
    print(f"{yaml} ({snap.width} x {snap.height} cells at {snap.resolution:g} m, version {snap.version})")
    return 0


def run_load(args: argparse.Namespace) -> int:
    import numpy as np

    from fleetlink.field.mapserver import MapError, read_map

    try:
        m = read_map(args.yaml)
    except MapError as exc:
        print(f"fleetlink map load: {exc}", file=sys.stderr)
        return 1
    g = m.grid
    occ, free, unknown = int((g == 100).sum()), int((g == 0).sum()), int((g == -1).sum())
    print(
        f"{m.source}: {m.width} x {m.height} cells at {m.resolution:g} m ({m.width * m.resolution:.2f} x {m.height * m.resolution:.2f} m)"
    )
    print(f"origin {list(m.origin)}, mode {m.mode}, negate {int(m.negate)}")
    print(f"occupied {occ}, free {free}, unknown {unknown} ({100.0 * unknown / max(1, g.size):.1f} % unknown)")
    if occ:
        rows, cols = np.nonzero(g == 100)
        x0, y0 = m.cell_center(int(cols.min()), int(rows.min()))
        x1, y1 = m.cell_center(int(cols.max()), int(rows.max()))
        print(f"walls span x {x0:.2f}..{x1:.2f} m, y {y0:.2f}..{y1:.2f} m")
    return 0


def run_replay(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from fleetlink.agent.mapping.carmen import CarmenStats, open_log, read_records
    from fleetlink.agent.mapping.grid import GridConfig
    from fleetlink.agent.mapping.mapper import MapperConfig
    from fleetlink.agent.mapping.replay import format_trajectory, replay
    from fleetlink.field.mapserver import write_map

    if not args.resolution > 0:
        print("fleetlink map replay: --resolution must be > 0", file=sys.stderr)
        return 2
    cfg = MapperConfig(grid=GridConfig(resolution=args.resolution), matching=not args.no_matching)
    stats = CarmenStats()
    try:
        with open_log(args.log) as f:
            result = replay(read_records(f, stats), replace(cfg))
    except OSError as exc:
        print(f"fleetlink map replay: cannot read {args.log}: {exc}", file=sys.stderr)
        return 1
    for example in stats.examples:
        log.warning("%s: skipped %s", args.log, example)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "trajectory.txt").write_text(format_trajectory(result.rows), encoding="ascii", errors="replace")
    m = result.mapper
    if m.grid.empty:
        print(f"fleetlink map replay: no usable scans in {args.log} ({stats.summary()})", file=sys.stderr)
        return 1
    cells, res, origin = m.occupancy()
    write_map(cells, res, (origin[0], origin[1], 0.0), out, "map")
    print(f"{args.log}: {stats.summary()}")
    print(
        f"{len(result.rows)} scans mapped ({m.matched} matched, {m.fallbacks} on odometry); wrote {out}/map.pgm, map.yaml, trajectory.txt"
    )
    return 0
