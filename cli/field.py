"""The simulated field.

Without an action it starts the demo in real time: the built-in "demo" scenario (or --scenario),
every robot's control board and lidar served on TCP like real hardware, an agent-side board link
per robot talking to its board through real bytes, ground truth published on Zenoh under
fleetlink/v1/sim/<robot>/truth, and each robot's live board status on the terminal. Stop with
Ctrl-C, or give --duration.

`fleetlink field --secure` runs it all as a secured site would (fleetlink.site.security): deploy/'s
Mosquitto and Zenoh router with generated passwords and ACLs (TLS with a throwaway CA when openssl
is there), agents logged in as their robot ids, the UWB gateway as uwb-gateway, ground truth as
sim, the console as the operator; it prints where the credentials are so another console can join.
The demo and the secured site are one composition, fleetlink.site.field.FieldSite: this module
only parses the arguments and presents.

`fleetlink field run SCENARIO --lockstep --out DIR` runs a scenario in simulated time, as fast as
the CPU allows, with every robot's whole agent, and writes the robots' true trajectories and the
agents' logs (see docs/field-scenarios.md); ``--field-only`` runs the field alone.
"""

from __future__ import annotations

import argparse
import sys
import threading
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from fleetlink.field.plans import FloorPlan
    from fleetlink.field.scenario import Scenario
    from fleetlink.site.field import FieldSite

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
    parser.add_argument(
        "--light",
        type=int,
        default=0,
        metavar="N",
        help="N light robots instead of the scenario (real wire messages, no agents: pose 20 Hz, state 1 Hz, acks; "
        "docs/operations.md 'Scale')",
    )
    parser.add_argument(
        "--zenoh-connect",
        action="append",
        default=None,
        metavar="ENDPOINT",
        help="with --light: connect to this Zenoh router as a client (repeat for more) instead of listening",
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
        "--field-only",
        action="store_true",
        help="with --lockstep: the field alone, robots moving open-loop (no agents; for benchmarks of the field)",
    )
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

    if args.light:
        return _run_light(args)
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
        return _run_lockstep(scenario, plan, args.out, args.field_only)
    duration = scenario.duration if args.field_command == "run" else args.duration
    return _run_realtime(scenario, plan, duration, args)


def _run_lockstep(scenario: Scenario, plan: FloorPlan, out: Path | None, field_only: bool = False) -> int:
    """Whole agents in simulated time (fleetlink.site.lockstep), or with ``field_only`` the field
    alone with its open-loop motion."""
    from fleetlink.field.lockstep import FieldRun, write_outputs
    from fleetlink.site.lockstep import MissionRun, write_mission_outputs

    if out is None:
        print("error: --lockstep needs --out DIR", file=sys.stderr)
        return 2
    try:
        if field_only:
            # Four or more lidars: cast most of them in a second process (same results, both cores).
            lidars = sum(1 for r in scenario.robots if r.lidar) if scenario.lidar.enabled else 0
            with FieldRun(scenario, plan, lidar_worker=lidars >= 4) as field_run:
                result = field_run.run()
            write_outputs(result, out)
            written = "truth/*.csv, events.log, summary.json"
        elif scenario.casualties:  # a rescue sortie: its scripted operator (fleetlink.site.sortie)
            from fleetlink.site.sortie import SortieRun, write_sortie_outputs

            with SortieRun(scenario, plan, record=True) as sortie_run:
                sortie = sortie_run.run()
            result = sortie.mission.field
            write_sortie_outputs(sortie, out)
            written = "truth/*.csv, agents/*.log, operator.log, events.log, contact.csv, marks.csv, sortie.log, sortie.json, summary.json"
        else:
            with MissionRun(scenario, plan) as mission:
                mission_result = mission.run()
            result = mission_result.field
            write_mission_outputs(mission_result, out)
            written = "truth/*.csv, agents/*.log, operator.log, events.log, contact.csv, summary.json"
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    who = "the field alone" if field_only else "whole agents"
    print(
        f"{result.scenario.name}: {result.sim_seconds:.1f} s simulated in {result.wall_seconds:.1f} s "
        f"({result.real_time_factor:.1f}x real time), {len(result.truth)} robot(s), {who}, {result.scans} lidar turns"
    )
    for line in result.events:
        print(f"  {line}")
    print(f"wrote {out}: {written}")
    return 0


def _run_realtime(scenario: Scenario, plan: FloorPlan, duration: float, args: argparse.Namespace) -> int:
    """The field in real time as one site (fleetlink.site.field): the demo, or with --secure a
    secured site; the console on it, or the boards' live status (demo) without one."""
    from fleetlink.shared.clock import SystemClock
    from fleetlink.site.brokers import SiteError
    from fleetlink.site.field import FieldSite, Security
    from fleetlink.site.security import missing_tools

    security = None
    if args.secure:
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
        security = Security(operators=tuple(args.operator or ["op-operator-1"]))
    console = args.console == "on" or (args.console == "auto" and sys.stdin.isatty() and sys.stdout.isatty())
    operator = security.operators[0] if security is not None else "operator-1"
    if console:
        _log_to_file("field.log")  # from here on logs would scribble over the console
    clock = SystemClock()
    try:
        site = FieldSite(
            scenario,
            plan,
            clock,
            pty=args.pty,
            agents=console or security is not None,  # agents drive the boards; else the demo's open loop
            operator=operator if console else None,
            mqtt_url=args.mqtt_url,
            truth_listen=None if args.zenoh_listen == "none" or security is not None else args.zenoh_listen,
            security=security,
        ).start()
    except (SiteError, ValueError) as exc:
        what = "the secured site" if security is not None else "the field"
        print(f"error: cannot start {what}: {exc}", file=sys.stderr)
        return 2
    try:
        # One write: print() writes a line and its newline apart, and an agent's log line from
        # another thread could land between them (a test read "ca.crt2026-12-02 ..." as the CA's path).
        sys.stderr.write("".join(f"{line}\n" for line in site.describe()))
        if console:
            from fleetlink.cli.console import ConsoleSettings, run_console

            settings = ConsoleSettings(
                operator=operator,
                zenoh_listen=(site.zenoh_endpoint,) if security is None and site.zenoh_endpoint else (),
                zenoh_connect=(site.zenoh_endpoint,) if security is not None and site.zenoh_endpoint else (),
                mqtt_url=site.mqtt_url or ConsoleSettings.mqtt_url,
            )
            return run_console(settings, site.take_link())
        if site.boards is not None:
            _show_boards(site, duration, args)
        else:
            _wait(site, duration)
    except KeyboardInterrupt:
        pass
    finally:
        site.stop()
    return 0


def _run_light(args: argparse.Namespace) -> int:
    """``--light N``: N light robots (fleetlink.field.light) on Zenoh, in this one process, with a
    status line every few seconds (what was published, how far the publisher fell behind, its CPU)."""
    import os

    from fleetlink.field.light_runner import open_light_fleet
    from fleetlink.shared.clock import SystemClock

    if args.light < 0 or args.light > 10_000:
        print("error: --light takes 1-10000 robots", file=sys.stderr)
        return 2
    clock = SystemClock()
    connect = tuple(args.zenoh_connect or ())
    listen = () if connect or args.zenoh_listen == "none" else (args.zenoh_listen,)
    try:
        runner = open_light_fleet(
            args.light, clock, connect=connect, listen=listen, mode="client" if connect else "peer"
        )
    except Exception as exc:  # zenoh.ZError: a bad or busy endpoint
        print(f"error: cannot open the light fleet's Zenoh session: {exc}", file=sys.stderr)
        return 2
    where = f"connected to {', '.join(connect)}" if connect else f"listening on {', '.join(listen) or 'nothing'}"
    print(f"fleetlink field --light: {args.light} light robots, {where}; Ctrl-C to stop", flush=True)
    stop = threading.Event()
    start = last = clock.now()
    cpu_last = sum(os.times()[:2])
    sent_last = 0
    try:
        while not stop.wait(min(2.0, args.duration) if args.duration else 2.0):
            now, cpu = clock.now(), sum(os.times()[:2])
            s = runner.fleet.stats
            print(
                f"t={now - start:6.1f} s  {(runner.published - sent_last) / (now - last):7.0f} msg/s  "
                f"poses {s.poses}  states {s.states}  acks {s.acks}  skipped {s.skipped}  "
                f"lag max {s.lag_max_s * 1e3:.1f} ms  CPU {(cpu - cpu_last) / (now - last) * 100:.0f} %",
                flush=True,
            )
            last, cpu_last, sent_last = now, cpu, runner.published
            if args.duration and now - start >= args.duration:
                break
    except KeyboardInterrupt:
        pass
    finally:
        runner.close()
    return 0


def _log_to_file(path: str) -> None:
    import logging

    logging.getLogger().handlers.clear()
    logging.basicConfig(filename=path, level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")


def _show_boards(site: FieldSite, duration: float, args: argparse.Namespace) -> None:
    """The demo without a console: the robots driven open-loop, each board's live status on the terminal."""
    from fleetlink.operator.board_status import render

    assert site.boards is not None
    clock, field = site.clock, site.field
    stop = threading.Event()
    start = clock.now()
    tty = sys.stdout.isatty()
    while not stop.wait(1.0 / args.refresh):
        now = clock.now()
        t = now - start
        site.boards.step(t)
        lines = [
            f"fleetlink field: {field.scenario.name} on {field.plan.name}, {len(site.boards.sessions)} robot(s), "
            f"t = {t:6.1f} s   (Ctrl-C to stop)"
        ]
        if site.truth is not None:
            lines.append(f"ground truth on Zenoh {args.zenoh_listen}: fleetlink/v1/sim/<robot>/truth")
        lines.append("")
        for name, session, _ in site.boards.sessions:
            ep = site.endpoints[name]
            lines += [*render(f"{name} (board {ep.board}, lidar {ep.lidar or 'none'})", session.snapshot, now), ""]
        for line in field.events.log[-5:]:
            lines.append(f"event: {line}")
        out = "\n".join(lines) + "\n"
        sys.stdout.write(("\x1b[H\x1b[2J" + out) if tty else out)
        sys.stdout.flush()
        if duration and t >= duration:
            break


def _wait(site: FieldSite, duration: float) -> None:
    """A headless secured site: its agents run until Ctrl-C or ``duration``."""
    clock = site.clock
    stop = threading.Event()
    start = clock.now()
    print(f"fleetlink field --secure: {site.scenario.name}, {len(site.endpoints)} robot(s); Ctrl-C to stop")
    while not stop.wait(1.0):
        if duration and clock.now() - start >= duration:
            break
