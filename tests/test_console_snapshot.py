"""Snapshot tests of the console's main screen (pytest-textual-snapshot's ``snap_compare``).

The console runs on the same in-memory rig as tests/test_console.py (the real OperatorLink, codec
and link manager over memory transports), but on a ``SimClock`` that only the test moves: ages,
link health and order ids on screen come out the same on every run. The robots' messages are
injected one by one (no talking thread), so the fleet model sees the same sequence every time.

The SVGs live in tests/__snapshots__/test_console_snapshot/. After a deliberate change to the
screen, look at the failure report pytest prints, then accept the new pictures with
``./dev test tests/test_console_snapshot.py --snapshot-update`` and commit them.
"""

from __future__ import annotations

import asyncio
import json
import math
from collections.abc import Awaitable, Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from fleetlink.operator.dose import FleetDose
from fleetlink.operator.maps import MapFollower
from fleetlink.shared import wire
from fleetlink.shared.clock import SimClock
from fleetlink.shared.dose import DoseGrid
from fleetlink.shared.map_codec import snapshot_fields
from fleetlink.shared.messages import (
    AgvPosition,
    BatteryState,
    Event,
    FixStatus,
    Goal,
    Home,
    HomeSource,
    Lease,
    MapSnapshot,
    Mark,
    OperatingMode,
    Order,
    Pose,
    Scan,
    Severity,
    State,
    Teleop,
    UwbFix,
    Velocity,
)
from fleetlink.shared.scan_codec import scan_fields
from tests.harness.messages import state as harness_state
from tests.test_console import ME, Rig

SIZE = (140, 45)
START = 100.0
"""Simulated seconds at which the console starts; the robots speak from here on."""

Snap = Callable[..., bool]
"""``snap_compare(app, press=(), terminal_size=(w, h), run_before=None) -> bool``."""


def make_rig(tmp_path: Path, *, read_only: bool = False) -> Rig:
    """The console rig of tests/test_console.py, on a simulated clock instead of the system's."""
    rig = Rig(tmp_path, read_only=read_only, clock=SimClock(start=START))
    rig.start()
    return rig


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[Rig]:
    r = make_rig(tmp_path)
    try:
        yield r
    finally:
        r.close()


@pytest.fixture
def read_only_rig(tmp_path: Path) -> Iterator[Rig]:
    r = make_rig(tmp_path, read_only=True)
    try:
        yield r
    finally:
        r.close()


# -- fixed data ---------------------------------------------------------------------------------

RES = 0.1
ORIGIN = (-1.0, -1.0)


def room() -> np.ndarray:
    """An 8 m x 5 m room from (-1, -1): walls around, a door on the right, a half wall inside,
    unknown beyond a corner the robots have not seen. Row 0 is the bottom (y = -1)."""
    h, w = 50, 80
    cells = np.zeros((h, w), dtype=np.int8)
    cells[0, :] = cells[-1, :] = 100
    cells[:, 0] = cells[:, -1] = 100
    cells[20:30, -1] = 0  # the door, y 1..2 m
    cells[25:, 40] = 100  # a half wall at x = 3 m, from y = 1.5 m up
    cells[35:49, 60:79] = -1  # not seen yet
    return cells


ANCHORS = [("a1", -1.0, -1.0, 2.0), ("a2", 7.0, -1.0, 2.0), ("a3", 7.0, 4.0, 2.0), ("a4", -1.0, 4.0, 2.0)]


def state(rig: Rig, robot: str, x: float, y: float, theta: float, **over: Any) -> State:
    position = AgvPosition(x=x, y=y, theta=theta, mapId="office", positionInitialized=True, localizationScore=0.9)
    return harness_state(rig.counter(robot), agvPosition=position, **over)


def say(rig: Rig, msg: wire.Message) -> None:
    """A robot's message, heard on both links (the console keeps the first copy)."""
    rig.zenoh.inject(msg)
    rig.mqtt.inject(msg)


def pose(rig: Rig, robot: str, x: float, y: float, theta: float, *, uwb_stale: bool = False) -> None:
    """Like ``Rig.pose``, with the agent's UWB-stale flag."""
    msg = rig.counter(robot).make(
        Pose, x=x, y=y, theta=theta, sd_x_m=0.05, sd_y_m=0.05, sd_theta_rad=0.01, odom_x=x, odom_y=y,
        odom_theta=theta, vx=0.0, omega=0.0, uwbStale=uwb_stale,
    )  # fmt: skip
    say(rig, msg)


def event(rig: Rig, robot: str, kind: str, text: str, severity: Severity) -> Event:
    return rig.counter(robot).make(Event, kind=kind, text=text, severity=severity, data=())


def two_robots(rig: Rig) -> None:
    """r1 idle by the left wall, r2 on an order towards the door; anchors, the room map, a mark
    from another console and three notices. All synchronous: the console's feed folds it all in as
    one batch before the next frame, so the first fit of the map is always the same."""
    clock = rig.clock
    assert isinstance(clock, SimClock)
    status = {"gateway": "g1", "anchors": [list(a) for a in ANCHORS]}
    # the gateway's retained status, as MQTT delivers it
    rig.mqtt.inject_raw("fleetlink/uwb/g1/status", json.dumps(status).encode())
    follower = MapFollower(rig.fleet)
    snap = rig.counter("r1").make(MapSnapshot, **snapshot_fields(room(), RES, ORIGIN, 7))
    with rig.lock:
        assert follower.on_snapshot("r1", snap)

    say(rig, state(rig, "r1", 0.5, 0.5, 0.0, batteryState=BatteryState(batteryCharge=87.0, charging=False)))
    say(rig, rig.counter("r1").make(Lease, holder="", until=0.0))
    pose(rig, "r1", 0.5, 0.5, 0.0)
    say(rig, event(rig, "r1", "goal_reached", "reached (0.50, 0.50)", Severity.INFO))
    fix = rig.counter("r1").make(
        UwbFix, tag="t1", x=0.52, y=0.49, z=0.3, sd_x=0.08, sd_y=0.08, quality=95, status=FixStatus.OK,
        anchors=("a1", "a2", "a3", "a4"), residual_rms_m=0.04, measured_at=clock.wall(),
    )  # fmt: skip
    say(rig, fix)

    clock.advance(0.2)
    r2_goal = Goal(x=6.5, y=1.5, theta=None)
    say(
        rig,
        state(
            rig, "r2", 4.0, 0.5, math.pi / 4, operatingMode=OperatingMode.AUTOMATIC, driveMode="goto",
            batteryState=BatteryState(batteryCharge=42.0, charging=False), uwbStale=True,
            orderId="operator-1-order-3", goal=r2_goal, driving=True,
        ),
    )  # fmt: skip
    say(rig, rig.counter("r2").make(Lease, holder=ME, until=clock.wall() + 60))
    for k in range(6):  # the way it came: a trail behind it
        x = 2.5 + 0.25 * k
        pose(rig, "r2", x, -0.25 + 0.125 * k, math.pi / 4, uwb_stale=True)
    say(rig, event(rig, "r2", "guard_refusal", "obstacle 0.35 m ahead: forward refused", Severity.WARNING))
    other = wire.HeaderCounter(clock, robot="r1", sender="operator-2")
    rig.zenoh.inject(
        other.make(Mark, markId="op2-1", x=5.5, y=3.0, label="victim", kind="casualty", sd_m=0.0, removed=False)
    )
    clock.advance(0.1)  # on screen: r1 last heard 300 ms ago, r2 100 ms ago (both links still healthy)


async def settle(pilot: Any) -> None:
    """Wait until the console has drawn two frames since the last step (one for what the step
    changed, one on the clock tick), so the table, notices and map show what was injected (the
    simulated clock does not move meanwhile)."""
    frames = pilot.app.frame_times
    seen = len(frames)
    for _ in range(200):
        await asyncio.sleep(0.05)
        if len(frames) >= seen + 2:
            break
    await pilot.pause()


def before(*steps: Callable[[Any], Awaitable[None] | None]) -> Callable[[Any], Awaitable[None]]:
    async def run(pilot: Any) -> None:
        for step in steps:
            result = step(pilot)
            if result is not None:
                await result
            await settle(pilot)

    return run


# -- the snapshots --------------------------------------------------------------------------------


def test_two_robots_reporting(snap_compare: Snap, rig: Rig) -> None:
    """Fleet table with r1 (free lease, UWB ok) and r2 (on an order, leased to you, UWB stale);
    the map with the room, four anchors (A), r1 selected, r2 with its trail and goal (G), another
    console's casualty mark; notices for a goal reached and a guard refusal."""
    assert snap_compare(rig.app, terminal_size=SIZE, run_before=before(lambda _p: two_robots(rig)))


def test_robot_selected_while_driving(snap_compare: Snap, rig: Rig) -> None:
    """Tab selects r2 (the next row), i drives it forward: it reports MANUAL / teleop and moves up
    the room (r1 keeps reporting where it is)."""
    clock = rig.clock
    assert isinstance(clock, SimClock)

    async def drive(pilot: Any) -> None:
        await pilot.press("tab")  # the next robot; the map keeps the focus
        await pilot.press("i")

    def moves(_pilot: Any) -> None:
        for k in range(1, 5):
            clock.advance(0.05)
            pose(rig, "r1", 0.5, 0.5, 0.0)
            pose(rig, "r2", 4.0, 0.5 + 0.3 * k, math.pi / 2, uwb_stale=True)
        say(
            rig,
            state(
                rig, "r2", 4.0, 1.7, math.pi / 2, operatingMode=OperatingMode.MANUAL, driveMode="teleop",
                velocity=Velocity(vx=0.3, omega=0.0), driving=True, uwbStale=True,
                batteryState=BatteryState(batteryCharge=42.0, charging=False),
            ),
        )  # fmt: skip

    assert snap_compare(rig.app, terminal_size=SIZE, run_before=before(lambda _p: two_robots(rig), drive, moves))
    assert rig.app.selected == "r2"
    drives = rig.zenoh.messages(Teleop)
    assert drives and all(t.header.robot == "r2" and t.v > 0 for t in drives)


def test_goal_confirmation_after_map_click(snap_compare: Snap, rig: Rig) -> None:
    """A click on the map opens the dialog: the world point, and y / m / n."""

    async def click(pilot: Any) -> None:
        await pilot.click("#map", offset=(50, 12))

    assert snap_compare(rig.app, terminal_size=SIZE, run_before=before(lambda _p: two_robots(rig), click))
    assert not rig.zenoh.messages(Order)  # nothing sent before the answer


def test_read_only_mode(snap_compare: Snap, read_only_rig: Rig) -> None:
    """READ-ONLY in the status line; a drive key is refused with a notice, nothing goes out."""
    r = read_only_rig

    async def drive(pilot: Any) -> None:
        await pilot.press("i")

    assert snap_compare(r.app, terminal_size=SIZE, run_before=before(lambda _p: two_robots(r), drive))
    assert r.zenoh.sent == [] and r.mqtt.sent == []


# -- the map ------------------------------------------------------------------------------------------


def ray_cast(cells: np.ndarray, x: float, y: float, beams: int = 360) -> tuple[np.ndarray, np.ndarray]:
    """What a lidar at (x, y), heading 0, sees of ``room()``: the range to the first wall each beam."""
    angles = np.arange(beams) * (2 * math.pi / beams)
    ranges = np.zeros(beams)
    h, w = cells.shape
    for k, a in enumerate(angles):
        for step in range(1, 1500):
            d = step * 0.01
            i = math.floor((x + d * math.cos(a) - ORIGIN[0]) / RES)
            j = math.floor((y + d * math.sin(a) - ORIGIN[1]) / RES)
            if not (0 <= i < w and 0 <= j < h):
                break
            if cells[j, i] == 100:
                ranges[k] = d
                break
    return angles, ranges


def map_extras(rig: Rig) -> None:
    """On top of ``two_robots``: r1's lidar scan (it is selected), r2's home, a hazard and a note."""
    clock = rig.clock
    assert isinstance(clock, SimClock)
    angles, ranges = ray_cast(room(), 0.5, 0.5)
    rig.zenoh.inject(rig.counter("r1").make(Scan, **scan_fields(angles, ranges, (0.5, 0.5, 0.0))))
    home = Home(x=0.5, y=3.0, theta=None, source=HomeSource.LOCALISED)
    say(
        rig,
        state(
            rig, "r2", 4.0, 0.5, math.pi / 4, operatingMode=OperatingMode.AUTOMATIC, driveMode="goto",
            batteryState=BatteryState(batteryCharge=42.0, charging=False), uwbStale=True,
            orderId="operator-1-order-3", goal=Goal(x=6.5, y=1.5, theta=None), driving=True, home=home,
        ),
    )  # fmt: skip
    other = wire.HeaderCounter(clock, robot="r2", sender="operator-2")
    for mark_id, kind, x, y in (("op2-2", "hazard", 2.0, 3.3), ("op2-3", "note", 6.0, -0.4)):
        rig.zenoh.inject(other.make(Mark, markId=mark_id, x=x, y=y, label=kind, kind=kind, sd_m=0.0, removed=False))


def dose_layer(rig: Rig) -> None:
    """A dose layer over the left of the room, rising left to right from nothing to twice the target."""
    res = 0.05
    xs = np.arange(0, 60) * res  # x 0 .. 3 m
    dose = np.tile(np.clip(xs / 3.0, 0.0, 1.0) * 200.0, (80, 1))  # y -0.5 .. 3.5 m
    grid = DoseGrid.from_array(dose, res, (-res / 2, -0.5 - res / 2))
    layer = FleetDose(grid, 100.0, ("r1",), (), 60.0, 0.0, 23, 1)
    with rig.lock:
        rig.app.doses.layer = layer


def test_the_map_in_half_blocks_with_a_scan_home_marks_and_an_alarm(snap_compare: Snap, rig: Rig) -> None:
    """The map at two pixels a cell: the room's walls, floor and unknown corner in colour, r1's
    lidar scan (r1 is selected) in red over it, r2's trail, goal, home and its alarm (UWB stale),
    a casualty, a hazard and a note, the anchors, the legend on the bottom lines."""
    seen: list[str] = []

    def legend(pilot: Any) -> None:
        frame = pilot.app.query_one("#map").frame
        seen.extend(frame.text(frame.height - k) for k in (1, 2))

    steps = before(lambda _p: two_robots(rig), lambda _p: map_extras(rig), legend)
    assert snap_compare(rig.app, terminal_size=SIZE, run_before=steps)
    assert "scan" in " ".join(seen)  # explained now that one is drawn


def test_the_map_with_the_dose_layer(snap_compare: Snap, rig: Rig) -> None:
    """D shows the dose layer: the floor coloured by its dose against the target, the scale above
    the legend."""

    async def show(pilot: Any) -> None:
        await pilot.press("D")

    steps = before(lambda _p: two_robots(rig), lambda _p: map_extras(rig), lambda _p: dose_layer(rig), show)
    assert snap_compare(rig.app, terminal_size=SIZE, run_before=steps)
