"""Record every fleet message on both links into an MCAP file, or say what a recording holds.

    fleetlink record --out mission.mcap --zenoh-connect tcp/10.0.0.5:7447 --mqtt mqtt://10.0.0.5:1883
    fleetlink record --summary mission.mcap [--scan]

The recorder joins the fleet as the console does (the same connection options, and ``--config``
takes a console TOML for them) and records until Ctrl-C, SIGTERM or ``--duration``. Each wire
message goes to the channel ``/fleetlink/<link>/<topic>`` as JSON with its JSON Schema; poses and
maps also to Foxglove's schemas (``/foxglove/<robot>/pose``, ``/foxglove/<robot>/map``). Chunks are
zstd-compressed and closed at least every second: a crash loses at most the last one.
``--summary`` reads a file's summary section (its index and statistics) when it has one, and
every message when it has none (cut short by a crash) or with ``--scan``. See docs/recording.md.
"""

from __future__ import annotations

import argparse
import logging
import socket
import sys
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    what = parser.add_mutually_exclusive_group(required=True)
    what.add_argument("--out", type=Path, help="record into this MCAP file (overwritten)")
    what.add_argument("--summary", type=Path, metavar="FILE", help="print what a recording holds and exit")
    parser.add_argument(
        "--scan",
        action="store_true",
        help="with --summary: read every message (each chunk's CRC checked) instead of the file's summary section",
    )
    add_connection_arguments(parser)
    parser.add_argument("--duration", type=float, help="stop after this many seconds (default: until Ctrl-C)")
    parser.add_argument(
        "--chunk-age", type=float, default=None, help="close a chunk at least this often, s (default 0.75)"
    )
    parser.add_argument("--compression", choices=("zstd", "lz4"), default="zstd")


def add_connection_arguments(parser: argparse.ArgumentParser) -> None:
    """How a listener joins the fleet, as the console does (the recorder, ``fleetlink foxglove``)."""
    parser.add_argument("--config", type=Path, help="a console TOML file for the connection ([zenoh], [mqtt], login)")
    parser.add_argument("--zenoh-connect", action="append", default=None, help="Zenoh endpoint to connect to (repeat)")
    parser.add_argument("--zenoh-listen", action="append", default=None, help="Zenoh endpoint to listen on (repeat)")
    parser.add_argument("--mqtt", dest="mqtt_url", help="MQTT broker url (default mqtt://127.0.0.1:1883)")
    parser.add_argument("--user", help="log in to the router and the broker as this user")
    parser.add_argument("--password-file", type=Path, help="the --user's password (one line)")
    parser.add_argument("--ca-file", help="the site CA, for tls/ Zenoh endpoints and mqtts:// urls")


def run(args: argparse.Namespace) -> int:
    from fleetlink.site.recorder import RecordingError, summarise

    if args.summary is not None:
        try:
            print(summarise(args.summary, index=not args.scan).text(str(args.summary)))
        except RecordingError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        return 0
    if args.scan:
        print("error: --scan goes with --summary", file=sys.stderr)
        return 2
    return record(args)


def connection_settings(args: argparse.Namespace) -> Any:
    """The console's settings from ``add_connection_arguments``' options (``ConfigError`` or
    ``ValueError`` for bad ones)."""
    from fleetlink.cli.console import load_settings

    for name in ("operator", "read_only", "marks_file", "audit_log"):
        setattr(args, name, None)  # the console's options a listener has not: its defaults
    return load_settings(args)


def run_until_stopped(clock: Any, duration: float | None) -> None:
    """Wait on ``clock`` for ``duration`` seconds (None: until Ctrl-C); Ctrl-C ends it quietly."""
    deadline = None if duration is None else clock.now() + duration
    try:
        while deadline is None or clock.now() < deadline:
            clock.sleep(0.2 if deadline is None else max(0.0, min(0.2, deadline - clock.now())))
    except KeyboardInterrupt:
        pass


def open_links(settings: Any, role: str, clock: Any) -> list[Any]:
    """The listener's Zenoh and MQTT endpoints (not started), logged in as ``settings`` say."""
    from fleetlink.cli.console import mqtt_client_settings
    from fleetlink.site.recorder import open_recorder_links

    auth: dict[str, object] = {}
    if settings.user is not None:
        auth = {"username": settings.user, "password": settings.password}
        if not settings.zenoh_listen:
            auth["mode"] = "client"
    if settings.ca_file is not None:
        auth["root_ca"] = settings.ca_file
    return open_recorder_links(
        mqtt_url=settings.mqtt_url,
        mqtt=mqtt_client_settings(settings),
        zenoh_listen=settings.zenoh_listen,
        zenoh_connect=settings.zenoh_connect,
        zenoh_auth=auth,
        client_id=f"{role}-{socket.gethostname()}"[:64],
        clock=clock,
        role=role,
    )


def record(args: argparse.Namespace) -> int:
    from fleetlink.shared.clock import SystemClock
    from fleetlink.shared.config import ConfigError
    from fleetlink.site.recorder import CHUNK_AGE_S, Recorder, use_recorder_runtime

    try:
        settings = connection_settings(args)
    except (ConfigError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.duration is not None and not args.duration > 0:
        print("error: --duration must be > 0", file=sys.stderr)
        return 2
    clock = SystemClock()
    use_recorder_runtime()  # (one zenoh receive thread: before the first session opens)
    try:
        links = open_links(settings, "recorder", clock)
        recorder = Recorder(
            args.out, links, clock, chunk_age_s=args.chunk_age or CHUNK_AGE_S, compression=args.compression
        ).start()
    except Exception as exc:  # zenoh raises its own ZError for bad endpoints; a file we cannot write
        print(f"error: cannot start the recorder: {exc}", file=sys.stderr)
        return 1
    print(f"recording to {args.out} (Ctrl-C to stop)", file=sys.stderr, flush=True)
    try:
        run_until_stopped(clock, args.duration)
    finally:
        recorder.stop()
    core = recorder.core
    print(
        f"recorded {recorder.written} messages from {len(core.robots)} robots to {args.out}"
        + (f"; refused {sum(core.rejected.values())} bad inputs" if core.rejected else "")
        + (f"; dropped {recorder.dropped} (disk too slow)" if recorder.dropped else ""),
        file=sys.stderr,
    )
    return 0
