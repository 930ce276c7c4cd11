"""The disinfection round as a mission (issue 16): whole agents in lockstep, a round planned on the
robot's own map as the console plans it, sent as an order with nodes, run node by node, scored
against the truth (site/disinfection.py). At a low target dose, so the round is short."""

from __future__ import annotations

import pytest

from fleetlink.site.disinfection import RoundRun, RoundSetup

LIVING = (0.0, 0.0, 6.0, 4.5)
PUT_DOWN = ("uvc-1", 1.0, 0.8, 25.0)


@pytest.mark.slow
def test_a_uv_round_brings_the_dose_to_the_reachable_floor_of_the_room_and_ends_with_the_lamp_off() -> None:
    setup = RoundSetup("apartment", "living", LIVING, (PUT_DOWN,), mode="uv", target_j_m2=3.0, deadline_s=1500.0)
    with RoundRun(setup) as run:
        result = run.run()
        board = run.mission.field.rigs[0].robot.board.state
        lamp_after = board.uv_lamp
        dose_inside = float(run.dose[run.reach].min())
    assert result.finished, result.notes
    assert result.coverage >= 0.98, (result.coverage, result.notes)  # the benchmark's goal is 0.99
    assert result.reachable_m2 > 18.0  # the living room less its furniture
    assert dose_inside >= 0.0 and not lamp_after  # the last node switches the lamp off
    assert result.lamp_on_s > 0 and result.lamp_outside_s <= 2.0
    assert result.bumps == 0
    assert result.predicted_s > 0 and result.time_s is not None and result.time_s < 3 * result.predicted_s


@pytest.mark.slow
def test_a_sweep_passes_the_brush_over_the_room_on_a_path_near_the_boustrophedon_ideal() -> None:
    setup = RoundSetup("apartment", "living", (2.0, 0.0, 6.0, 2.2), (PUT_DOWN,), mode="sweep", deadline_s=900.0)
    with RoundRun(setup) as run:
        result = run.run()
    assert result.finished, result.notes
    # Measured 0.987 with a path 1.19x the ideal (2026-11-28; the benchmark's goals are 0.95 and
    # 1.2x). It was 0.82 at 2.2x when lanes stopped 0.3 m short of walls and lanes across them swept
    # along those walls, where the guard slowed the robot and it weaved. A regression guard.
    assert result.coverage >= 0.95, (result.coverage, result.notes)
    assert result.ideal_path_m is not None and result.path_m <= 1.3 * result.ideal_path_m
    # The path counts from the first lane (its start, node n1, reached as the robot's state says):
    # the way there from where the robot stood is reported apart.
    assert 0.0 < result.approach_path_m < 0.1 * result.path_m, result.figures()
    assert result.lamp_on_s == 0.0 and result.bumps == 0


@pytest.mark.parametrize(
    ("kw", "why"),
    [({"mode": "mop"}, "mode must be one of"), ({"mode": "park", "robots": (PUT_DOWN, PUT_DOWN)}, "one robot")],
)
def test_a_round_setup_that_cannot_run_says_why(kw: dict[str, object], why: str) -> None:
    args: dict[str, object] = {"plan": "apartment", "room": "living", "rect": LIVING, "robots": (PUT_DOWN,), **kw}
    with pytest.raises(ValueError, match=why):
        RoundSetup(**args)  # type: ignore[arg-type]


def test_the_truth_counts_the_floor_the_brush_swept_between_samples() -> None:
    # The truth samples the robot every 0.2 s: its positions are 0.06-0.1 m apart on a lane, more
    # where it speeds up. The brush sweeps all the way between them; discs at the samples alone
    # leave the lane's edges scalloped (here, samples 0.15 m apart, cells 0.155 m off the lane).
    import numpy as np

    from fleetlink.agent import coverage as cv
    from fleetlink.site.disinfection import _Crew
    from fleetlink.site.rounds import ROUND_CONFIG

    fm = cv.FloorMap(np.ones((40, 80), dtype=bool), 0.05, (0.0, 0.0), ROUND_CONFIG)
    run = RoundRun.__new__(RoundRun)
    run.truth_fm, run.room = fm, cv.rectangle(fm, 0.0, 0.0, 4.0, 2.0)
    run.swept = np.zeros(fm.shape, dtype=bool)
    crew = _Crew("r")
    for i in range(7):
        run._brush(crew, 1.0 + 0.15 * i, 1.03)
    gx, gy = fm.centres()
    rad = fm.config.tool_width_m / 2.0
    lane = (np.abs(gy - 1.03) <= rad - 1e-9) & (gx >= 1.0) & (gx <= 1.9)
    assert run.swept[lane].all()
    assert not run.swept[np.abs(gy - 1.03) > rad + 1e-9].any()


def test_after_a_bump_the_operator_backs_the_robot_out_before_resuming() -> None:
    # A robot left against what it bumped keeps its bumper pressed: the lamp interlock refuses a UV
    # round's resume ("lamp refused"), and the kitchen's two-robot round at seed 16 waited so until
    # its deadline. As a person would, the bench's operator holds the drive key back first.
    from types import SimpleNamespace

    from fleetlink.shared.clock import SimClock
    from fleetlink.shared.messages import ActionType, Event, Severity, Teleop
    from fleetlink.shared.wire import HeaderCounter
    from fleetlink.site.disinfection import BACK_OUT_AFTER_S, BACK_OUT_FOR_S, BACK_OUT_MPS, HAZARD_RESUME_S, _Crew

    sent: list[tuple[float, str, object]] = []
    now = [0.0]
    bump = HeaderCounter(SimClock(), robot="uvc-1", sender="agent-uvc-1").make(
        Event, kind="bump", text="bumper pressed: stopped", severity=Severity.ERROR, data=()
    )
    run = RoundRun.__new__(RoundRun)
    run.op = SimpleNamespace(
        acks=[], events=[bump], states={}, action=lambda robot, kind, _id: sent.append((now[0], robot, kind))
    )
    run._send = lambda robot, cls, **f: sent.append((now[0], robot, f["v"] if cls is Teleop else cls))  # type: ignore[method-assign]
    run.crews = {"uvc-1": _Crew("uvc-1", order_id="uv-uvc-1-1", sent_at=0.0)}
    run.notes, run._acks, run._events, run.skipped = [], 0, 0, 0
    run._read(10.0)
    for k in range(1, 70):
        now[0] = 10.0 + 0.1 * k
        run._after_hazards(now[0])
    backs = [t for t, _, what in sent if what == BACK_OUT_MPS]
    resumes = [t for t, _, what in sent if what is ActionType.RESUME]
    assert BACK_OUT_MPS < 0.0 and len(backs) >= 9  # about a second, ten a second
    assert min(backs) >= 10.0 + BACK_OUT_AFTER_S - 1e-9 and max(backs) < 10.0 + BACK_OUT_AFTER_S + BACK_OUT_FOR_S
    assert resumes == [pytest.approx(10.0 + HAZARD_RESUME_S)]
    assert max(backs) < resumes[0]


@pytest.mark.slow
def test_two_robots_in_the_bedroom_plan_around_each_other_where_they_stand() -> None:
    """The bench's two-robot bedroom round at seed 16 (bench/coverage.py): uvc-1's dwell point lay
    0.1 m from where uvc-2 stood, finished; the map held only uvc-2's near face, and uvc-1 drove
    into it. Each agent now hears the other's pose and plans around it as a body (agent/peers.py)."""
    bedroom = (0.0, 5.7, 6.5, 8.0)
    robots = (("uvc-1", 2.2, 6.2, 0.0), ("uvc-2", 6.0, 6.6, 180.0))
    setup = RoundSetup("apartment", "bedroom", bedroom, robots, mode="uv", seed=16, deadline_s=1200.0)
    with RoundRun(setup) as run:
        result = run.run()
        heard = {r.name: r.node.core.peers.peers for r in run.mission.robots}
    assert heard == {"uvc-1": frozenset({"uvc-2"}), "uvc-2": frozenset({"uvc-1"})}
    assert result.finished, result.notes
    assert result.bumps == 0, result.notes
    assert result.coverage >= 0.99, (result.coverage, result.notes)
    assert result.lamp_outside_s == 0.0
