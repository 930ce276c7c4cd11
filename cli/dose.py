"""UV dose reports. ``save`` fetches each robot's dose layer over Zenoh (the queryable
``fleetlink/v1/<robot>/dose``) and its map (``fleetlink/v1/<robot>/map``, for the floor the dose is
judged on), sums the layers in the site frame and writes the report into a folder: ``dose.pgm`` and
``dose.png`` (the dose as a fraction of the target on the floor, north up), ``dose.csv`` (one line
per floor cell: x_m, y_m, dose_j_per_m2, at_target), ``summary.txt`` and ``summary.json`` (area at
the target, area below it, and where: the under-dosed regions). See docs/payload.md, "Dose layer".

Examples:
  fleetlink dose save --robot uvc-1 --robot uvc-2 --out out/dose --connect tcp/127.0.0.1:7447
  fleetlink dose save --robot uvc-1 --out out/kitchen --box 0 0 4 3     # only that rectangle's floor
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="dose_command", metavar="ACTION", required=True)
    save = sub.add_parser("save", help="fetch robots' dose layers over Zenoh and write the dose report")
    save.add_argument("--robot", action="append", required=True, help="robot id (repeatable)")
    save.add_argument("--out", required=True, help="folder for dose.pgm, dose.png, dose.csv, summary.txt/.json")
    save.add_argument(
        "--connect", action="append", default=[], metavar="ENDPOINT", help="zenoh endpoint to connect to (repeatable)"
    )
    save.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for each answer (default 5)")
    save.add_argument(
        "--box", type=float, nargs=4, metavar=("X1", "Y1", "X2", "Y2"), help="judge only the floor in this rectangle"
    )
    save.add_argument(
        "--target",
        type=float,
        metavar="MJ_CM2",
        help="judge against this dose in mJ/cm² (a round's own dose) instead of the robots' configured target",
    )
    save.add_argument(
        "--no-maps", action="store_true", help="judge the cells the lamps reached, not the robots' mapped floor"
    )
    save.set_defaults(_run=run_save)


def run(args: argparse.Namespace) -> int:  # pragma: no cover - argparse always sets a sub-action
    return int(args._run(args))


def run_save(args: argparse.Namespace) -> int:
    from fleetlink.agent.dose_share import fetch_dose
    from fleetlink.agent.mapping.share import fetch_map
    from fleetlink.links.zenoh import ZenohEndpoint
    from fleetlink.operator.dose import dose_report, save_report
    from fleetlink.shared import keys
    from fleetlink.shared.dose import j_m2
    from fleetlink.shared.dose_codec import SharedDose
    from fleetlink.shared.map_codec import SharedMap
    from fleetlink.shared.wire import WireError

    name = "fleetlink dose save"
    try:
        robots = [keys.check_robot_id(r) for r in dict.fromkeys(args.robot)]
    except ValueError as exc:
        print(f"{name}: {exc}", file=sys.stderr)
        return 2
    box: tuple[float, float, float, float] | None = None
    if args.box:
        box = (args.box[0], args.box[1], args.box[2], args.box[3])
    if box is not None and (box[0] == box[2] or box[1] == box[3]):
        print(f"{name}: --box: the rectangle's corners must differ in x and in y", file=sys.stderr)
        return 2
    if args.target is not None and not (math.isfinite(args.target) and args.target > 0):
        print(f"{name}: --target: the dose must be a number above 0 mJ/cm², got {args.target}", file=sys.stderr)
        return 2
    layers: dict[str, SharedDose] = {}
    maps: list[SharedMap] = []
    with ZenohEndpoint(connect=args.connect, label="zenoh-dose-save") as link:
        for robot in robots:
            snap = fetch_dose(link, robot, timeout=args.timeout)
            if snap is None:
                print(f"{name}: no dose layer from robot {robot!r} within {args.timeout:g} s", file=sys.stderr)
                continue
            try:
                layers[robot] = SharedDose.from_snapshot(snap)
            except WireError as exc:
                print(f"{name}: robot {robot!r}'s dose layer refused: {exc.reason}", file=sys.stderr)
                continue
            if args.no_maps:
                continue
            m = fetch_map(link, robot, timeout=args.timeout)
            if m is None:
                print(f"{name}: no map from robot {robot!r}: its floor is left out", file=sys.stderr)
                continue
            try:
                maps.append(SharedMap.from_snapshot(m))
            except ValueError as exc:
                print(f"{name}: robot {robot!r}'s map refused: {exc}", file=sys.stderr)
    if not layers:
        print(f"{name}: no dose layer to report on", file=sys.stderr)
        return 1
    try:
        report = dose_report(layers, maps, box, target_j_m2=None if args.target is None else j_m2(args.target))
        paths = save_report(report, Path(args.out))
    except (OSError, ValueError) as exc:
        print(f"{name}: {exc}", file=sys.stderr)
        return 1
    print(report.text(), end="")
    print(f"wrote {', '.join(str(p) for p in paths)}")
    return 0
