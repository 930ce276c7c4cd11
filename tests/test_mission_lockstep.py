"""Whole agents in lockstep (fleetlink.site.lockstep): real agents, in-process links, simulated time.

Two scouts in the office, each with its whole agent (board session over Control Bus bytes, lidar
over RPLIDAR bytes, fusion with the UWB gateway's fixes, guard, pilot, mapping, planner), a goal
each and a teleop burst sent by a scripted operator over the in-process Zenoh link: the same seed
twice gives byte-identical truth and agent logs, whether the map keepers run in a second process
or in line, and the go-to reaches its goal as the go-to bench demands of it.
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import pytest

from fleetlink.field.scenario import parse_scenario
from fleetlink.site.lockstep import MissionRun, write_mission_outputs

# One worker runs this module under pytest-xdist, so its module-scoped set-up runs once.
pytestmark = pytest.mark.xdist_group("mission_lockstep")

SCENARIO = """
name = "two-scouts"
plan = "office"
seed = 11
duration_s = 24.0

[lidar]
rate_hz = 10.0
samples_per_second = 2000.0

[[robots]]
name = "scout-1"
start = "entrance"
drive = "agent"

[[robots]]
name = "scout-2"
start = "lobby-06"
drive = "agent"

[[events]]
at_s = 3.0
kind = "goal"
robot = "scout-1"
x = {gx}
y = {gy}
theta_deg = 90.0

[[events]]
at_s = 3.0
kind = "teleop"
robot = "scout-2"
v = 0.25
omega = 0.0
duration_s = 2.0

[[events]]
at_s = 8.0
kind = "goal"
robot = "scout-2"
x = {g2x}
y = {g2y}
"""


def _scenario(seed: int = 11) -> tuple[object, tuple[float, float], tuple[float, float]]:
    from fleetlink.field.plans import load_plan

    plan = load_plan("office")
    sx, sy, _ = plan.starts["entrance"]
    s2x, s2y, s2th = plan.starts["lobby-06"]
    goal = (sx + 1.5, sy)  # along the corridor the scout starts in
    goal2 = (s2x + 0.5 * math.cos(s2th), s2y + 0.5 * math.sin(s2th))
    text = SCENARIO.format(gx=goal[0], gy=goal[1], g2x=goal2[0], g2y=goal2[1]).replace("seed = 11", f"seed = {seed}")
    return parse_scenario(tomllib.loads(text)), goal, goal2


def _run(tmp: Path, seed: int = 11, *, map_worker: bool = True) -> tuple[object, Path]:
    scenario, _, _ = _scenario(seed)
    with MissionRun(scenario, map_worker=map_worker) as run:
        assert (run.map_worker is not None) == map_worker
        result = run.run()
    return result, write_mission_outputs(result, tmp)


@pytest.fixture(scope="module")
def twice(tmp_path_factory: pytest.TempPathFactory) -> tuple[object, Path, Path]:
    """The same seed twice: the map keepers in a worker process, then in line."""
    first, a = _run(tmp_path_factory.mktemp("a"), map_worker=True)
    _, b = _run(tmp_path_factory.mktemp("b"), map_worker=False)
    return first, a, b


def test_same_seed_gives_byte_identical_truth_and_agent_logs(twice: tuple[object, Path, Path]) -> None:
    _, a, b = twice
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file() and p.name != "summary.json")
    assert {str(f) for f in files} >= {
        "truth/scout-1.csv",
        "truth/scout-2.csv",
        "agents/scout-1.log",
        "agents/scout-2.log",
        "operator.log",
        "events.log",
    }
    for f in files:
        assert (a / f).read_bytes() == (b / f).read_bytes(), f"{f} differs between two runs of one seed"
    log = (a / "agents" / "scout-1.log").read_text()
    # The whole agent ran: poses, state, acks of the operator's order, the goal reached.
    for topic in (" pose ", " state ", " ack ", " events ", " map/updates "):
        assert topic in log, topic
    assert "goal_reached" in log


def test_another_seed_gives_other_numbers(twice: tuple[object, Path, Path], tmp_path: Path) -> None:
    _, a, _ = twice
    _, c = _run(tmp_path, seed=12)
    assert (a / "truth" / "scout-1.csv").read_bytes() != (c / "truth" / "scout-1.csv").read_bytes()


def test_goto_in_lockstep_meets_the_goto_bench_goals(twice: tuple[object, Path, Path]) -> None:
    result, _, _ = twice
    _, goal, _ = _scenario()
    acks = [a for a in result.acks if a.header.robot == "scout-1" and a.commandTopic == "order"]
    assert acks and acks[0].result.value == "accepted", acks
    reached = [e for e in result.events if e.header.robot == "scout-1" and e.kind == "goal_reached"]
    assert reached, [(e.kind, e.text) for e in result.events if e.header.robot == "scout-1"]
    truth = result.field.truth["scout-1"]
    _, x, y, th, v, w = truth[-1]  # at rest at the end of the run
    # bench/goto.py's goals: true error p95 <= 15 cm; heading <= 2 deg (p95).
    assert math.hypot(x - goal[0], y - goal[1]) <= 0.15
    assert abs(math.remainder(th - math.pi / 2, math.tau)) <= math.radians(2.0)
    assert abs(v) < 1e-3 and abs(w) < 1e-3


def test_the_teleop_burst_moved_the_robot_through_its_agent(twice: tuple[object, Path, Path]) -> None:
    result, _, _ = twice
    truth = result.field.truth["scout-2"]
    at = {round(r[0], 2): r for r in truth}
    moved_before = math.hypot(at[3.0][1] - truth[0][1], at[3.0][2] - truth[0][2])
    moved_burst = math.hypot(at[5.5][1] - at[3.0][1], at[5.5][2] - at[3.0][2])
    assert moved_before < 0.01  # nobody drives it before the operator does
    assert 0.3 < moved_burst < 0.6  # 0.25 m/s for 2 s, through the motion limits and the deadman
    sent = [c for c in result.commands if " scout-2 teleop " in c]
    assert len(sent) >= 8  # one every 0.25 s, and the release
    assert '"v": 0.0' in sent[-1]


def test_a_round_of_places_is_sent_one_goal_after_another_in_the_site_frame() -> None:
    """``MissionRun.visit``: with UWB, each place goes out in the site frame once the last goal ended
    (the ward round, tests/test_ward_round.py, sends them on a robot's own map)."""
    from fleetlink.field.plans import load_plan

    text = SCENARIO.split("[[events]]")[0].replace('drive = "agent"', 'drive = "idle"')
    with MissionRun(parse_scenario(tomllib.loads(text)), record=False, map_worker=False) as run:
        assert run.uwb is not None and run.robots[0].own_frame is None
        outcomes = run.visit("scout-1", ["lobby-01", "entrance"], step_s=1.0, until_s=90.0)
        result = run.run(run.clock.now() + 0.5)
    assert outcomes == [("lobby-01", "goal_reached"), ("entrance", "goal_reached")], outcomes
    x, y, _ = load_plan("office").starts["entrance"]
    end = result.field.truth["scout-1"][-1]
    assert math.hypot(end[1] - x, end[2] - y) < 0.3, end
    # The second robot was sent nowhere.
    assert [e for e in result.events if e.header.robot == "scout-2" and e.kind.startswith("goal")] == []


def test_a_round_cut_short_sends_nothing_after_its_time_and_names_no_unknown_robot() -> None:
    text = SCENARIO.split("[[events]]")[0].replace('drive = "agent"', 'drive = "idle"')
    with MissionRun(parse_scenario(tomllib.loads(text)), record=False, map_worker=False) as run:
        with pytest.raises(ValueError, match="no robot 'scout-9'"):
            run.visit("scout-9", ["entrance"])
        outcomes = run.visit("scout-1", ["lobby-01", "entrance"], step_s=0.5, until_s=1.0)
        orders = [line for line in run.operator.sent if " scout-1 order " in line]
    # The first goal still going at 1 s; the second never sent (the robot keeps its one order).
    assert outcomes == [("lobby-01", None), ("entrance", None)], outcomes
    assert len(orders) == 1, orders
