"""Maps. ``save`` fetches a robot's map over Zenoh (the queryable ``fleetlink/v1/<robot>/map``) and
writes it as a ROS map_server map (PGM + YAML); ``load`` reads a map_server map and prints a summary
(``fleetlink field`` takes the same file as a floor plan); ``replay`` builds a map offline from a
CARMEN log (FLASER, ROBOTLASER1, RAWLASER1, ODOM lines; .gz accepted), writing DIR/map.pgm, DIR/map.yaml,
DIR/trajectory.txt (``ipc_timestamp x y theta`` per scan, the timestamp copied from the log) and
DIR/corrected.log (the input log with each scan's pose replaced by the mapper's: the SLAM result as
the Freiburg ``metricEvaluator`` reads it). ``relations`` writes a complete relation set (Kümmerle
et al. 2009) from a corrected log's poses; ``score`` scores a trajectory (``trajectory.txt`` or a
corrected CARMEN log) against one (mean ± sd translational and rotational error, all pairs, local
pairs and revisits).

Examples:
  fleetlink map save --robot r1 --out maps/r1 --connect tcp/127.0.0.1:7447
  fleetlink map load maps/r1/map.yaml
  fleetlink map replay ../shared/data/intel-corrected.log.gz --out out/intel
  fleetlink map relations --log ../shared/data/intel-corrected.log.gz --out out/intel.relations
  fleetlink map score --trajectory out/intel/trajectory.txt --relations out/intel.relations
  fleetlink map score --trajectory out/intel/corrected.log --relations out/intel.relations
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from pathlib import Path

log = logging.getLogger(__name__)

PROGRESS_SCANS = 1000
"""``replay`` says on stderr how many scans it has mapped every this many (a long log takes minutes)."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="map_command", metavar="ACTION", required=True)

    save = sub.add_parser("save", help="fetch a robot's map (or the fleet map) over Zenoh and write PGM + YAML")
    who = save.add_mutually_exclusive_group(required=True)
    who.add_argument("--robot", help="robot id")
    who.add_argument(
        "--fleet", action="store_true", help="the fleet map (served by the console, or by `fleetlink map fleet`)"
    )
    save.add_argument("--out", required=True, help="folder (or base path) for map.pgm + map.yaml")
    save.add_argument(
        "--connect", action="append", default=[], metavar="ENDPOINT", help="zenoh endpoint to connect to (repeatable)"
    )
    save.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for the map (default 5)")
    save.set_defaults(_run=run_save)

    fl = sub.add_parser("fleet", help="build the fleet map from every robot's map and serve it (a site with a router)")
    fl.add_argument(
        "--connect", action="append", default=[], metavar="ENDPOINT", help="zenoh endpoint to connect to (repeatable)"
    )
    fl.add_argument("--period", type=float, default=2.0, help="seconds between builds while maps change (default 2)")
    fl.set_defaults(_run=run_fleet)

    load = sub.add_parser("load", help="read a map_server map (YAML) and print a summary")
    load.add_argument("yaml", help="the map's YAML file")
    load.set_defaults(_run=run_load)

    rep = sub.add_parser("replay", help="build a map from a CARMEN log")
    rep.add_argument("log", help="CARMEN log (plain or .gz)")
    rep.add_argument("--out", required=True, help="output folder: map.pgm, map.yaml, trajectory.txt, corrected.log")
    rep.add_argument("--resolution", type=float, default=0.05, help="metres per cell (default 0.05)")
    rep.add_argument("--no-matching", action="store_true", help="map at the odometry poses (no scan matching)")
    rep.add_argument(
        "--no-closure", action="store_true", help="no loop closure: the front end's poses as they were mapped"
    )
    rep.add_argument(
        "--open-space",
        action="store_true",
        help="every submap drawn with its surfaces filled and large corrections asked a higher score there (by"
        " default only submaps whose walls were seen 5 m off or more: halls, outdoors; docs/mapping.md, 'Open"
        " spaces')",
    )
    rep.add_argument(
        "--long-loops",
        action="store_true",
        help="for loops hundreds of metres long: each submap searched in a window grown with its own drift from"
        " the robot, three checks a node (docs/mapping.md, 'Against the published relations': MIT's Killian Court)",
    )
    rep.set_defaults(_run=run_replay)

    rel = sub.add_parser("relations", help="write a complete relation set from a corrected CARMEN log")
    rel.add_argument(
        "--log",
        required=True,
        metavar="LOG",
        help="corrected CARMEN log (plain or .gz): its scan poses are the reference",
    )
    rel.add_argument(
        "--out", required=True, metavar="FILE", help="relations file to write (t1 t2 x y z roll pitch yaw per line)"
    )
    rel.add_argument(
        "--max-distance", type=float, default=3.0, metavar="M", help="pair scans at most M metres apart (default 3)"
    )
    rel.add_argument(
        "--min-overlap",
        type=float,
        default=0.5,
        metavar="F",
        help="pair scans when this share of one's endpoints lies in the other's view (0..1, default 0.5)",
    )
    rel.add_argument(
        "--match",
        action="store_true",
        help="measure each relation again by matching its two scans and keep only the unambiguous ones"
        " (as the published Freiburg relations were made; docs/mapping.md)",
    )
    rel.add_argument(
        "--by-index",
        action="store_true",
        help="name scans by their order in the log (0, 1, ...) instead of their times: for corrected logs"
        " whose scans share one time (written with %%g, or all 0); score with --by-index too",
    )
    rel.set_defaults(_run=run_relations)

    sco = sub.add_parser("score", help="score a trajectory against relations (relation errors)")
    sco.add_argument(
        "--trajectory",
        required=True,
        metavar="FILE",
        help="t x y theta per line (replay's trajectory.txt), or a corrected CARMEN log (replay's corrected.log)",
    )
    sco.add_argument("--relations", required=True, metavar="FILE", help="t1 t2 x y z roll pitch yaw per line")
    sco.add_argument(
        "--by-index",
        action="store_true",
        help="the relations name scans by index (written by relations --by-index): the trajectory's rows,"
        " or the corrected log's scans, are taken in order as scans 0, 1, ...; local means fewer than 20"
        " scans apart",
    )
    sco.add_argument("--json", metavar="FILE", help="also write the figures as JSON")
    sco.set_defaults(_run=run_score)


def run(args: argparse.Namespace) -> int:  # pragma: no cover - argparse always sets a sub-action
    return int(args._run(args))


def run_save(args: argparse.Namespace) -> int:
    from fleetlink.agent.mapping.share import fetch_map
    from fleetlink.field.mapserver import write_map
    from fleetlink.links.zenoh import ZenohEndpoint
    from fleetlink.shared import keys
    from fleetlink.shared.map_codec import decode_cells

    robot = keys.FLEET_MAP if args.fleet else args.robot
    try:
        keys.check_robot_id(robot)
    except ValueError as exc:
        print(f"fleetlink map save: {exc}", file=sys.stderr)
        return 2
    with ZenohEndpoint(connect=args.connect, label="zenoh-map-save") as link:
        snap = fetch_map(link, robot, timeout=args.timeout)
    if snap is None:
        what = (
            "no fleet map (is a console or `fleetlink map fleet` running?)"
            if args.fleet
            else f"no map from robot {robot!r}"
        )
        print(f"fleetlink map save: {what} within {args.timeout:g} s", file=sys.stderr)
        return 1
    cells = decode_cells(snap.cells, snap.width, snap.height)
    out = Path(args.out)
    if out.suffix not in (".yaml", ".yml", ".pgm"):
        out.mkdir(parents=True, exist_ok=True)  # a folder: out/map.pgm + out/map.yaml
    yaml = write_map(cells, snap.resolution, (snap.origin_x, snap.origin_y, 0.0), out, "map")
    print(f"{yaml} ({snap.width} x {snap.height} cells at {snap.resolution:g} m, version {snap.version})")
    return 0


def run_fleet(args: argparse.Namespace) -> int:
    import signal
    import threading

    from fleetlink.agent.mapping.share import MapShare, fetch_map
    from fleetlink.links.zenoh import ZenohEndpoint
    from fleetlink.operator.fleet import FleetModel
    from fleetlink.operator.maps import MapFetcher, MapFollower
    from fleetlink.shared import keys, wire
    from fleetlink.shared.clock import SystemClock
    from fleetlink.shared.messages import MapUpdate, State
    from fleetlink.site.fleetmap import FleetMapService

    if not (args.period > 0):
        print("fleetlink map fleet: --period must be > 0", file=sys.stderr)
        return 2
    clock = SystemClock()
    lock = threading.Lock()
    follower = MapFollower(FleetModel("fleet-map"))
    rejected = 0
    done = threading.Event()

    def hear(key: str, payload: bytes) -> None:
        nonlocal rejected
        try:
            msg = wire.decode_key(key, payload)
        except wire.WireError as exc:
            rejected += 1
            if rejected == 1:
                log.warning("fleet map: rejected %s: %s (further rejections counted)", key, exc.reason)
            return
        with lock:
            if isinstance(msg, State) and msg.header.robot != keys.FLEET_MAP:
                follower.fleet.robot(msg.header.robot)  # a robot is heard: its map is wanted
            elif isinstance(msg, MapUpdate):
                follower.on_update(msg)

    with ZenohEndpoint(connect=args.connect, label="zenoh-fleet-map") as link:
        share = MapShare(link, keys.FLEET_MAP, clock, sender="fleet-map")
        share.start()

        def built(result: object) -> None:
            log.info("fleet map version %s built", getattr(result, "version", "?"))

        service = FleetMapService(follower, lock, clock, share=share, period_s=args.period, on_built=built, query=link)
        link.subscribe(f"{keys.PREFIX}/*/{State.TOPIC}", hear)
        link.subscribe(f"{keys.PREFIX}/*/{MapUpdate.TOPIC}", hear)
        fetcher = MapFetcher(follower, lambda r: fetch_map(link, r), clock, lock, after_poll=service.step).start()
        signal.signal(signal.SIGTERM, lambda *_: done.set())
        print("fleetlink map fleet: serving fleetlink/v1/fleet/map; Ctrl-C stops", flush=True)
        try:
            done.wait()
        except KeyboardInterrupt:
            pass
        finally:
            fetcher.stop()
            share.stop()
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

    from fleetlink.agent.mapping.carmen import CarmenStats, corrected_lines, open_log, read_records
    from fleetlink.agent.mapping.closure import replay_closer
    from fleetlink.agent.mapping.grid import GridConfig
    from fleetlink.agent.mapping.mapper import MapperConfig
    from fleetlink.agent.mapping.replay import format_trajectory, replay
    from fleetlink.field.mapserver import write_map

    if not args.resolution > 0:
        print("fleetlink map replay: --resolution must be > 0", file=sys.stderr)
        return 2
    cfg = MapperConfig(grid=GridConfig(resolution=args.resolution), matching=not args.no_matching)
    closer = replay_closer(open_space_fill=args.open_space, long_loops_search=args.long_loops)
    cfg = replace(cfg, closer=None if args.no_closure else closer)
    stats = CarmenStats()

    def progress(stage: str, n: int) -> None:
        # On stderr, so the summary on stdout stays what it was; a long log takes minutes.
        if stage == "final":
            print(f"{args.log}: final pass over {n} nodes", file=sys.stderr, flush=True)
        elif n % PROGRESS_SCANS == 0:
            print(f"{args.log}: {n} scans mapped", file=sys.stderr, flush=True)

    try:
        with open_log(args.log) as f:
            result = replay(read_records(f, stats), cfg, progress=progress)
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
    try:
        with open_log(args.log) as f, (out / "corrected.log").open("w", encoding="utf-8", newline="") as w:
            w.writelines(corrected_lines(f, dict(zip(result.lines, (p for _, p in result.rows), strict=True))))
    except (OSError, ValueError) as exc:  # the log changed under us, or cannot be read twice
        print(f"fleetlink map replay: cannot write {out}/corrected.log: {exc}", file=sys.stderr)
        return 1
    print(f"{args.log}: {stats.summary()}")
    mx, my, mth = m.config.mount
    if (mx, my, mth) != (0.0, 0.0, 0.0):
        print(
            f"laser mounted at ({mx:.3f}, {my:.3f}) m, {math.degrees(mth):.1f} deg on the robot: trajectory.txt holds"
            " the robot's pose, as corrected.log's robot fields do (its laser fields: the laser's)"
        )
    closed = ""
    if m.closer is not None:
        st = m.closer.stats
        closed = (
            f"; {len(m.closer)} nodes, {st.accepted} loop closures of {st.attempts} checked,"
            f" final pass {st.final_edges - st.final_pairs} submap matches and {st.final_pairs} scan pairs"
            f" ({len(m.closer.closures)} edges kept"
            + (f"; {st.final_behind} refused, walls seen from behind" if st.final_behind else "")
            + ")"
            + (
                f"; {st.conflicts_dropped} online closures let go, the rest of the graph did not bear them out"
                f" ({st.conflicts_online} as it mapped, {st.conflicts_dropped - st.conflicts_online} before the"
                " final pass)"
                if st.conflicts_dropped
                else ""
            )
        )
        if st.odometry_edges:  # what the log's odometry was found worth, and so weighed at
            closed += f", the odometry's {st.odometry_edges} steps held at {100 * st.odometry_sd_xy:.1f} cm"
    print(
        f"{len(result.rows)} scans mapped ({m.matched} matched, {m.fallbacks} on odometry{closed});"
        f" wrote {out}/map.pgm, map.yaml, trajectory.txt, corrected.log"
    )
    return 0


def run_relations(args: argparse.Namespace) -> int:
    from fleetlink.agent.mapping.carmen import CarmenStats, LaserRecord, open_log, read_records
    from fleetlink.agent.mapping.relations import (
        DEFAULT_LOCAL_S,
        format_relations,
        generate_relations,
        indistinct_times,
    )

    name = "fleetlink map relations"
    if not (math.isfinite(args.max_distance) and args.max_distance > 0):
        print(f"{name}: --max-distance must be a number of metres above 0, got {args.max_distance}", file=sys.stderr)
        return 2
    if not 0.0 <= args.min_overlap <= 1.0:
        print(f"{name}: --min-overlap must be a share within 0..1, got {args.min_overlap}", file=sys.stderr)
        return 2
    stats = CarmenStats()
    try:
        with open_log(args.log) as f:
            scans = [r for r in read_records(f, stats) if isinstance(r, LaserRecord)]
    except OSError as exc:
        print(f"{name}: cannot read {args.log}: {exc}", file=sys.stderr)
        return 1
    for example in stats.examples:
        log.warning("%s: skipped %s", args.log, example)
    if len(scans) < 2:
        print(f"{name}: fewer than two scans in {args.log} ({stats.summary()})", file=sys.stderr)
        return 1
    times = [float(i) for i in range(len(scans))] if args.by_index else [r.timestamp for r in scans]
    problem = indistinct_times(times)
    if problem:
        print(f"{name}: {args.log}: scan {problem}; name scans by index with --by-index", file=sys.stderr)
        return 1
    # Each record's own maximum means "no return" (NaN here), so one maximum range serves them all.
    ranges = [r.measured() for r in scans]
    relations = generate_relations(
        times,
        [r.pose for r in scans],
        max_distance_m=args.max_distance,
        min_overlap=args.min_overlap,
        scans=[(d, r.angles) for d, r in zip(ranges, scans, strict=True)],
        max_range=max(r.max_range for r in scans),
        mount=scans[0].laser_offset,  # one mount for the log (ROBOTLASER1 could vary it per record)
    )
    if args.match:
        from fleetlink.agent.mapping.pairmatch import match_relations

        matched = match_relations(
            relations,
            times,
            [(d, r.angles) for d, r in zip(ranges, scans, strict=True)],
            max_range=max(r.max_range for r in scans),
            mount=scans[0].laser_offset,
        )
        print(matched.summary())
        relations = matched.relations
    try:
        Path(args.out).write_text(format_relations(relations), encoding="ascii")
    except OSError as exc:
        print(f"{name}: cannot write {args.out}: {exc}", file=sys.stderr)
        return 1
    local = sum(abs(r.t2 - r.t1) < DEFAULT_LOCAL_S for r in relations)
    unit = "scans" if args.by_index else "s"
    print(f"{args.log}: {stats.summary()}")
    print(
        f"{len(relations)} relations from {len(scans)} scans ({local} within {DEFAULT_LOCAL_S:g} {unit},"
        f" {len(relations) - local} revisits); wrote {args.out}"
        + ("; its times are scan indices" if args.by_index else "")
    )
    return 0


def run_score(args: argparse.Namespace) -> int:
    import json

    from fleetlink.agent.mapping.carmen import LaserRecord, open_log, read_records
    from fleetlink.agent.mapping.relations import (
        format_score,
        indistinct_times,
        parse_relations,
        parse_trajectory,
        score,
    )

    name = "fleetlink map score"
    try:
        with open_log(args.trajectory) as f:
            lines = f.readlines()
        if any(line.split(None, 1)[:1] in (["FLASER"], ["ROBOTLASER1"]) for line in lines):
            # A corrected CARMEN log (replay's corrected.log, or any SLAM result in that form).
            scans = [r for r in read_records(lines) if isinstance(r, LaserRecord)]
            times, poses = [r.timestamp for r in scans], [r.pose for r in scans]
        else:
            times, poses = parse_trajectory(lines)
        if args.by_index:
            times = [float(i) for i in range(len(poses))]
    except (OSError, ValueError) as exc:
        print(f"{name}: cannot read {args.trajectory}: {exc}", file=sys.stderr)
        return 1
    try:
        with open(args.relations, encoding="utf-8", errors="replace") as f:
            relations = parse_relations(f)
    except (OSError, ValueError) as exc:
        print(f"{name}: cannot read {args.relations}: {exc}", file=sys.stderr)
        return 1
    if not relations:
        print(f"{name}: no relations in {args.relations}", file=sys.stderr)
        return 1
    problem = indistinct_times(times)
    if problem:
        print(f"{name}: {args.trajectory}: {problem}; name scans by index with --by-index", file=sys.stderr)
        return 1
    try:
        result = score(times, poses, relations)
    except ValueError as exc:
        print(f"{name}: {args.trajectory}: {exc}", file=sys.stderr)
        return 1
    print(format_score(result, "scans" if args.by_index else "s"), end="")
    if args.json:
        doc = {
            "trajectory": args.trajectory,
            "relations": args.relations,
            "by_index": args.by_index,
            **result.as_dict(),
        }
        try:
            Path(args.json).write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
        except OSError as exc:
            print(f"{name}: cannot write {args.json}: {exc}", file=sys.stderr)
            return 1
    if result.count == 0:
        print(f"{name}: none of the {len(relations)} relations' times is in {args.trajectory}", file=sys.stderr)
        return 1
    return 0
