"""Serve the live fleet to Foxglove (or Lichtblick) over Foxglove's WebSocket protocol.

    fleetlink foxglove --zenoh-connect tcp/10.0.0.5:7447 --mqtt mqtt://10.0.0.5:1883 --host 0.0.0.0
    then, in Foxglove: Open connection -> Foxglove WebSocket -> ws://<this host>:8765

It joins the fleet as the flight recorder does (the same connection options, and ``--config``
takes a console TOML for them) and serves each robot's pose (``/foxglove/<robot>/pose``,
``foxglove.PoseInFrame``), the robots' maps and the fleet map (``/foxglove/<robot>/map``,
``/foxglove/fleet/map``, ``foxglove.Grid``), the fleet's UV dose layer (``/foxglove/fleet/dose``)
and the field's ground truth when it is on the wire, all in the site frame ``map``, until Ctrl-C,
SIGTERM or ``--duration``. See docs/foxglove.md.
"""

from __future__ import annotations

import argparse
import sys

from fleetlink.cli.record import add_connection_arguments, connection_settings, open_links, run_until_stopped


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--host", default="127.0.0.1", help="address to serve on (default 127.0.0.1; 0.0.0.0: all)")
    parser.add_argument("--port", type=int, default=None, help="WebSocket port (default 8765, Foxglove's)")
    parser.add_argument(
        "--grid-period", type=float, default=None,
        help="send a changing map or dose layer at most this often, s (default 1)",
    )  # fmt: skip
    add_connection_arguments(parser)
    parser.add_argument("--duration", type=float, help="stop after this many seconds (default: until Ctrl-C)")


def run(args: argparse.Namespace) -> int:
    from fleetlink.shared.clock import SystemClock
    from fleetlink.shared.config import ConfigError
    from fleetlink.site.foxglove_live import GRID_PERIOD_S
    from fleetlink.site.foxglove_server import DEFAULT_PORT, FoxgloveLive

    try:
        settings = connection_settings(args)
    except (ConfigError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.duration is not None and not args.duration > 0:
        print("error: --duration must be > 0", file=sys.stderr)
        return 2
    port = DEFAULT_PORT if args.port is None else args.port
    grid_period = GRID_PERIOD_S if args.grid_period is None else args.grid_period
    if not grid_period >= 0:
        print("error: --grid-period must be >= 0", file=sys.stderr)
        return 2
    clock = SystemClock()
    try:
        links = open_links(settings, "foxglove", clock)
        live = FoxgloveLive(links, clock, host=args.host, port=port, grid_period_s=grid_period).start()
    except Exception as exc:  # zenoh's ZError for bad endpoints, a port in use
        print(f"error: cannot start the Foxglove server: {exc}", file=sys.stderr)
        return 1
    print(f"serving the fleet on ws://{args.host}:{live.port} (Ctrl-C to stop)", file=sys.stderr, flush=True)
    try:
        run_until_stopped(clock, args.duration)
    finally:
        live.stop()
    core = live.core
    print(
        f"served {core.sent} messages from {len(core.robots)} robots"
        + (f"; refused {sum(core.rejected.values())} bad inputs" if core.rejected else "")
        + (f"; dropped {live.dropped} (fell behind)" if live.dropped else ""),
        file=sys.stderr,
    )
    return 0
