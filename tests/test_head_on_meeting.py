"""Two scouts met head on at a goal, as a mission: whole agents in lockstep in the exhibition hall
without UWB (field/scenarios/expo-dark-team.toml, its wandering off). Scout-1 is sent 6 m into the
hall, scout-2 to the middle of the hall beyond it; the moment scout-1 arrives and is sent on to the
north, scout-2 is sent to where scout-1 stands (through the frames the truth gives). They meet there:
scout-2's guard bars the way and the mark of what barred it covers the goal. Before, the go-to failed
on the spot ("blocked ... and no way around", as the two-scout console test did in CI:
docs/mapping-history.md "The goal another robot had just left"). Now the route waits for what barred
it to move (agent/route.py), plans again, and scout-2 reaches the goal: scored against the truth.

The second test sends scout-2 from where it started, 5 m off, as scout-1 leaves the goal. Its map
holds scout-1 at the goal beyond the 5 m a sector with no return clears. Before, it waited where it
stood and the wait ran out ("no path ... (waited 6 s)"); now the route first goes to within
``approach_m`` of the goal to look, the map clears, and scout-2 reaches it.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from fleetlink.field.scenario import load_scenario
from fleetlink.shared.se2 import compose, relative
from fleetlink.site.lockstep import MissionResult, MissionRun

TEAM = Path(__file__).resolve().parents[1] / "field" / "scenarios" / "expo-dark-team.toml"
GOAL = (6.0, 0.0)  # in scout-1's frame: 6 m into the hall from the entrance
ON = (18.5, 0.5)  # scout-1's next goal, to the north of the hall
MIDDLE = (8.7, -6.4)  # scout-2's first goal, in its own frame: the middle of the hall, north of scout-1's

pytestmark = pytest.mark.slow


def meet(scout2_first: tuple[float, float] | None, delay_s: float) -> tuple[MissionResult, tuple[float, float]]:
    """Scout-1 to ``GOAL``, scout-2 to ``scout2_first`` (None: it stays where it starts); when scout-1
    arrives it goes on to ``ON`` and, ``delay_s`` later (0: at that step), scout-2 is sent to where
    scout-1 stood. The result, and that place on the plan."""
    with MissionRun(load_scenario(TEAM), record=False, map_worker=False) as run:
        scout1, scout2 = run.robots
        for r in run.robots:
            r.wander = False
        op = run.operator
        state = {"phase": 0, "left_at": math.nan}
        seen = [0]
        site_goal = compose(scout1.own_frame, (*GOAL, 0.0))

        def send_scout2() -> None:
            x, y, _ = relative(scout2.own_frame, site_goal)
            op.goal("scout-2", x, y, None, "s2-where-s1-stood")
            state["phase"] = 3

        def operate(t: float) -> None:
            new = op.events[seen[0] :]
            seen[0] = len(op.events)
            if state["phase"] == 0 and t > 3.0:
                op.goal("scout-1", *GOAL, None, "s1-first")
                if scout2_first is not None:
                    op.goal("scout-2", *scout2_first, None, "s2-first")
                state["phase"] = 1
            elif state["phase"] == 1 and any(e.kind == "goal_reached" and e.header.robot == "scout-1" for e in new):
                op.goal("scout-1", *ON, None, "s1-on")
                state["phase"], state["left_at"] = 2, t
                if delay_s == 0.0:
                    send_scout2()
            elif state["phase"] == 2 and t >= state["left_at"] + delay_s:
                send_scout2()

        run.field.controllers.append(operate)
        result = run.run(60.0)
    assert state["phase"] == 3, "scout-1 never reached its first goal"
    return result, (site_goal[0], site_goal[1])


def test_a_scout_sent_where_another_stands_waits_for_it_to_go_and_reaches_the_goal() -> None:
    result, goal = meet(MIDDLE, 0.0)
    two = [e for e in result.events if e.header.robot == "scout-2"]
    kinds = [(e.kind, e.text) for e in two]
    # The meeting happened, and was waited out rather than failed.
    assert any(k == "waiting" for k, _ in kinds), kinds
    assert not any(k == "goal_failed" for k, _ in kinds), kinds
    assert any(e.kind == "goal_reached" and "s2-where-s1-stood" in e.text for e in two), kinds
    # Against the truth: scout-2 stands where scout-1 stood.
    _, x, y = result.field.truth["scout-2"][-1][:3]
    assert math.dist((x, y), goal) < 0.15, (x, y, goal)


@pytest.mark.parametrize("delay_s", [0.0, 1.0], ids=["as-scout-1-leaves", "a-second-later"])
def test_a_scout_sent_from_afar_to_where_another_stood_goes_nearer_to_look_and_reaches_it(delay_s: float) -> None:
    result, goal = meet(None, delay_s)
    two = [e for e in result.events if e.header.robot == "scout-2"]
    kinds = [(e.kind, e.text) for e in two]
    assert not any(k == "goal_failed" for k, _ in kinds), kinds
    assert any(e.kind == "goal_reached" and "s2-where-s1-stood" in e.text for e in two), kinds
    _, x0, y0 = result.field.truth["scout-2"][0][:3]
    assert math.dist((x0, y0), goal) > 4.5, "scout-2 was to start far from the goal"
    _, x, y = result.field.truth["scout-2"][-1][:3]
    assert math.dist((x, y), goal) < 0.15, (x, y, goal)
