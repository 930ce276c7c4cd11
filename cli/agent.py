"""Run one robot's agent: `fleetlink agent --config robot.toml` (see deploy/robot.example.toml).

Talks to its control board (serial or socket://), listens for commands on Zenoh (primary) and
MQTT (fallback) at once, takes UWB fixes from MQTT, and publishes pose, state, events and acks on
both. Ctrl-C stops the robot and says OFFLINE.
"""

from __future__ import annotations

import argparse
import sys
import threading
from pathlib import Path

AGENT_SWITCH_INTERVAL_S = 0.001


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", type=Path, required=True, help="the robot's TOML configuration")
    parser.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds (default: run)")


def run(args: argparse.Namespace) -> int:
    from fleetlink.agent.config import ConfigError, load_agent_config
    from fleetlink.agent.runtime import AgentRuntime

    try:
        config = load_agent_config(args.config)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    # The agent is one robot's real-time process: its link threads, control loop and command
    # delivery share the GIL. Python hands it over every 5 ms by default, so under a flood a lease
    # holder's teleop waited 5 ms per hand-over behind busy link threads (bench/abuse.py); 1 ms
    # keeps the command lane and the control loop prompt for a little throughput.
    sys.setswitchinterval(AGENT_SWITCH_INTERVAL_S)
    agent = AgentRuntime(config)
    stop = threading.Event()
    try:
        agent.start()
        stop.wait(args.duration if args.duration > 0 else None)
    except KeyboardInterrupt:
        pass
    finally:
        agent.stop()
    return 0
