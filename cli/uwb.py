"""The UWB gateway: true poses from the field (Zenoh) in, UWB fixes out over MQTT, like a real RTLS.

For every tag (a robot, per the config's tag mapping) it simulates two-way ranges to the anchors
at the configured rate, solves a robust multilateration, and publishes the native fleetlink fix
(msgpack, ``fleetlink/v1/<robot>/uwb``), the raw ranges (``fleetlink/v1/<robot>/uwb/ranges``) and
a Qorvo DWM1001 PANS location (JSON, ``dwm/node/<tag>/uplink/location``), plus a retained status
with a last will on ``fleetlink/uwb/<gateway>/status``. See docs/protocols/uwb.md.

Examples:
  fleetlink uwb --config uwb.toml
  fleetlink uwb --config uwb.toml --seconds 30
"""

from __future__ import annotations

import argparse
import sys


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--config", required=True, metavar="FILE", help="the gateway's TOML configuration")
    parser.add_argument("--seconds", type=float, default=None, help="stop after this long (default: until Ctrl-C)")
    parser.add_argument("--check", action="store_true", help="validate the configuration, print a summary, exit")


def run(args: argparse.Namespace) -> int:
    from fleetlink.field.scenario import site_geometry
    from fleetlink.positioning.config import ConfigError, load_config
    from fleetlink.positioning.publisher import UwbGateway
    from fleetlink.shared.clock import SystemClock

    try:
        config = load_config(args.config, site=site_geometry)
    except (ConfigError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    tags = ", ".join(f"{t.id}->{t.robot}" for t in config.tags) or "auto (tag id = robot id)"
    print(
        f"gateway {config.gateway_id}: {len(config.anchors)} anchors, tags {tags}, {config.rate_hz:g} Hz, "
        f"solver {config.solver}, MQTT {config.mqtt.host}:{config.mqtt.port}"
    )
    if args.check:
        return 0
    clock = SystemClock()
    with UwbGateway(config, clock) as gw:
        deadline = None if args.seconds is None else clock.now() + args.seconds
        next_report = clock.now() + 5.0
        while deadline is None or clock.now() < deadline:
            clock.sleep(0.2)
            if clock.now() >= next_report:
                next_report += 5.0
                with gw._lock:
                    counts = dict(sorted(gw.core.counts.items()))
                state = "connected" if gw.up else "NOT connected to MQTT"
                print(f"{state}; {counts}", flush=True)
    return 0
