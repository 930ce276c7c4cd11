"""A real ``fleetlink agent`` process on a simulated board served over TCP, for drills that signal,
flood or measure the process itself."""

from __future__ import annotations

import contextlib
import json
import subprocess
import sys
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

from fleetlink.field.board import SimulatedBoard
from fleetlink.field.device_server import DeviceServer
from fleetlink.shared.clock import SystemClock
from tests.harness.mosquitto import free_port

__all__ = ["AgentProcess", "agent_process"]


@dataclass
class AgentProcess:
    proc: subprocess.Popen[bytes]
    board: SimulatedBoard
    zenoh_endpoint: str
    """Where the agent's Zenoh peer listens (connect to it)."""


@contextlib.contextmanager
def agent_process(
    folder: Path, mqtt_port: int, *, output: int | None = subprocess.DEVNULL, operators: Sequence[str] = ()
) -> Iterator[AgentProcess]:
    """Robot ``r1``: its board served on a free TCP port, Zenoh listening on another, MQTT on the
    given broker. ``output``: where the process's stdout and stderr go (``subprocess.PIPE`` to read
    them); ``operators``: its allowlist (empty: anyone). Killed on the way out if it is still running."""
    board = SimulatedBoard()
    server = DeviceServer(board, SystemClock(), name="board")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    cfg = folder / "robot.toml"
    cfg.write_text(
        f'robot = "r1"\nboard = "socket://127.0.0.1:{server.serve_tcp()}"\noperators = {json.dumps(list(operators))}\n'
        f'[zenoh]\nlisten = ["{endpoint}"]\n[mqtt]\nurl = "mqtt://127.0.0.1:{mqtt_port}"\n'
    )
    proc = subprocess.Popen(
        [sys.executable, "-m", "fleetlink.cli.main", "agent", "--config", str(cfg)],
        stdout=output,
        stderr=subprocess.STDOUT if output is not None else None,
    )
    try:
        yield AgentProcess(proc, board, endpoint)
    finally:
        if proc.poll() is None:
            proc.kill()
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(10)
        server.stop()
