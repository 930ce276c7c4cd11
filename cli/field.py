"""The simulated field.

Without an action it starts the demo in real time: the built-in "demo" scenario (or --scenario),
every robot's control board and lidar served on TCP like real hardware, an agent-side board link
per robot talking to its board through real bytes, ground truth published on Zenoh under
fleetlink/v1/sim/<robot>/truth, and each robot's live board status on the terminal. Stop with
Ctrl-C, or give --duration.

`fleetlink field --secure` runs it all as a secured site would (field/secure.py): deploy/'s
Mosquitto and Zenoh router with generated passwords and ACLs (TLS with a throwaway CA when openssl
is there), agents logged in as their robot ids, the UWB gateway as uwb-gateway, ground truth as
sim, the console as the operator; it prints where the credentials are so another console can join.

`fleetlink field run SCENARIO --lockstep --out DIR` runs a scenario in simulated time, as fast as
the CPU allows, and writes the robots' true trajectories (see docs/field-scenarios.md).
"""

from __future__ import annotations

import argparse
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from fleetlink.agent.board.transport import Port
    from fleetlink.field.plans import FloorPlan
    from fleetlink.field.scenario import Scenario

SCENARIOS = Path(__file__).resolve().parent.parent / "field" / "scenarios"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--scenario", default="demo", help="a built-in scenario name or a scenario file (default: demo)"
    )
    parser.add_argument(
        "--duration", type=float, default=0.0, help="stop after this many seconds (default: until Ctrl-C)"
    )
    parser.add_argument("--refresh", type=float, default=4.0, help="status refreshes per second (default 4)")
    parser.add_argument("--pty", action="store_true", help="serve boards and lidars on pseudo-terminals instead of TCP")
    parser.add_argument(
        "--zenoh-listen",
        default="tcp/127.0.0.1:7447",
        help="Zenoh endpoint for ground truth (default tcp/127.0.0.1:7447; 'none' disables publishing)",
    )
    parser.add_argument(
        "--console",
        choices=("auto", "on", "off"),
        default="auto",
        help="run an agent per robot and open the operator console on the field (auto: when the terminal is interactive)",
    )
    parser.add_argument(
        "--mqtt",
        dest="mqtt_url",
        help="MQTT broker for agents, UWB and console (default: an embedded mosquitto, else amqtt)",
    )
    parser.add_argument(
        "--secure",
        action="store_true",
        help="a secured site: deploy/'s broker and router with passwords, ACLs and TLS (needs mosquitto)",
    )
    parser.add_argument(
        "--operator",
        action="append",
        default=None,
        help="with --secure: operator accounts op-<name> (repeat; the first is the field's console; "
        "default op-operator-1)",
    )
    sub = parser.add_subparsers(dest="field_command", metavar="ACTION")
    run = sub.add_parser(
        "run",
        help="run a scenario (lockstep: simulated time as fast as possible; or real time)",
        description="Run a scenario. With --lockstep, simulated time runs as fast as the CPU allows and "
        "the robots' true trajectories are written to --out.",
    )
    run.add_argument("scenario", help="a scenario file, or a built-in scenario name")
    run.add_argument("--lockstep", action="store_true", help="simulated time, as fast as possible, deterministic")
    run.add_argument("--out", type=Path, help="output folder (required with --lockstep)")
    run.add_argument(
        "--duration", dest="run_duration", type=float, default=None, help="override the scenario's duration (s)"
    )
    run.add_argument("--seed", type=int, default=None, help="override the scenario's seed")


def resolve_scenario(name: str) -> Path:
    path = Path(name)
    if path.exists():
        return path
    builtin = SCENARIOS / f"{name}.toml"
    if builtin.exists():
        return builtin
    known = ", ".join(sorted(p.stem for p in SCENARIOS.glob("*.toml")))
    raise FileNotFoundError(f"no scenario file {name!r} and no built-in scenario of that name (built-in: {known})")


def run(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from fleetlink.field.plans import PlanError, load_plan
    from fleetlink.field.scenario import ScenarioError, load_scenario

    name = args.scenario
    try:
        scenario = load_scenario(resolve_scenario(name))
        if args.field_command == "run":
            if args.run_duration is not None:
                scenario = replace(scenario, duration=args.run_duration)
            if args.seed is not None:
                scenario = replace(scenario, seed=args.seed)
        plan = load_plan(scenario.plan)
    except (FileNotFoundError, ScenarioError, PlanError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.field_command == "run" and args.lockstep:
        return _run_lockstep(scenario, plan, args.out)
    duration = scenario.duration if args.field_command == "run" else args.duration
    if getattr(args, "secure", False):
        return _run_secure(scenario, plan, duration, args)
    return _run_realtime(scenario, plan, duration, args)


def _run_lockstep(scenario: Scenario, plan: FloorPlan, out: Path | None) -> int:
    from fleetlink.field.lockstep import FieldRun, write_outputs

    if out is None:
        print("error: --lockstep needs --out DIR", file=sys.stderr)
        return 2
    try:
        # Four or more lidars: cast most of them in a second process (same results, both cores).
        lidars = sum(1 for r in scenario.robots if r.lidar) if scenario.lidar.enabled else 0
        with FieldRun(scenario, plan, lidar_worker=lidars >= 4) as field_run:
            result = field_run.run()
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    write_outputs(result, out)
    print(
        f"{result.scenario.name}: {result.sim_seconds:.1f} s simulated in {result.wall_seconds:.1f} s "
        f"({result.real_time_factor:.1f}x real time), {len(result.truth)} robot(s), {result.scans} lidar scans"
    )
    for line in result.events:
        print(f"  {line}")
    print(f"wrote {out}/truth/*.csv, {out}/events.log, {out}/summary.json")
    return 0


def _run_realtime(scenario: Scenario, plan: FloorPlan, duration: float, args: argparse.Namespace) -> int:
    from fleetlink.agent.board.session import BoardSession
    from fleetlink.field.drivers import Driver, driver_for
    from fleetlink.field.realtime import RealtimeField
    from fleetlink.field.truth import TruthPublisher
    from fleetlink.operator.board_status import render
    from fleetlink.shared.clock import SystemClock

    clock = SystemClock()
    publisher = None
    if args.zenoh_listen != "none":
        try:
            publisher = TruthPublisher.open(args.zenoh_listen, clock)
        except Exception as exc:  # zenoh raises its own ZError
            print(
                f"warning: cannot publish ground truth on {args.zenoh_listen}: {exc}; continuing without",
                file=sys.stderr,
            )
    # Ground truth fans out to Zenoh and, with the console, to the UWB simulator (added later).
    sinks: list[Callable[[Any], None]] = [publisher.publish] if publisher is not None else []

    def truth_sink(sample: Any) -> None:
        for sink in list(sinks):
            sink(sample)

    field = RealtimeField(scenario, plan, clock, truth_sink=truth_sink, pty=args.pty)
    sessions: list[tuple[str, BoardSession, Driver]] = []
    console = args.console == "on" or (args.console == "auto" and sys.stdin.isatty() and sys.stdout.isatty())
    try:
        endpoints = field.start()
        if console:  # agents drive the boards and the console drives the agents (cli/console.py)
            from fleetlink.cli.console import run_field_console

            return run_field_console(
                endpoints, clock, args.mqtt_url, scenario=field.scenario, plan=field.plan, add_truth_sink=sinks.append
            )
        for i, spec in enumerate(field.scenario.robots):
            url = endpoints[spec.name].board
            session = BoardSession(_opener(url), clock, seed=i)
            session.start()
            sessions.append((spec.name, session, driver_for(spec, i)))
        stop = threading.Event()
        start = clock.now()
        tty = sys.stdout.isatty()
        while not stop.wait(1.0 / args.refresh):
            now = clock.now()
            t = now - start
            for _, session, driver in sessions:
                session.set_velocity(*driver(session.snapshot, t))
            lines = [
                f"fleetlink field: {field.scenario.name} on {field.plan.name}, {len(sessions)} robot(s), t = {t:6.1f} s   (Ctrl-C to stop)"
            ]
            if publisher is not None:
                lines.append(f"ground truth on Zenoh {args.zenoh_listen}: fleetlink/v1/sim/<robot>/truth")
            lines.append("")
            for name, session, _ in sessions:
                ep = endpoints[name]
                lines += [*render(f"{name} (board {ep.board}, lidar {ep.lidar or 'none'})", session.snapshot, now), ""]
            for line in field.events.log[-5:]:
                lines.append(f"event: {line}")
            out = "\n".join(lines) + "\n"
            sys.stdout.write(("\x1b[H\x1b[2J" + out) if tty else out)
            sys.stdout.flush()
            if duration and t >= duration:
                break
    except KeyboardInterrupt:
        pass
    finally:
        for _, session, _ in sessions:
            session.set_velocity(0.0, 0.0)
        for _, session, _ in sessions:
            session.stop()
        field.stop()
        if publisher is not None:
            publisher.close()
    return 0


def _opener(url: str) -> Callable[[], Port]:
    from fleetlink.agent.board.transport import SerialPort

    return lambda: SerialPort(url)


def _run_secure(scenario: Scenario, plan: FloorPlan, duration: float, args: argparse.Namespace) -> int:
    """The field as a secured site (field/secure.py): agents, UWB gateway, truth and console log in."""
    import logging

    from fleetlink.field.realtime import RealtimeField
    from fleetlink.field.secure import SecureField, SecureSite, SiteError, missing_tools
    from fleetlink.shared.clock import SystemClock

    if args.mqtt_url:
        print("error: --secure runs its own broker (deploy/'s configuration); leave out --mqtt", file=sys.stderr)
        return 2
    missing = missing_tools()
    if missing:
        print(
            f"error: --secure needs {', '.join(missing)}: the embedded amqtt fallback has no password file "
            "and no ACL, so it cannot run a secured site (install with .ci/install-mosquitto, or "
            "apt-get install mosquitto)",
            file=sys.stderr,
        )
        return 2
    operators = args.operator or ["op-operator-1"]
    clock = SystemClock()
    try:
        site = SecureSite([r.name for r in scenario.robots], operators).start()
    except (SiteError, ValueError) as exc:
        print(f"error: cannot start the secured site: {exc}", file=sys.stderr)
        return 2
    sinks: list[Callable[[Any], None]] = []

    def truth_sink(sample: Any) -> None:
        for sink in list(sinks):
            sink(sample)

    field = RealtimeField(scenario, plan, clock, truth_sink=truth_sink, pty=args.pty)
    secure: SecureField | None = None
    console = args.console == "on" or (args.console == "auto" and sys.stdin.isatty() and sys.stdout.isatty())
    try:
        endpoints = field.start()
        secure = SecureField(site, endpoints, clock, scenario=field.scenario, plan=field.plan).start()
        sinks.append(secure.truth_sink)
        for line in site.describe():
            print(line, file=sys.stderr)
        if console:
            from fleetlink.cli.console import ConsoleSettings, run_console

            logging.getLogger().handlers.clear()  # logs would scribble over the console
            logging.basicConfig(
                filename="field.log", level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s"
            )
            link = secure.operator_link(operators[0]).start()
            settings = ConsoleSettings(
                operator=operators[0], zenoh_connect=(site.zenoh_endpoint,), mqtt_url=site.mqtt_url
            )
            return run_console(settings, link)
        stop = threading.Event()
        start = clock.now()
        print(f"fleetlink field --secure: {field.scenario.name}, {len(endpoints)} robot(s); Ctrl-C to stop")
        while not stop.wait(1.0):
            if duration and clock.now() - start >= duration:
                break
    except KeyboardInterrupt:
        pass
    finally:
        if secure is not None:
            secure.stop()
        field.stop()
        site.stop()
    return 0
