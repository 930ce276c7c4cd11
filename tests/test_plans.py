from __future__ import annotations

import copy
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from fleetlink.field.floor import Floor, ray_cast
from fleetlink.field.plans import (
    BUILTIN_PLANS,
    ROBOT_RADIUS,
    Anchor,
    FloorPlan,
    PlanError,
    Pose,
    builtin_plans,
    dump_plan,
    load_plan,
    parse_plan,
    save_plan,
)

# -- the built-in plans ----------------------------------------------------------------------------


@pytest.mark.parametrize("name", builtin_plans())
def test_every_builtin_loads_and_its_starts_are_clear(name: str) -> None:
    plan = load_plan(name)
    assert plan.name == name
    assert plan.starts and plan.anchors and len(plan.segments()) > 4
    for start, pose in plan.starts.items():
        assert plan.clearance(pose.x, pose.y) > ROBOT_RADIUS, start
        assert plan.is_clear(pose.x, pose.y), start
    segs = plan.segments()
    assert segs.shape[1] == 4 and segs.dtype == np.float64


def test_builtin_names() -> None:
    assert set(BUILTIN_PLANS) <= set(builtin_plans())
    assert "apartment-map" in builtin_plans()


def test_apartment_is_a_flat_with_rooms_furniture_dock_and_ceiling_anchors() -> None:
    plan = load_plan("apartment")
    assert 9 <= plan.width <= 12 and 7 <= plan.height <= 10
    assert {"living", "kitchen", "bedroom", "bathroom"} <= set(plan.doors)
    assert len(plan.obstacles) >= 3  # sofa, table, bed, ...
    assert "dock" in plan.starts and len(plan.starts) >= 3
    assert plan.starts["dock"].theta == pytest.approx(math.pi / 2)  # theta_deg = 90 in the file
    assert len(plan.anchors) >= 4 and all(a.z == pytest.approx(2.4) for a in plan.anchors)
    for x1, y1, x2, y2 in plan.doors.values():
        assert 0.75 <= math.hypot(x2 - x1, y2 - y1) <= 1.0


def test_office_has_corridor_rooms_doors_stairwell_and_anchors() -> None:
    plan = load_plan("office")
    assert (plan.width, plan.height) == (40.0, 20.0)
    assert {"room-3", "fire-door", "stairwell"} <= set(plan.doors)
    assert len(plan.anchors) >= 8
    assert "entrance" in plan.starts and len(plan.starts) >= 8
    assert plan.is_cliff(2.0, 18.0) and not plan.is_cliff(5.0, 17.0)  # stairs vs landing
    floor = plan.to_floor()
    assert floor.over_cliff(2.0, 18.0) and not floor.over_cliff(2.0, 10.0)
    # Down the corridor from the lobby: open to the far wall, blocked by the closed fire door.
    assert ray_cast(plan.segments(), 6.5, 9.75, 0.0, 100.0) == pytest.approx(33.5)
    closed = plan.segments(closed_doors=("fire-door",))
    assert ray_cast(closed, 6.5, 9.75, 0.0, 100.0) == pytest.approx(16.0)


def test_hall_fits_fifty_robots_on_a_grid() -> None:
    plan = load_plan("hall")
    assert plan.width >= 55 and plan.height >= 35
    assert len(plan.anchors) >= 8
    bays = [p for n, p in plan.starts.items() if n.startswith("bay-")]
    assert len(bays) >= 50
    assert list(plan.starts)[1:4] == ["bay-01", "bay-02", "bay-03"]
    xy = np.array([(p.x, p.y) for p in plan.starts.values()])
    d = np.hypot(xy[:, None, 0] - xy[None, :, 0], xy[:, None, 1] - xy[None, :, 1])
    np.fill_diagonal(d, np.inf)
    assert d.min() >= 1.0


def test_expos_patrol_places_see_their_walls_five_metres_off_or_more() -> None:
    # What the plan is for: open-space mapping (docs/mapping.md "Open spaces"), where the closer fills a
    # submap whose scans saw their walls 5 m off or more; from every patrol place a 12 m lidar sees them
    # that far (the median hit range of a turn: measured 5.9-7.3 m), most beams returning.
    from fleetlink.field.raycast import Raycaster

    plan = load_plan("expo")
    assert plan.width == 40 and plan.height == 25 and len(plan.anchors) >= 8
    caster = Raycaster(plan.segments())
    for name in ("sw", "s", "se", "ne", "n", "nw"):
        p = plan.starts[name]
        hits = caster.cast_fan(p.x, p.y, 0.0, math.radians(1.0), 360, 12.0)
        seen = hits[np.isfinite(hits)]
        assert 5.0 <= float(np.median(seen)) <= 12.0, name
        assert seen.size > 120, name  # a third of the beams or more return (measured 165-267 of 360)


def test_segments_add_closed_doors_and_refuse_unknown_ones() -> None:
    plan = load_plan("apartment")
    base = plan.segments()
    assert base.shape == (len(plan.walls) + sum(len(p) for p in plan.obstacles), 4)
    closed = plan.segments(closed_doors=["bedroom", "kitchen"])
    assert closed.shape[0] == base.shape[0] + 2
    assert tuple(closed[-2]) == plan.doors["bedroom"]
    with pytest.raises(PlanError, match=r"no door 'garage'.*doors: living"):
        plan.segments(closed_doors=["garage"])
    base[0, 0] = 99.0  # callers get a copy
    assert plan.segments()[0, 0] != 99.0


def test_to_floor_gives_the_board_a_floor() -> None:
    plan = load_plan("apartment")
    floor = plan.to_floor(closed_doors=("living",))
    assert isinstance(floor, Floor)
    assert len(floor.walls) == len(plan.segments()) + 1
    dock = plan.starts["dock"]
    assert floor.clearance(dock.x, dock.y) == pytest.approx(0.4)
    assert floor.ray(dock.x, dock.y, -math.pi / 2, 5.0) == pytest.approx(0.4)  # the wall behind the dock
    assert not floor.over_cliff(dock.x, dock.y)


def test_contains_is_cliff_and_is_clear() -> None:
    plan = load_plan("office")
    assert plan.contains(0.0, 0.0) and plan.contains(40.0, 20.0) and not plan.contains(40.1, 5.0)
    assert not plan.is_clear(3.0, 7.0)  # a pillar
    assert not plan.is_clear(2.0, 18.0)  # the stairs
    assert not plan.is_clear(6.05, 5.0)  # against a wall
    assert plan.is_clear(20.0, 9.75)


def test_plans_are_frozen_values() -> None:
    a, b = load_plan("apartment"), load_plan("apartment")
    assert a == b and hash(a) == hash(b)
    with pytest.raises(AttributeError):
        a.name = "x"  # type: ignore[misc]
    with pytest.raises(TypeError):
        a.starts["x"] = Pose(1, 1, 0)  # type: ignore[index]


def test_programmatic_plan_is_validated_and_normalised() -> None:
    plan = FloorPlan(
        name="box",
        bounds=(0, 0, 4, 3),
        walls=[[0, 0, 4, 0], [4, 0, 4, 3], [4, 3, 0, 3], [0, 3, 0, 0]],  # type: ignore[arg-type]
        starts={"a": (1, 1, 0.5)},  # type: ignore[dict-item]
        anchors=[("A1", 0, 0, 2)],  # type: ignore[arg-type]
    )
    assert plan.walls[0] == (0.0, 0.0, 4.0, 0.0) and isinstance(plan.walls, tuple)
    assert plan.starts["a"] == Pose(1.0, 1.0, 0.5) and plan.anchors == (Anchor("A1", 0.0, 0.0, 2.0),)
    with pytest.raises(PlanError, match=r"<memory>: starts\.b: \(0\.1, 1\) is 0\.100 m from walls\[3\]"):
        FloorPlan(name="box", bounds=(0, 0, 4, 3), walls=plan.walls, starts={"b": Pose(0.1, 1, 0)})


# -- validation ------------------------------------------------------------------------------------

BASE: dict[str, Any] = {
    "name": "t",
    "bounds": [0.0, 0.0, 6.0, 4.0],
    "walls": [[0.0, 0.0, 6.0, 0.0], [6.0, 0.0, 6.0, 4.0], [6.0, 4.0, 0.0, 4.0], [0.0, 4.0, 0.0, 0.0]],
    "obstacles": [{"name": "box", "polygon": [[4.0, 1.0], [5.0, 1.0], [5.0, 2.0], [4.0, 2.0]]}],
    "cliffs": [{"polygon": [[0.5, 3.0], [1.5, 3.0], [1.5, 3.8], [0.5, 3.8]]}],
    "doors": {"d1": [3.0, 0.0, 3.0, 1.0]},
    "starts": {"s": {"x": 1.0, "y": 1.0, "theta_deg": 0.0}},
    "anchors": [{"id": "A1", "x": 0.0, "y": 0.0, "z": 2.4}, {"id": "A2", "x": 6.0, "y": 4.0, "z": 2.4}],
}


def _with(**changes: Any) -> dict[str, Any]:
    data = copy.deepcopy(BASE)
    for key, value in changes.items():
        if value is None:
            data.pop(key, None)
        else:
            data[key] = value
    return data


def test_base_plan_is_valid() -> None:
    plan = parse_plan(BASE, "t.toml")
    assert plan.starts["s"] == Pose(1.0, 1.0, 0.0) and plan.source == "t.toml"


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (_with(bounds=None), "t.toml: bounds: missing required key"),
        (_with(walls=None), "t.toml: walls: missing required key"),
        (
            _with(wall=[]),
            "t.toml: wall: unknown key (did you mean walls?); allowed: access_points, anchors, bounds, cliffs, dead_zones",
        ),
        (_with(bounds="big"), "bounds: expected [xmin, ymin, xmax, ymax], got str 'big'"),
        (_with(bounds=[0, 0, 6]), "bounds: expected [xmin, ymin, xmax, ymax]"),
        (_with(bounds=[6, 0, 0, 4]), "bounds: expected xmin < xmax and ymin < ymax"),
        (_with(bounds=[0, 0, math.inf, 4]), "bounds[2]: must be finite, got inf"),
        (_with(name=3), "name: expected a string, got int 3"),
        (_with(walls={"a": 1}), "walls: expected a list of [x1, y1, x2, y2] segments"),
        (_with(walls=[[0, 0, 6, 0], [1, 1, 2]]), "walls[1]: expected [x1, y1, x2, y2], got [1, 1, 2]"),
        (_with(walls=[[0, 0, 6, "0"]]), "walls[0][3]: expected a number, got str '0'"),
        (_with(walls=[[0, 0, 6, True]]), "walls[0][3]: expected a number, got bool True"),
        (_with(walls=[[0, math.nan, 6, 0]]), "walls[0][1]: must be finite, got nan"),
        (_with(walls=[[0, 0, 6, 0], [2, 2, 2, 2]]), "walls[1]: degenerate segment: both ends at (2, 2)"),
        (_with(walls=[[0, 0, 7, 0]]), "walls[0]: point (7, 0) lies outside the bounds [0, 0, 6, 4]"),
        (
            _with(obstacles=[{"polygon": [[1, 1], [2, 2]]}]),
            "obstacles[0].polygon: needs at least 3 items, got 2; expected a polygon of [x, y] points",
        ),
        (_with(obstacles=[{"polygon": [[1, 1], [2, 2], [3, 3]]}]), "obstacles[0]: the polygon has no area"),
        (_with(obstacles=[{"polygon": [[1, 1], [2, 2], [3]]}]), "obstacles[0].polygon[2]: expected [x, y], got [3]"),
        (
            _with(obstacles=[{"poly": []}]),
            "obstacles[0].poly: unknown key (did you mean polygon?); allowed: name, polygon",
        ),
        (_with(obstacles=[{"name": "x"}]), "obstacles[0].polygon: missing required key"),
        (_with(obstacles={"polygon": []}), "obstacles: expected an array of tables, got a table"),
        (_with(cliffs=[{"polygon": [[1, 1], [2, 1]]}]), "cliffs[0].polygon: needs at least 3 items, got 2"),
        (_with(doors={"d1": [3, 0, 3]}), "doors.d1: expected [x1, y1, x2, y2]"),
        (_with(doors={"d1": [3, 1, 3, 1]}), "doors.d1: degenerate segment"),
        (_with(doors={"bad name": [3, 0, 3, 1]}), "doors.bad name: names use letters, digits"),
        (_with(doors=[1]), "doors: expected a table, got [1]"),
        (
            _with(starts={"s": {"x": 1, "y": 1, "theta": 1.57}}),
            "starts.s.theta: unknown key (did you mean theta_deg?); allowed: theta_deg, x, y",
        ),
        (_with(starts={"s": {"x": 1, "y": 1}}), "starts.s.theta_deg: missing required key"),
        (_with(starts={"s": [1, 1, 0]}), "starts.s: expected a table { x = ..., y = ..., theta_deg = ... }"),
        (_with(starts={"s": {"x": 1, "y": math.inf, "theta_deg": 0}}), "starts.s.y: must be finite"),
        (_with(starts={"s": {"x": 7, "y": 1, "theta_deg": 0}}), "starts.s: (7, 1) lies outside the bounds"),
        (_with(starts={"s": {"x": 4.5, "y": 1.5, "theta_deg": 0}}), "starts.s: (4.5, 1.5) is inside obstacles[0]"),
        (_with(starts={"s": {"x": 1, "y": 3.5, "theta_deg": 0}}), "starts.s: (1, 3.5) is over cliffs[0]"),
        (_with(starts={"s": {"x": 1, "y": 0.1, "theta_deg": 0}}), "starts.s: (1, 0.1) is 0.100 m from walls[0]"),
        (
            _with(starts={"s": {"x": 3.9, "y": 1.5, "theta_deg": 0}}),
            "starts.s: (3.9, 1.5) is 0.100 m from obstacles[0]",
        ),
        (_with(starts={"s p": {"x": 1, "y": 1, "theta_deg": 0}}), "starts.s p: names use letters"),
        (
            _with(anchors=[{"id": "A1", "x": 0, "y": 0, "z": 2}, {"id": "A1", "x": 1, "y": 0, "z": 2}]),
            "anchors[1].id: anchor 'A1' appears twice",
        ),
        (_with(anchors=[{"id": "A1", "x": 0, "y": 0}]), "anchors[0].z: missing required key"),
        (
            _with(anchors=[{"id": "A1", "x": 0, "y": 0, "z": 2, "h": 1}]),
            "anchors[0].h: unknown key; allowed: id, x, y, z",
        ),
        (_with(anchors=[{"id": 1, "x": 0, "y": 0, "z": 2}]), "anchors[0].id: expected a string, got int 1"),
        (
            _with(start_grid=[{"prefix": "g", "x0": 1, "y0": 1, "dx": 0.2, "dy": 1, "nx": 2, "ny": 1, "theta_deg": 0}]),
            "start_grid[0].dx: must be at least 0.34 m",
        ),
        (
            _with(start_grid=[{"prefix": "g", "x0": 1, "y0": 1, "dx": 1, "dy": 1, "nx": 2.5, "ny": 1, "theta_deg": 0}]),
            "start_grid[0].nx: expected a whole number, got float 2.5",
        ),
        (
            _with(start_grid=[{"prefix": "s", "x0": 2, "y0": 1, "dx": 1, "dy": 1, "nx": 1, "ny": 1}]),
            "start_grid[0].theta_deg: missing required key",
        ),
        (
            _with(start_grid=[{"prefix": "g", "x0": 1, "y0": 2.5, "dx": 1, "dy": 1, "nx": 2, "ny": 2, "theta_deg": 0}]),
            "starts.g03: (1, 3.5) is over cliffs[0]",
        ),
    ],
)
def test_validation_names_the_key_and_the_problem(data: dict[str, Any], message: str) -> None:
    with pytest.raises(PlanError) as err:
        parse_plan(data, "t.toml")
    assert message in str(err.value)
    assert str(err.value).startswith("t.toml: ")


def test_start_grid_names_and_collisions() -> None:
    grid = {"prefix": "g-", "x0": 1.0, "y0": 1.0, "dx": 0.5, "dy": 0.5, "nx": 3, "ny": 2, "theta_deg": 90.0}
    plan = parse_plan(_with(start_grid=[grid]))
    names = [n for n in plan.starts if n.startswith("g-")]
    assert names == ["g-01", "g-02", "g-03", "g-04", "g-05", "g-06"]
    assert plan.starts["g-05"] == pytest.approx((1.5, 1.5, math.pi / 2))
    with pytest.raises(PlanError, match=r"start_grid\[0\]: start 's01' already exists"):
        parse_plan(
            _with(
                starts={"s01": {"x": 1.0, "y": 1.0, "theta_deg": 0.0}},
                start_grid=[{**grid, "prefix": "s", "nx": 1, "ny": 1, "y0": 2.0}],
            )
        )


def test_load_plan_errors_name_the_file(tmp_path: Path) -> None:
    with pytest.raises(PlanError, match=r"garage: no such plan: not a built-in \(apartment, "):
        load_plan("garage")
    bad = tmp_path / "bad.toml"
    bad.write_text("bounds = [0, 0\n")
    with pytest.raises(PlanError, match=r"bad\.toml: not valid TOML"):
        load_plan(bad)
    inf = tmp_path / "inf.toml"
    inf.write_text("bounds = [0, 0, 5, 5]\nwalls = [[0, 0, inf, 0]]\n")
    with pytest.raises(PlanError, match=r"inf\.toml: walls\[0\]\[2\]: must be finite, got inf"):
        load_plan(inf)
    other = tmp_path / "plan.json"
    other.write_text("{}")
    with pytest.raises(PlanError, match=r"unknown plan format \.json"):
        load_plan(other)
    with pytest.raises(PlanError, match="cannot read"):
        load_plan(tmp_path / "missing.toml")


# -- TOML round trip -------------------------------------------------------------------------------

CUSTOM = """
name = "garage"
description = "A \\"double\\" garage"
bounds = [0.0, 0.0, 6.5, 5.0]
walls = [
  [0.0, 0.0, 6.5, 0.0],
  [6.5, 0.0, 6.5, 5.0],
  [6.5, 5.0, 0.0, 5.0],
  [0.0, 5.0, 0.0, 0.0],
  [3.0, 0.0, 3.0, 2.0],
]

[[obstacles]]
name = "car"
polygon = [[0.5, 2.5], [2.5, 2.5], [2.5, 4.7], [0.5, 4.7]]

[[cliffs]]
polygon = [[4.0, 4.0], [6.0, 4.0], [5.0, 4.9]]

[doors]
inner = [3.0, 2.0, 3.0, 2.8]

[starts]
door = { x = 4.5, y = 1.0, theta_deg = 135.0 }

[[start_grid]]
prefix = "row-"
x0 = 3.5
y0 = 2.5
dx = 0.5
dy = 0.5
nx = 3
ny = 1
theta_deg = -30.0

[[anchors]]
id = "G1"
x = 0.0
y = 0.0
z = 2.2
"""


def test_toml_round_trip(tmp_path: Path) -> None:
    src = tmp_path / "garage.toml"
    src.write_text(CUSTOM)
    plan = load_plan(src)
    assert plan.name == "garage" and plan.description == 'A "double" garage'
    assert list(plan.starts) == ["door", "row-01", "row-02", "row-03"]
    assert plan.starts["door"].theta == pytest.approx(math.radians(135.0))
    out = save_plan(plan, tmp_path / "copy.toml")
    again = load_plan(out)
    assert again.walls == plan.walls and again.obstacles == plan.obstacles and again.cliffs == plan.cliffs
    assert dict(again.doors) == dict(plan.doors) and again.anchors == plan.anchors
    assert again.bounds == plan.bounds and again.description == plan.description and again.name == plan.name
    assert list(again.starts) == list(plan.starts)
    for name, pose in plan.starts.items():
        assert again.starts[name] == pytest.approx(pose, abs=1e-12)
    assert dump_plan(again) == dump_plan(plan)
    assert np.array_equal(again.segments(["inner"]), plan.segments(["inner"]))


def test_dump_of_every_builtin_reloads(tmp_path: Path) -> None:
    for name in BUILTIN_PLANS:
        plan = load_plan(name)
        again = load_plan(save_plan(plan, tmp_path / f"{name}.toml"))
        assert again.walls == plan.walls and len(again.starts) == len(plan.starts)


def test_nearest_segment_distances_by_hand() -> None:
    from fleetlink.field.plans import nearest_segment_distances

    segs = np.array([[0.0, 0.0, 2.0, 0.0], [3.0, -1.0, 3.0, 1.0]])
    pts = np.array([[1.0, 0.5], [-1.0, 0.0], [2.5, 0.0], [3.0, 2.0], [10.0, 0.0]])
    d = nearest_segment_distances(pts, segs)
    assert d == pytest.approx([0.5, 1.0, 0.5, 1.0, 7.0])
    many = np.column_stack((np.linspace(0.0, 2.0, 5001), np.full(5001, 0.25)))  # more than one chunk
    assert nearest_segment_distances(many, segs, chunk=1000) == pytest.approx(np.full(5001, 0.25))
    assert np.isinf(nearest_segment_distances(pts, np.zeros((0, 4)))).all()
