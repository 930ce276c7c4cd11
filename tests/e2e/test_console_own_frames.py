"""End to end: two scouts without UWB in the real console (``fleetlink field --scenario
expo-dark-team``), real time, real agents. Each maps in its own frame. The test types like a person:
scout-2's detail and its localisation alarm say it is not on the fleet map yet, and a goal sent to
it then warns that it is in the robot's own frame; both scouts are driven into the hall; once their
maps share enough of it the console's fleet map finds scout-2's frame (the detail line says nothing
more about it, the alarm clears), and a goal
typed on the fleet map for scout-2 is reached there: where scout-1 stood after its first goal; a
sweep of a rectangle drawn there is run by scout-2 inside it.
"""

from __future__ import annotations

import contextlib
import math
import re
from pathlib import Path

import pytest

from tests.e2e.test_console_field import (
    CONSOLE_E2E,
    command,
    console_field,
    quit_field,
    screen,
    tmux,
)
from tests.harness import wait_until

pytestmark = CONSOLE_E2E  # the console's e2e tests' rules: under CI they must run, one at a time

POSE = re.compile(r"(scout-\d) [^│\n]*?pose ([+-]\d+\.\d+) ([+-]\d+\.\d+)")
OFF_MAP = "not on the fleet map yet"
LOCALISATION_ALARM = re.compile(r"WARN\s+scout-2\s+localisation")
ROUND = re.compile(r"round sweep-scout-2-\S+: (\d+)/(\d+) nodes done")


OPERATOR_LOST = "hears no operator"
"""A robot's alarm on stopping for want of its operator (``comms-loss: stop``): its goal is dropped."""


def shown_pose(session: str, robot: str) -> tuple[float, float] | None:
    m = POSE.search(screen(session))
    return (float(m.group(2)), float(m.group(3))) if m and m.group(1) == robot else None


@pytest.mark.slow
def test_two_scouts_without_uwb_come_onto_one_fleet_map_in_the_console(tmp_path: Path) -> None:
    fleet_map = ("the fleet map", lambda lines: [line for line in lines if "fleet map:" in line])
    with console_field(tmp_path, "--scenario expo-dark-team", 200, 56, fleet_map) as (session, pane_pid):
        wait_until(lambda: shown_pose(session, "scout-1") is not None, timeout=60, message="scout-1 selected, its pose")
        tmux("send-keys", "-t", session, "Tab")
        wait_until(
            lambda: shown_pose(session, "scout-2") is not None and OFF_MAP in screen(session),
            timeout=60,
            message="scout-2 selected, not on the fleet map yet",
        )
        # Its localisation warns: the fleet map has not found it (it never has a site position).
        wait_until(
            lambda: LOCALISATION_ALARM.search(screen(session)) is not None,
            timeout=20,
            message="scout-2's localisation alarm while it is not on the fleet map",
        )
        # In its own frame: the middle of the hall, 8.7 m on and 6.4 m to its right from where it started.
        command(session, "goal 8.7 -6.4")
        wait_until(
            lambda: "scout-2 is not on the fleet map yet" in screen(session),
            timeout=10,
            message="the console warning that the goal is in scout-2's own frame",
        )
        tmux("send-keys", "-t", session, "Tab")
        wait_until(lambda: shown_pose(session, "scout-1") is not None, timeout=10, message="scout-1 selected")

        def scout_1_at_6_0() -> bool:
            p = shown_pose(session, "scout-1")
            return p is not None and math.dist(p, (6.0, 0.0)) < 0.2

        # scout-1's frame is the fleet map's: 6 m into the hall. Sent again if a robot stopped on losing
        # its operator meanwhile, as an operator would (a loaded 2-core run, 2026-12-07: the console
        # starved for seconds, both robots stopped, "hears no operator", scout-1 idle 0.6 m short).
        for _ in range(3):
            lost = screen(session).count(OPERATOR_LOST)
            command(session, "goal 6 0")
            wait_until(
                lambda lost=lost: scout_1_at_6_0() or screen(session).count(OPERATOR_LOST) > lost,  # type: ignore[misc]
                timeout=90,
                message="scout-1 at (6, 0)",
            )
            if scout_1_at_6_0():
                break
        assert scout_1_at_6_0()
        # scout-2 at its first goal, the middle of the hall ((19.95, 12) on the plan), before scout-1 goes
        # on: scout-1's way north crosses scout-2's way there, at (20.8, 8.7) on the plan, and neither
        # knows where the other is (no site frame to share poses in). On a loaded machine scout-2 came
        # late and drove into scout-1's side there (2026-12-06); standing, it is an obstacle either
        # robot's lidar maps and plans around.
        tmux("send-keys", "-t", session, "Tab")

        def scout_2_in_the_middle() -> bool:
            # Its pose in its own frame, or on the fleet map once that has found it there (scout-1's
            # frame: (11.0, 0.55)); or the console's line saying it arrived (it may scroll away).
            text = screen(session)
            p = shown_pose(session, "scout-2")
            return ("scout-2: goal_reached" in text) or (
                p is not None and (math.dist(p, (8.7, -6.4)) < 0.3 or math.dist(p, (11.0, 0.55)) < 0.5)
            )

        wait_until(scout_2_in_the_middle, timeout=90, message="scout-2 at its first goal, the middle of the hall")
        tmux("send-keys", "-t", session, "Tab")
        wait_until(lambda: shown_pose(session, "scout-1") is not None, timeout=10, message="scout-1 selected again")

        # On, past the middle, to the north of the hall: (22, 19.5) on the plan, east of the pillars at
        # x = 20 (heading for (20, 19.5), straight between them, it bumped on loaded runs, 2 of 4).
        # There first: scout-2's legs below cross the middle of the hall that scout-1 drives through,
        # and neither robot knows where the other is (no site frame to share poses in), so only the
        # ultrasonic keeps them apart. On a loaded machine they met there: scout-2 bumped into
        # scout-1, which then failed its goal, blocked three times by scout-2 standing in its way.
        # Once (a clean clone's run, 2026-12-06) its ultrasonic barred it 0.38 m short, by the
        # pillars, and the goal failed: as an operator would, the goal is sent again then.
        def scout_1_north() -> bool:
            p = shown_pose(session, "scout-1")
            return p is not None and math.dist(p, (18.5, -1.5)) < 0.3

        sent_text, failed_text = "scout-1: goal (18.50, -1.50) sent", "scout-1: goal_failed"
        for attempt in range(2):
            text = screen(session)
            sent, failed = text.count(sent_text), text.count(failed_text)
            command(session, "goal 18.5 -1.5")
            wait_until(
                lambda sent=sent: screen(session).count(sent_text) > sent,  # type: ignore[misc]
                timeout=10,
                message="scout-1's goal sent",
            )
            wait_until(
                lambda failed=failed: scout_1_north() or screen(session).count(failed_text) > failed,  # type: ignore[misc]
                timeout=90,
                message="scout-1 at (18.5, -1.5), to the north of the hall, or its goal failed",
            )
            if scout_1_north() or attempt == 1:
                break
        wait_until(scout_1_north, timeout=10, message="scout-1 at (18.5, -1.5), to the north of the hall")
        tmux("send-keys", "-t", session, "Tab")
        wait_until(lambda: shown_pose(session, "scout-2") is not None, timeout=10, message="scout-2 selected")

        def found() -> bool:
            return shown_pose(session, "scout-2") is not None and OFF_MAP not in screen(session)

        # As an operator would: on through the hall (its own frame) until the fleet map has it. On a
        # loaded machine the maps of the first legs may not yet tell the places apart.
        for leg in ((8.05, -13.5), (14.8, -1.3), (8.7, -6.4)):
            if found():
                break
            command(session, f"goal {leg[0]} {leg[1]}")
            with contextlib.suppress(AssertionError):
                wait_until(
                    lambda leg=leg: (
                        found()  # type: ignore[misc]
                        or ((p := shown_pose(session, "scout-2")) is not None and math.dist(p, leg) < 0.3)
                    ),
                    timeout=90,
                    message=f"scout-2 at {leg} in its own frame",
                )
        wait_until(found, timeout=60, message="scout-2 found on the fleet map (its detail no longer saying it is not)")
        wait_until(
            lambda: LOCALISATION_ALARM.search(screen(session)) is None,
            timeout=20,
            message="scout-2's localisation alarm cleared once the fleet map placed it",
        )
        # A goal on the fleet map: where scout-1 stood after its first goal, now that scout-1 has gone
        # on to the north of the hall, as an operator would send it. Sent while scout-1 drove away, it
        # met scout-1 head on at the goal (the hall's middle lies between both robots' goals): a
        # meeting the route now waits out, but a map that saw scout-1 there may hold it longer than
        # the wait (docs/mapping-history.md "The goal another robot had just left").
        command(session, "goal 6 0")
        wait_until(
            lambda: (p := shown_pose(session, "scout-2")) is not None and math.dist(p, (6.0, 0.0)) < 0.2,
            timeout=120,
            message="scout-2 at (6, 0) on the fleet map",
        )
        # A sweep drawn on the fleet map: planned on scout-2's map through its frame, sent in its own.
        command(session, "sweep rect 5 -1 7 1")
        wait_until(
            lambda: re.search(r"scout-2: sweep sent as order sweep-scout-2-\S+ \(\d+ nodes\)", screen(session)),
            timeout=60,
            message="scout-2's sweep sent",
        )

        def sweeping() -> bool:
            text = screen(session)
            done = ROUND.search(text)
            p = shown_pose(session, "scout-2")
            inside = p is not None and 4.7 <= p[0] <= 7.3 and -1.3 <= p[1] <= 1.3
            return done is not None and int(done.group(1)) >= 3 and inside

        wait_until(sweeping, timeout=120, message="scout-2 three nodes into its sweep, inside the rectangle")
        quit_field(session, pane_pid)
