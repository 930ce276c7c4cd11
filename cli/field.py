"""The simulated field, in real time. For now: simulated control boards served on TCP, one agent-side
board link per robot talking to its board through real bytes, each robot wandering its room and
avoiding walls with its ultrasonic sensor, and their live board status on the terminal. Later
issues add lidars, UWB, the full agents and the operator console.

Stop with Ctrl-C, or give --duration.
"""

from __future__ import annotations

import argparse
import math
import sys
import threading


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--robots", type=int, default=2, help="how many robots (default 2)")
    parser.add_argument(
        "--duration", type=float, default=0.0, help="stop after this many seconds (default: run until Ctrl-C)"
    )
    parser.add_argument("--speed", type=float, default=0.25, help="cruise speed in m/s (default 0.25)")
    parser.add_argument("--refresh", type=float, default=4.0, help="status refreshes per second (default 4)")


def run(args: argparse.Namespace) -> int:
    from fleetlink.agent.board.session import BoardSession
    from fleetlink.agent.board.transport import SerialPort
    from fleetlink.field.board import BoardConfig, SimulatedBoard
    from fleetlink.field.board_server import BoardServer
    from fleetlink.field.floor import Floor
    from fleetlink.operator.board_status import render
    from fleetlink.shared.clock import SystemClock

    if args.robots < 1 or not math.isfinite(args.speed) or args.refresh <= 0:
        print("error: --robots must be >= 1, --speed finite, --refresh > 0", file=sys.stderr)
        return 2
    clock = SystemClock()
    servers: list[BoardServer] = []
    sessions: list[tuple[str, BoardSession]] = []
    try:
        for i in range(args.robots):
            floor = Floor.box(6.0, 4.0)
            floor.add_wall(3.0, 0.0, 3.0, 1.6)  # a half wall to steer around
            board = SimulatedBoard(
                BoardConfig(noise_seed=i, dock=(0.5, 0.5)), floor, pose=(1.0 + 0.4 * i, 2.0, 0.3 * i)
            )
            server = BoardServer(board, clock)
            port = server.serve_tcp()
            servers.append(server)
            url = f"socket://127.0.0.1:{port}"
            session = BoardSession(lambda url=url: SerialPort(url), clock, seed=i)
            session.start()
            sessions.append((f"robot-{i + 1} ({url})", session))
        stop = threading.Event()
        start = clock.now()
        tty = sys.stdout.isatty()
        while not stop.wait(1.0 / args.refresh):
            now = clock.now()
            for _, session in sessions:
                _wander(session, args.speed)
            lines = [
                f"fleetlink field: {len(sessions)} simulated robot(s), t = {now - start:6.1f} s   (Ctrl-C to stop)",
                "",
            ]
            for name, session in sessions:
                lines += [*render(name, session.snapshot, now), ""]
            if tty:
                sys.stdout.write("\x1b[H\x1b[2J" + "\n".join(lines) + "\n")
            else:
                sys.stdout.write("\n".join(lines) + "\n")
            sys.stdout.flush()
            if args.duration and now - start >= args.duration:
                break
    except KeyboardInterrupt:
        pass
    finally:
        for _, session in sessions:
            session.set_velocity(0.0, 0.0)
        for _, session in sessions:
            session.stop()
        for server in servers:
            server.stop()
    return 0


def _wander(session: object, speed: float) -> None:
    """A tiny reactive driver so the demo moves: cruise, turn away when the ultrasonic sees a wall."""
    from fleetlink.agent.board.session import BoardSession

    assert isinstance(session, BoardSession)
    snap = session.snapshot
    if not snap.connected or snap.sensors is None:
        return
    front = snap.sensors.distances[0]
    bumped = snap.bumpers is not None and (snap.bumpers.triggered(0) or snap.bumpers.triggered(1))
    if bumped:
        session.set_velocity(-0.1, 0.8)
    elif 0 < front < 0.6:
        session.set_velocity(0.0, 1.2)
    else:
        session.set_velocity(speed, 0.0)
