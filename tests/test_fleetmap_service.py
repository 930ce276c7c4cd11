"""The fleet map end to end over real Zenoh peers on loopback: two robots share their maps (the
agent's MapShare), a console follows them and builds the fleet map (the console's own wiring,
cli/console.py ``fleet_map_service``), draws it instead of the robots' maps, serves it, and
``fleetlink map save --fleet`` writes it as map_server files."""

from __future__ import annotations

import math
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fleetlink.agent.mapping.fleetmap import RobotMap
from fleetlink.agent.mapping.keeper import MapPublication
from fleetlink.agent.mapping.share import MapShare, fetch_submap, fetch_submaps
from fleetlink.cli.console import fleet_map_service
from fleetlink.cli.main import main
from fleetlink.field.mapserver import read_map
from fleetlink.links.inprocess import InProcessBus
from fleetlink.links.mqtt import MqttEndpoint
from fleetlink.links.zenoh import ZenohEndpoint
from fleetlink.operator.console import attach
from fleetlink.operator.fleet import FleetModel
from fleetlink.operator.links import OperatorLink, mqtt_settings_for
from fleetlink.operator.maprender import WALL
from fleetlink.operator.maps import MapFetcher, MapFollower, to_grid
from fleetlink.operator.mapview import MapView
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import SimClock, SystemClock
from fleetlink.shared.map_codec import SharedMap, decode_cells
from fleetlink.shared.messages import FleetFrames, LinkName, MapSubmaps, Pose
from fleetlink.site.fleetmap import FleetMapService
from tests.harness import wait_until
from tests.harness.console_rig import Rig
from tests.test_console import run_async
from tests.test_fleetmap import (
    BENT,
    FURNISHED,
    RES,
    close_to,
    distance_to_walls,
    own_frame,
    robot_map,
    undo,
    walls_of,
    with_submaps,
)


def publish_pose(link: ZenohEndpoint, counter: wire.HeaderCounter, x: float, y: float) -> None:
    msg = counter.make(
        Pose, x=x, y=y, theta=0.0, sd_x_m=0.1, sd_y_m=0.1, sd_theta_rad=0.1, odom_x=x, odom_y=y,
        odom_theta=0.0, vx=0.0, omega=0.0, uwbStale=False,
    )  # fmt: skip
    link.publish(wire.key_of(msg), wire.encode(msg))


@dataclass
class Following:
    """A console following robots' maps over real links (its own wiring, ``fleet_map_service``),
    and the robots' side of the link with a ``MapShare`` each."""

    link: OperatorLink
    robots_side: ZenohEndpoint
    fleet: FleetModel
    lock: threading.Lock
    service: FleetMapService
    shares: dict[str, MapShare]
    counters: dict[str, wire.HeaderCounter]

    def publish(self, robot: str, m: RobotMap) -> None:
        self.shares[robot].publish(
            MapPublication(m.version, m.cells, m.resolution, m.origin, None, site_frame=m.site_frame)
        )

    def heard(self, x: float, y: float) -> None:
        """Every robot's pose heard: the console fetches their maps."""
        for r in self.shares:
            publish_pose(self.robots_side, self.counters[r], x, y)


@contextmanager
def following(peers: Any, mosquitto: Any, robots: tuple[str, ...]) -> Iterator[Following]:
    clock = SystemClock()
    robots_side = ZenohEndpoint(session=peers[1])
    robots_side.start()
    link = OperatorLink(
        clock,
        "op-fleet",
        ZenohEndpoint(session=peers[0]),
        MqttEndpoint(mqtt_settings_for(f"mqtt://127.0.0.1:{mosquitto.port}"), client_id="op-fleet"),
    ).start()
    fleet = FleetModel("op-fleet")
    lock = threading.Lock()
    follower = MapFollower(fleet, retry_s=0.5)
    attach(link, fleet, lock, follower)
    service = fleet_map_service(link, follower, lock, clock, "op-fleet")
    service.period_s = 0.2
    fetcher = MapFetcher(follower, lambda r: link.fetch_map(r, timeout=2.0), clock, lock, period_s=0.1,
                         after_poll=service.step).start()  # fmt: skip
    shares = {r: MapShare(robots_side, r, clock) for r in robots}
    counters = {r: wire.HeaderCounter(clock, robot=r, sender=f"agent-{r}") for r in robots}
    try:
        for share in shares.values():
            share.start()
        yield Following(link, robots_side, fleet, lock, service, shares, counters)
    finally:
        fetcher.stop()
        for share in shares.values():
            share.stop()
        if service.share is not None:
            service.share.stop()
        robots_side.close()
        link.close()


def test_two_robots_maps_become_one_fleet_map_that_the_cli_saves(
    zenoh_peers: Any, mosquitto: Any, tmp_path: Path
) -> None:
    peers = zenoh_peers(2)
    off = (0.0, 0.2, math.radians(1.0))  # r2's map 0.2 m and a degree off r1's
    maps = {"r1": robot_map((0.0, 0.0, 6.5, 6.0)), "r2": robot_map((2.5, 0.0, 9.0, 6.0), off)}
    with following(peers, mosquitto, tuple(maps)) as f:
        for r, m in maps.items():
            f.publish(r, m)

        def built() -> bool:
            f.heard(3.0, 1.0)
            with f.lock:
                return (
                    keys.FLEET_MAP in f.fleet.grids
                    and f.service.result is not None
                    and bool(f.service.result.registrations)
                )

        wait_until(built, timeout=30, message="the fleet map built from both robots' maps")
        assert f.service.share is not None
        result = f.service.result
        assert result is not None
        # The fleet map's walls are single: its own walls lie on the floor's, once a's placement is undone.
        merged = walls_of(result.cells, result.origin, result.resolution)
        d = distance_to_walls(undo(result.corrections["r1"], merged))
        assert np.median(d) <= 0.05 and np.mean(d > 0.1) < 0.05

        out = tmp_path / "fleet"
        args = ["map", "save", "--fleet", "--out", str(out), "--connect", peers.endpoints[0]]
        wait_until(lambda: main(args) == 0, timeout=20, message="fleetlink map save --fleet")
        saved = read_map(out / "map.yaml")
        assert saved.grid.shape == result.cells.shape
        assert ((saved.grid == 100) == (result.cells == 100)).all()
        assert saved.origin[:2] == tuple(round(v, 6) for v in result.origin) or np.allclose(
            saved.origin[:2], result.origin
        )


def test_a_map_shared_whole_in_its_own_frame_is_found_not_taken_for_the_site_s(
    zenoh_peers: Any, mosquitto: Any
) -> None:
    """A robot without UWB and without loop closure shares its map whole, no submaps: its (empty)
    submap list still says the map is in its own frame, and the console's fleet map finds it there."""
    peers = zenoh_peers(2)
    start = (7.5, 1.0, math.radians(137.0))  # where r2 began, in the site frame
    maps = {"r1": robot_map((0.0, 0.0, 7.5, 6.0), floor=FURNISHED), "r2": own_frame((1.5, 0.0, 9.0, 6.0), start)}
    with following(peers, mosquitto, tuple(maps)) as f:
        heard: list[FleetFrames] = []
        f.robots_side.subscribe(
            keys.key(keys.FLEET_MAP, FleetFrames.TOPIC),
            lambda key, payload: heard.append(wire.decode_key(key, payload)),  # type: ignore[arg-type]
        )
        for r, m in maps.items():
            f.publish(r, m)
        # Asked again until it answers: a query sent before the robot's queryable has reached the
        # console's peer gets no reply at all, however long it waits (a loaded CI host, twice).
        answers: list[MapSubmaps] = []

        def listed() -> bool:
            listing = fetch_submaps(f.link.query_link(), "r2", timeout=2.0)
            answers.extend([listing] if listing is not None else [])
            return bool(answers)

        wait_until(listed, timeout=30, message="r2's submap list")
        assert answers[0].submaps == () and not answers[0].site_frame

        def found() -> bool:
            f.heard(3.0, 1.0)
            with f.lock:
                return "r2" in f.fleet.frames

        wait_until(found, timeout=30, message="r2's own frame found on the fleet map")
        with f.lock:
            assert close_to(f.fleet.frames["r2"], start), f.fleet.frames["r2"]
            assert "r1" not in f.fleet.frames  # in the site frame: drawn as it reports
        # ... and says so on the link, for Foxglove and the recorder (FleetFrames).
        wait_until(lambda: any(m.frames for m in heard), timeout=10, message="FleetFrames with r2's frame")
        (sent,) = next(m for m in heard if m.frames).frames
        assert sent.robot == "r2" and close_to((sent.x, sent.y, sent.theta), start)


def wall_runs(view: MapView, x: float, y0: float, y1: float) -> int:
    """How many separate walls the map widget draws in the pixel column at ``x`` between y0 and y1."""
    assert view.frame is not None
    col, top = view.geometry.to_pixel(x, y1)
    _, bottom = view.geometry.to_pixel(x, y0)
    runs, inside = 0, False
    for prow in range(top, bottom + 1):
        wall = view.frame.pixel(col, prow) == WALL
        runs += wall and not inside
        inside = wall
    return runs


@run_async
async def test_the_console_draws_the_fleet_map_alone(tmp_path: Path) -> None:
    rig = Rig(tmp_path)
    follower = MapFollower(rig.fleet)
    service = FleetMapService(follower, rig.lock, rig.clock, period_s=0.0)
    a = robot_map((0.0, 0.0, 6.5, 6.0))
    b = robot_map((2.5, 0.0, 9.0, 6.0), (0.0, 0.2, 0.0))  # r2's map 0.2 m up: the wall y = 6 at 6.2
    rig.start()
    try:
        with rig.lock:
            for r, m in (("r1", a), ("r2", b)):
                follower.maps[r] = SharedMap(m.cells, m.resolution, m.origin, m.version)
                rig.fleet.set_grid(r, to_grid(follower.maps[r]))
        async with rig.app.run_test(size=(160, 48)) as pilot:
            await pilot.pause(0.3)
            view = rig.app.query_one(MapView)
            view.geometry.center_x, view.geometry.center_y, view.geometry.scale = 5.0, 5.5, 0.05
            view.update_view()
            await pilot.pause(0.2)
            assert wall_runs(view, 5.0, 5.6, 6.6) == 2  # the robots' maps overlaid: the wall twice
            assert service.step()
            view.update_view()
            await pilot.pause(0.2)
            assert wall_runs(view, 5.0, 5.6, 6.6) == 1  # the fleet map: once
    finally:
        rig.close()


def test_the_fleet_map_service_process_builds_and_serves_the_fleet_map(zenoh_peers: Any) -> None:
    """``fleetlink map fleet`` as its own process (a site with a router runs it so): it hears the
    robots' map updates, fetches their maps, and answers ``fleetlink/v1/fleet/map``."""
    import subprocess
    import sys

    from fleetlink.agent.mapping.share import fetch_map

    clock = SystemClock()
    peers = zenoh_peers(1)
    robots_side = ZenohEndpoint(session=peers[0])
    robots_side.start()
    maps = {"r1": robot_map((0.0, 0.0, 6.5, 6.0)), "r2": robot_map((2.5, 0.0, 9.0, 6.0), (0.05, 0.15, 0.01))}
    shares = {r: MapShare(robots_side, r, clock) for r in maps}
    service = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "fleetlink.cli.main",
            "map",
            "fleet",
            "--connect",
            peers.endpoints[0],
            "--period",
            "0.5",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        for r in shares.values():
            r.start()
        version = 1

        def served() -> bool:
            nonlocal version
            version += 1  # each robot's map changes a little, as it maps: an update the service hears
            for r, m in maps.items():
                cells = m.cells.copy()
                shares[r].publish(MapPublication(version, cells, m.resolution, m.origin, (0, 0, 1, 1), site_frame=True))
            snap = fetch_map(robots_side, keys.FLEET_MAP, timeout=1.0)
            return snap is not None and snap.width > 0

        wait_until(served, timeout=40, message="the fleet map served by `fleetlink map fleet`")
        snap = fetch_map(robots_side, keys.FLEET_MAP, timeout=1.0)
        assert snap is not None
        cells = decode_cells(snap.cells, snap.width, snap.height)
        merged = walls_of(cells, (snap.origin_x, snap.origin_y), snap.resolution)
        assert len(merged) > 500
    finally:
        service.terminate()
        try:
            out, err = service.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            service.kill()
            out, err = service.communicate()
        for share in shares.values():
            share.stop()
        robots_side.close()
    assert service.returncode == 0, err[-2000:]
    assert "serving fleetlink/v1/fleet/map" in out


@dataclass
class SubmapRig:
    """Two Zenoh endpoints (robots' side, console's side) and a console's fleet map service that
    already follows r1's whole map and r2's map bent along the way (``BENT``)."""

    robots_side: ZenohEndpoint
    console_side: ZenohEndpoint
    lock: threading.Lock
    follower: MapFollower
    service: FleetMapService
    r2: RobotMap

    def close(self) -> None:
        self.robots_side.close()
        self.console_side.close()


def submap_rig(zenoh_peers: Any) -> SubmapRig:
    peers = zenoh_peers(2)
    robots_side, console_side = ZenohEndpoint(session=peers[1]), ZenohEndpoint(session=peers[0])
    robots_side.start()
    console_side.start()
    lock = threading.Lock()
    follower = MapFollower(FleetModel("op-fleet"), retry_s=0.5)
    service = FleetMapService(follower, lock, SystemClock(), period_s=0.0, query=console_side)
    r1, r2 = robot_map((0.0, 0.0, 9.0, 6.0)), with_submaps(BENT)
    for r, m in (("r1", r1), ("r2", r2)):
        follower.maps[r] = SharedMap(m.cells.copy(), m.resolution, m.origin, m.version)
    return SubmapRig(robots_side, console_side, lock, follower, service, r2)


def wait_served(rig: SubmapRig, robot: str, *, cells: bool = True) -> None:
    """Until the console's side hears ``robot``'s submap queryables: a query sent before a
    declaration has reached the other peer goes unanswered (on a loaded machine a build began at once
    found no list and merged the map whole). ``cells``: probe the submap cells (declared after the
    list, in order on the one link); else the list (declared last by the caller)."""
    if cells:
        wait_until(lambda: fetch_submap(rig.console_side, robot, timeout=1.0), timeout=10, message=f"{robot}'s submaps")
    else:
        wait_until(
            lambda: fetch_submaps(rig.console_side, robot, timeout=1.0) is not None,
            timeout=10,
            message=f"{robot}'s submap list",
        )


def test_a_robot_s_bent_map_is_merged_from_its_submaps_fetched_over_the_link(zenoh_peers: Any) -> None:
    """r2 shares a map bent along the way (its submaps each further off) with its submap list: the
    console's service fetches the submaps, straightens them one by one against r1's map, and fetches
    none again while only their poses change."""
    rig = submap_rig(zenoh_peers)
    service, follower, lock, r2 = rig.service, rig.follower, rig.lock, rig.r2
    shares = {"r2": MapShare(rig.robots_side, "r2", SystemClock())}
    poses = tuple((s.index, s.version, s.pose) for s in BENT)
    try:
        shares["r2"].start()
        shares["r2"].publish(
            MapPublication(r2.version, r2.cells, RES, r2.origin, None, True, 5.0, BENT, submap_poses=poses)
        )
        wait_served(rig, "r2")
        wait_until(service.step, timeout=10, message="a fleet map built")
        result = service.result
        assert result is not None and service.submaps_fetched == 3
        assert {r.b_piece for r in result.registrations if r.b == "r2"} == {0, 1, 2}
        d = distance_to_walls(undo(result.corrections["r1"], walls_of(result.cells, result.origin, result.resolution)))
        assert np.median(d) <= 0.03 and np.mean(d > 0.1) < 0.01
        # Only r1's map changes: r2's submaps, unchanged with its map, are not asked about again.
        asked = shares["r2"].list_queries
        with lock:
            r1 = follower.maps["r1"]
            follower.maps["r1"] = SharedMap(r1.cells.copy(), r1.resolution, r1.origin, r1.version + 1)
        assert service.step() and shares["r2"].list_queries == asked
        # r2's graph moves its submaps (a closure): the list says so; the cells are not fetched again.
        moved = tuple((i, v, (p[0] + 0.01, p[1], p[2])) for i, v, p in poses)
        shares["r2"].publish(MapPublication(r2.version + 1, r2.cells, RES, r2.origin, None, True, 5.0, (), moved))
        with lock:
            follower.maps["r2"] = SharedMap(r2.cells.copy(), RES, r2.origin, r2.version + 1)
        assert service.step()
        assert service.submaps_fetched == 3
        assert service.core.maps["r2"].pieces[0].placed == moved[0][2]
        # r2's map begun again (its agent restarted): every submap is fetched anew.
        shares["r2"].publish(MapPublication(r2.version + 2, r2.cells, RES, r2.origin, None, True, 9.0, BENT, poses))
        with lock:
            follower.maps["r2"] = SharedMap(r2.cells.copy(), RES, r2.origin, r2.version + 2)
        assert service.step()
        assert service.submaps_fetched == 6
    finally:
        for share in shares.values():
            share.stop()
        rig.close()


def test_bad_submap_replies_leave_the_map_whole_and_are_counted_and_logged_once(zenoh_peers: Any, caplog: Any) -> None:
    """r2 lists three submaps but answers with cells that do not inflate, and one of another map:
    its map is merged whole, the replies are counted, logged once, not asked for again; the build
    goes on for everyone."""
    import zlib

    from fleetlink.shared.map_codec import snapshot_fields
    from fleetlink.shared.messages import MapSubmap, MapSubmaps, SubmapEntry

    rig = submap_rig(zenoh_peers)
    service, follower, lock, r2 = rig.service, rig.follower, rig.lock, rig.r2
    counter = wire.HeaderCounter(SystemClock(), robot="r2", sender="agent-r2")
    asked: list[str] = []

    def listing(_key: str) -> list[tuple[str, bytes]]:
        entries = tuple(
            SubmapEntry(index=s.index, version=s.version, x=s.pose[0], y=s.pose[1], theta=s.pose[2]) for s in BENT
        )
        return [
            (
                keys.key("r2", MapSubmaps.TOPIC),
                wire.encode(counter.make(MapSubmaps, began=5.0, site_frame=True, submaps=entries)),
            )
        ]

    def submap(key: str) -> list[tuple[str, bytes]]:
        asked.append(key)
        i = int(key.rpartition("/")[2])
        sm = BENT[i]
        began = 6.0 if i == 2 else 5.0  # another map's submap
        fields = dict(snapshot_fields(sm.cells, RES, sm.origin, sm.version, began))
        if i == 1:
            fields["cells"] = zlib.compress(b"\x00" * 7)  # not width x height cells
        msg = counter.make(MapSubmap, index=i, x=sm.pose[0], y=sm.pose[1], theta=sm.pose[2], **fields)
        return [(key, wire.encode(msg))]

    rig.robots_side.serve(keys.indexed_key("r2", "map/submap", "*"), submap)
    rig.robots_side.serve(keys.key("r2", MapSubmaps.TOPIC), listing)
    try:
        wait_served(rig, "r2", cells=False)
        with caplog.at_level("WARNING", logger="fleetlink.site.fleetmap"):
            assert service.step()
            result = service.result
            assert result is not None and set(result.piece_corrections["r2"]) == {-1}  # merged whole
            assert service.submaps_fetched == 1 and service.submaps_refused == 2
            with lock:
                follower.maps["r2"] = SharedMap(r2.cells.copy(), RES, r2.origin, r2.version + 1)
            assert service.step()  # the build goes on; submap 1 (cells bad) is not asked for again
        assert sum(k.endswith("/1") for k in asked) == 1 and sum(k.endswith("/2") for k in asked) == 2
        assert service.submaps_refused == 3
        assert len([r for r in caplog.records if "left out" in r.getMessage()]) == 1
    finally:
        rig.close()


def test_a_robot_standing_still_has_its_submaps_fetched_over_several_builds(zenoh_peers: Any, monkeypatch: Any) -> None:
    import fleetlink.site.fleetmap as service_module

    monkeypatch.setattr(service_module, "FETCH_PER_BUILD", 1)
    rig = submap_rig(zenoh_peers)
    service, r2 = rig.service, rig.r2
    share = MapShare(rig.robots_side, "r2", SystemClock())
    try:
        share.start()
        poses = tuple((s.index, s.version, s.pose) for s in BENT)
        share.publish(MapPublication(r2.version, r2.cells, RES, r2.origin, None, True, 5.0, BENT, poses))
        wait_served(rig, "r2")
        pieces = []
        for _ in range(4):  # the maps do not change: the builds go on while submaps are missing
            built = service.step()
            pieces.append(
                sorted(service.core.maps["r2"].pieces[i].index for i in range(len(service.core.maps["r2"].pieces)))
                if built
                else None
            )
        assert pieces == [[-1], [-1], [0, 1, 2], None]
        assert service.submaps_fetched == 3
    finally:
        share.stop()
        rig.close()


def test_a_robot_whose_submap_list_goes_unanswered_keeps_the_frame_it_last_said() -> None:
    """A lost reply is not news about the robot's frame: its map stays in the frame its list last said
    (its own, here), and only a robot never heard from is taken to be in the site frame."""

    class Answers:
        def __init__(self) -> None:
            self.replies: list[tuple[str, bytes]] = []

        def query(self, key_expr: str, timeout: float) -> list[tuple[str, bytes]]:
            return list(self.replies)

    clock = SimClock()
    link = Answers()
    listing = wire.HeaderCounter(clock, robot="r2", sender="agent-r2").make(
        MapSubmaps, began=1.0, site_frame=False, submaps=()
    )
    link.replies = [(wire.key_of(listing), wire.encode(listing))]
    service = FleetMapService(MapFollower(FleetModel("op")), threading.Lock(), clock, period_s=0.0, query=link)  # type: ignore[arg-type]
    m = robot_map((0.0, 0.0, 6.5, 6.0))
    assert service._fetch("r2", SharedMap(m.cells, m.resolution, m.origin, 1)) == ((), False)
    link.replies = []  # the next reply lost, the map moved on
    assert service._fetch("r2", SharedMap(m.cells, m.resolution, m.origin, 2)) == ((), False)
    assert service._fetch("r9", SharedMap(m.cells, m.resolution, m.origin, 2)) == ((), True)


def test_the_frames_name_the_map_they_were_found_for_and_a_map_begun_again_goes_out_at_once() -> None:
    """Each ``RobotFrame`` carries the ``began`` of the map it was found for (the robot's submap list
    says it): an agent restarted where it began maps the same walls in the same frame, and its new
    map's frame goes out at the next build, not at the next periodic send, so that peers take its
    poses again (agent/peers.py counts a frame only for poses of its own map)."""
    clock = SimClock(100.0)
    bus = InProcessBus(LinkName.ZENOH, clock_now=clock.now)
    op, robots_side, tap = bus.endpoint("op-fleet"), bus.endpoint("agents"), bus.endpoint("tap")
    for endpoint in (op, robots_side, tap):
        endpoint.start()
    heard: list[FleetFrames] = []
    tap.subscribe(
        keys.key(keys.FLEET_MAP, FleetFrames.TOPIC),
        lambda key, payload: heard.append(wire.decode_key(key, payload)),  # type: ignore[arg-type]
    )
    fleet_share = MapShare(op, keys.FLEET_MAP, clock, sender="op-fleet")
    fleet_share.start()
    follower = MapFollower(FleetModel("op-fleet"))
    service = FleetMapService(follower, threading.Lock(), clock, share=fleet_share, period_s=0.0, query=op)
    start = (7.5, 1.0, math.radians(137.0))  # where r2 began, in the site frame
    maps = {"r1": robot_map((0.0, 0.0, 7.5, 6.0), floor=FURNISHED), "r2": own_frame((1.5, 0.0, 9.0, 6.0), start)}
    shares = {r: MapShare(robots_side, r, clock) for r in maps}

    def share(robot: str, began: float, version: int, fetched: bool = True) -> None:
        """``robot`` shares its map (begun at ``began``); ``fetched``: the console has fetched it."""
        m = maps[robot]
        shares[robot].publish(
            MapPublication(version, m.cells, m.resolution, m.origin, None, site_frame=m.site_frame, began=began)
        )
        if fetched:
            follower.maps[robot] = SharedMap(m.cells, m.resolution, m.origin, version, began)

    def build() -> FleetFrames:
        heard.clear()
        clock.advance(1.0)
        service.step()
        while bus.deliver():
            pass
        (msg,) = heard
        return msg

    try:
        for share_ in shares.values():
            share_.start()
        share("r1", 12.0, 1)
        share("r2", 20.0, 1)
        for _ in range(10):  # the global search is spread over builds
            msg = build()
            if msg.frames:
                break
        (frame,) = msg.frames
        assert frame.robot == "r2" and frame.began == 20.0
        assert close_to((frame.x, frame.y, frame.theta), start)
        assert "r1" not in [f.robot for f in msg.frames]  # in the site frame
        # r2's agent restarts where it began: the same walls, a new map (its versions from 0 again).
        # Until the console has fetched the new map, the copy it holds (the old one) is left out:
        # no frame goes out for r2 that the new map's poses would be placed through.
        share("r2", 61.0, 0, fetched=False)
        m = maps["r2"]
        follower.maps["r2"] = SharedMap(m.cells, m.resolution, m.origin, 2, 20.0)  # the old map's last update
        msg = build()
        assert [f.robot for f in msg.frames] == [], msg.frames
        share("r2", 61.0, 0)
        for _ in range(10):
            msg = build()
            if msg.frames:
                break
        (frame,) = msg.frames
        assert frame.began == 61.0 and close_to((frame.x, frame.y, frame.theta), start)
    finally:
        for share_ in (*shares.values(), fleet_share):
            share_.stop()
        for endpoint in (op, robots_side, tap):
            endpoint.close()
