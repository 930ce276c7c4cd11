"""The VDA 5050 2.1 vehicle interface: every fleetlink robot as a VDA 5050 vehicle on MQTT.

Topics ``<interface>/v2/<manufacturer>/<robot>/{order,instantActions,state,visualization,
connection,factsheet}``; orders and instant actions from a master control become fleetlink orders
and instant actions (the bridge takes each driven robot's control lease, as a console does), sent
over Zenoh (primary) or MQTT (fallback). Every message is validated against the official 2.1.0
JSON schemas. See docs/vda5050.md.

Examples:
  fleetlink vda5050 --mqtt mqtt://127.0.0.1:1883 --zenoh-connect tcp/127.0.0.1:7447
  fleetlink vda5050 --mqtt mqtt://10.0.0.5:1883 --interface uagv --manufacturer fleetlink --robot uvc-1
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import threading

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--mqtt", dest="mqtt_url", default="mqtt://127.0.0.1:1883", help="the fleet's MQTT broker")
    parser.add_argument("--vda-mqtt", dest="vda_mqtt_url", help="the master control's broker (default: --mqtt)")
    parser.add_argument("--zenoh-connect", action="append", default=[], help="Zenoh endpoint to connect to (repeat)")
    parser.add_argument("--zenoh-listen", action="append", default=[], help="Zenoh endpoint to listen on (repeat)")
    parser.add_argument("--interface", default="uagv", help="VDA 5050 interfaceName, the topics' first level")
    parser.add_argument("--manufacturer", default="fleetlink", help="VDA 5050 manufacturer (topics and headers)")
    parser.add_argument("--map-id", default="site", help="the mapId the robots report and orders must use")
    parser.add_argument("--robot", action="append", default=[], help="serve only these robots (repeat; default all)")
    parser.add_argument("--sender", default="vda5050", help="the bridge's fleetlink login (sender id)")
    parser.add_argument("--state-period", type=float, default=5.0, help="seconds between unchanged states")
    parser.add_argument(
        "--max-vehicles", type=int, default=512, help="robots served at most (more are counted and logged once)"
    )


def run(args: argparse.Namespace) -> int:
    from fleetlink.shared.clock import SystemClock
    from fleetlink.site.vda5050 import open_bridge

    bridge = open_bridge(
        SystemClock(),
        mqtt_url=args.mqtt_url,
        vda_mqtt_url=args.vda_mqtt_url,
        zenoh_connect=args.zenoh_connect,
        zenoh_listen=args.zenoh_listen,
        sender=args.sender,
        manufacturer=args.manufacturer,
        interface=args.interface,
        map_id=args.map_id,
        robots=args.robot,
        state_period_s=args.state_period,
        max_vehicles=args.max_vehicles,
    )
    with bridge:
        log.info("VDA 5050 bridge up: %s/v2/%s/<robot>/...", args.interface, args.manufacturer)
        with contextlib.suppress(KeyboardInterrupt):
            threading.Event().wait()
    return 0
