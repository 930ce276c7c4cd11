"""The rescue sortie in lockstep (issue 15): whole agents, the office's radio, a scripted operator.

field/scenarios/sortie.toml with site/sortie.py's shorter script: both scouts drive out of the
entrance by teleop; scout-2 searches room-8, marks the casualty there and returns home; scout-1
goes down the corridor by go-tos into the records room (room-6, no radio), loses both links,
retraces under the ``retrace`` policy until it is reached again, and returns home. The operator
holds both leases (renewed every 2 s on both links) and sends through the console's link manager;
return home goes on both links. Asserted against truth: the mark, both robots home, no bump, the
contact span, nothing executed twice (the copies were refused). bench/sortie.py runs the full
sortie and the ``stop`` baseline.
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import pytest

from fleetlink.field.scenario import ScenarioError, load_scenario, parse_scenario
from fleetlink.shared.messages import AckResult, CommsPolicy
from fleetlink.site.sortie import Drive, GoTo, Home, Policy, Search, SortieResult, SortieRun, office_sortie, percentile

# One worker runs this module under pytest-xdist, so its module-scoped set-up runs once.
pytestmark = pytest.mark.xdist_group("sortie_mission")

SORTIE = Path(__file__).resolve().parents[1] / "field" / "scenarios" / "sortie.toml"


@pytest.fixture(scope="module")
def sortie() -> SortieResult:
    sc = load_scenario(SORTIE)
    with SortieRun(sc, script=office_sortie(sc, quick=True), policy=CommsPolicy.RETRACE) as run:
        return run.run()


@pytest.mark.slow
def test_both_scouts_finish_their_scripts_and_end_home(sortie: SortieResult) -> None:
    assert sortie.done == {"scout-1": True, "scout-2": True}, sortie.log
    assert sortie.sim_s < 300.0  # well before the scenario's 480 s deadline
    for robot, d in sortie.home_distance_m.items():
        assert d <= 0.20, (robot, d, sortie.log)
    # Return home was carried out (reached), not merely sent.
    homes = [line for line in sortie.log if "return home: reached" in line]
    assert len(homes) == 2, sortie.log
    truth = sortie.mission.field.truth
    for robot in ("scout-1", "scout-2"):
        _, _, _, _, v, w = truth[robot][-1]
        assert abs(v) < 1e-3 and abs(w) < 1e-3  # at rest at the end


@pytest.mark.slow
def test_the_casualty_in_sight_is_marked_from_the_robots_pose(sortie: SortieResult) -> None:
    assert [m.casualty for m in sortie.marks] == ["room-8"]
    (m,) = sortie.marks
    assert m.robot == "scout-2"
    assert m.error_m <= 0.30
    assert m.range_m <= 0.6  # the operator drove up to it before marking
    assert 0.0 < m.sd_m < 0.3  # the fused pose's uncertainty went with the mark
    # The odometry-only baseline of the same mark is worse (no UWB).
    assert m.odometry_error_m > m.error_m
    # The Mark went out on the wire.
    assert any(" marks " in line and "scout-2" in line for line in sortie.mission.commands)


@pytest.mark.slow
def test_the_records_room_cuts_both_links_and_retrace_brings_the_scout_back_in_contact(
    sortie: SortieResult,
) -> None:
    assert sortie.contact["scout-2"] == []
    (span,) = sortie.contact["scout-1"]
    lost, back = span
    assert back is not None, "scout-1 never came back in contact"
    assert back - lost <= 30.0
    assert sortie.regain_s == pytest.approx(back - lost)
    # Lost only after the 6 s comms timeout can it act: the retrace drove it out of the room.
    assert back - lost > 6.0
    (text,) = sortie.regained["scout-1"]
    assert "retrac" in text, text
    # The robot reported regained contact once it heard the operator's next lease renewal (2 s).
    heard = sortie.regain_heard_s
    assert heard is not None and back - lost <= heard <= back - lost + 2.5
    # Where the radio says: both links went at the records room's door (its dead zone starts at y 8.5).
    radio = [e for e in sortie.mission.field.events if "scout-1" in e and "out of radio reach" in e]
    assert {"zenoh", "mqtt"} <= {w for e in radio for w in e.split()}, radio
    assert sortie.out_of_contact_s["scout-1"] == pytest.approx(back - lost)


@pytest.mark.slow
def test_no_bumps_and_nothing_executed_twice(sortie: SortieResult) -> None:
    assert sortie.collisions == {"scout-1": 0, "scout-2": 0}, sortie.log
    assert sortie.min_clearance_m > 0.0
    assert sortie.executed_twice == 0, {k: [i for i, n in c.items() if n > 1] for k, c in sortie.executions.items()}
    # Each return home went on both links: the second copy was refused as a duplicate, not run.
    assert sortie.duplicates_refused >= 2
    dup = [a for a in sortie.mission.acks if a.result is AckResult.DUPLICATE]
    assert {a.header.robot for a in dup} == {"scout-1", "scout-2"}
    # Every order the agents accepted was accepted once (the acks agree with the agents' count).
    accepted = [
        (a.header.robot, a.orderId) for a in sortie.mission.acks if a.orderId and a.result is AckResult.ACCEPTED
    ]
    assert len(accepted) == len(set(accepted))
    orders = sum(1 for c in sortie.executions.values() for ident in c if ident[0] == "order")
    assert orders == len(accepted)


# -- the parts, without running agents ----------------------------------------------------------------


def test_the_sortie_scenario_places_casualties_in_rooms() -> None:
    sc = load_scenario(SORTIE)
    assert [r.name for r in sc.robots] == ["scout-1", "scout-2"]
    assert {c.name for c in sc.casualties} == {"room-2", "room-4", "room-8", "room-11"}
    assert all(c.label for c in sc.casualties)


def test_a_casualty_named_twice_is_refused_with_its_place() -> None:
    text = """
    plan = "office"
    [[robots]]
    name = "r1"
    start = "entrance"
    [[casualties]]
    name = "c"
    x = 1.0
    y = 9.0
    [[casualties]]
    name = "c"
    x = 2.0
    y = 9.0
    """
    with pytest.raises(ScenarioError, match=r"casualties\[1\]\.name: casualty 'c' appears twice"):
        parse_scenario(tomllib.loads(text), source="twice.toml")


def test_a_sortie_needs_casualties_and_casualties_on_the_floor() -> None:
    base = {"plan": "office", "robots": [{"name": "r1", "start": "entrance", "drive": "agent"}]}
    with pytest.raises(ValueError, match="needs"):
        SortieRun(parse_scenario(base))
    inside_pillar = {**base, "casualties": [{"name": "c", "x": 3.0, "y": 7.0}]}
    with pytest.raises(ValueError, match="obstacle"):
        SortieRun(parse_scenario(inside_pillar))
    one = parse_scenario({**base, "casualties": [{"name": "c", "x": 9.0, "y": 9.75}]})
    with pytest.raises(ValueError, match="two robots"):
        SortieRun(one)  # the office script drives two
    with pytest.raises(ValueError, match=r"robots the scenario does not have: \['nobody'\]"):
        SortieRun(one, script={"nobody": (Home(),)})


def test_the_office_script_has_every_part_of_the_sortie() -> None:
    sc = load_scenario(SORTIE)
    for quick in (False, True):
        script = office_sortie(sc, quick=quick)
        first, second = script["scout-1"], script["scout-2"]
        for tasks in (first, second):
            assert isinstance(tasks[0], Policy) and isinstance(tasks[1], Drive) and isinstance(tasks[-1], Home)
        assert any(isinstance(t, GoTo) and "records room" in t.note for t in first)
        assert any(isinstance(t, Search) for t in second)
    full = office_sortie(sc)
    searched = [t.note for tasks in full.values() for t in tasks if isinstance(t, Search)]
    assert sorted(searched) == sorted(c.name for c in sc.casualties)  # a search per casualty's room


def test_percentile_interpolates_like_numpy() -> None:
    assert percentile([1.0, 2.0, 3.0, 4.0], 95) == pytest.approx(3.85)
    assert percentile([0.5], 95) == 0.5
    assert math.isnan(percentile([], 95))
