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
