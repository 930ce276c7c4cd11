"""Map sharing over real Zenoh peers on loopback: the queryable serves the map, updates patch a copy,
``fleetlink map save`` writes it as map_server files, bad replies are rejected."""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from fleetlink.agent.mapping.keeper import MapKeeper, MapPublication, Turn
from fleetlink.agent.mapping.mapper import OnboardMapper
from fleetlink.agent.mapping.share import MapShare, fetch_map
from fleetlink.cli.main import main
from fleetlink.field.mapserver import read_map
from fleetlink.field.raycast import Raycaster
from fleetlink.links.zenoh import ZenohEndpoint
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import SimClock
from fleetlink.shared.map_codec import SharedMap, decode_cells, patch_fields
from fleetlink.shared.messages import MapSnapshot, MapUpdate

ROOM = np.array([[0.0, 0.0, 6.0, 0.0], [6.0, 0.0, 6.0, 4.0], [6.0, 4.0, 0.0, 4.0], [0.0, 4.0, 0.0, 0.0]])
ANGLES = np.linspace(0.0, 2 * math.pi, 360, endpoint=False)


def _scan(pose: tuple[float, float, float]) -> np.ndarray:
    r = Raycaster(ROOM).cast_fan(pose[0], pose[1], pose[2], 2 * math.pi / 360, 360, 12.0)
    return np.where(np.isfinite(r), r, 0.0)


def _until(cond, timeout: float = 5.0):  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = cond()
        if value:
            return value
        time.sleep(0.05)
    return cond()


def test_queryable_serves_the_map_and_updates_patch_a_copy(zenoh_peers, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    peers = zenoh_peers(2)
    agent, other = (ZenohEndpoint(session=s) for s in peers)
    agent.start()
    other.start()
    clock = SimClock()
    mapper = OnboardMapper()
    mapper.add_scan(0.0, _scan((1.0, 1.0, 0.0)), ANGLES, (1.0, 1.0, 0.0))
    updates: list[bytes] = []
    lock = threading.Lock()

    def on_update(_key: str, payload: bytes) -> None:
        with lock:
            updates.append(payload)

    other.subscribe(keys.key("r1", MapUpdate.TOPIC), on_update)
    try:
        with MapShare(agent, "r1", clock) as share:
            share.publish(MapPublication.of(mapper))
            snap = _until(lambda: fetch_map(other, "r1", timeout=1.0))
            assert isinstance(snap, MapSnapshot) and snap.version == mapper.version
            copy = SharedMap.from_snapshot(snap)
            cells, _, origin = mapper.occupancy()
            assert np.array_equal(copy.cells, cells) and copy.origin == pytest.approx(origin)

            # More of the room seen: an update patches the copy to the new version.
            mapper.add_scan(0.1, _scan((4.0, 3.0, 1.0)), ANGLES, (4.0, 3.0, 1.0))
            clock.advance(1.0)
            share.publish(MapPublication.of(mapper))
            raw = _until(lambda: list(updates))
            upd = wire.decode_key(keys.key("r1", MapUpdate.TOPIC), raw[-1])
            assert isinstance(upd, MapUpdate) and upd.base_version == copy.version
            assert copy.apply(upd) and copy.version == mapper.version
            assert np.array_equal(copy.cells, mapper.occupancy()[0])
            assert not copy.apply(upd)  # a stale update is refused: fetch a snapshot instead

            # The CLI fetches the same map through its own session and writes map_server files.
            out = tmp_path / "saved"
            args = ["map", "save", "--robot", "r1", "--out", str(out), "--connect", peers.endpoints[0]]
            assert main(args) == 0
            saved = read_map(out / "map.yaml")
            cells = mapper.occupancy()[0]
            assert saved.grid.shape == cells.shape
            assert ((saved.grid == 100) == (cells >= 65)).all()
            unknown = (cells < 0) | ((cells > 25) & (cells < 65))
            bad = (saved.grid == -1) != unknown
            assert not bad.any(), (cells[bad][:10], saved.grid[bad][:10])
            assert share.queries >= 2

            # Its agent restarted: a new map, its versions from its first scan again. No patch goes
            # out against the old map; the snapshot served is the new map's, named by its ``began``.
            sent = len(updates)
            fresh = OnboardMapper()
            fresh.add_scan(5.0, _scan((2.0, 2.0, 0.0)), ANGLES, (2.0, 2.0, 0.0))
            clock.advance(1.0)
            share.publish(dataclasses.replace(MapPublication.of(fresh), began=5.0))
            snap2 = _until(lambda: (s := fetch_map(other, "r1", timeout=1.0)) is not None and s.began == 5.0 and s)
            assert isinstance(snap2, MapSnapshot) and snap2.version == fresh.version < copy.version
            assert len(updates) == sent
            fresh.add_scan(5.1, _scan((3.0, 2.0, 0.5)), ANGLES, (3.0, 2.0, 0.5))
            clock.advance(1.0)
            share.publish(dataclasses.replace(MapPublication.of(fresh), began=5.0))
            raw = _until(lambda: updates[sent:])
            upd2 = wire.decode_key(keys.key("r1", MapUpdate.TOPIC), raw[-1])
            assert isinstance(upd2, MapUpdate) and upd2.began == 5.0
            assert not copy.apply(upd2)  # the old map's copy: not followed, whatever the versions say
            assert SharedMap.from_snapshot(snap2).apply(upd2)
    finally:
        other.close()
        agent.close()


def test_no_map_yet_and_bad_replies_give_none(zenoh_peers) -> None:  # type: ignore[no-untyped-def]
    agent, other = (ZenohEndpoint(session=s) for s in zenoh_peers(2))
    agent.start()
    other.start()
    try:
        with MapShare(agent, "r2", SimClock()) as share:
            time.sleep(0.2)
            assert fetch_map(other, "r2", timeout=1.0) is None  # no map yet: no answer
            assert share.queries == 1
        assert fetch_map(other, "r2", timeout=0.5) is None and share.queries == 1  # stopped: silent
        # A peer answering with garbage on the map key is rejected, not crashed on.
        agent.serve(keys.key("r3", "map"), lambda asked: [(keys.key("r3", "map"), b"\xc1junk")])
        time.sleep(0.2)
        assert fetch_map(other, "r3", timeout=1.0) is None
    finally:
        other.close()
        agent.close()


def test_codec_rejects_bad_cells() -> None:
    import zlib

    with pytest.raises(ValueError):
        decode_cells(b"not zlib", 2, 2)
    with pytest.raises(ValueError):
        decode_cells(zlib.compress(bytes(5)), 2, 2)  # one cell too many
    with pytest.raises(ValueError):
        decode_cells(zlib.compress(bytes([120, 0, 0, 0])), 2, 2)  # 120 is not a cell value


def _keeper_publications() -> list[MapPublication]:
    """A keeper with loop closure driven up and down the room: its publications, submaps and all."""
    keeper = MapKeeper(share_period=0.5)
    pubs = []
    t = 0.0
    for leg in range(4):
        for k in range(26):
            x = 0.8 + 0.17 * k if leg % 2 == 0 else 5.2 - 0.17 * k
            pose = (x, 1.5 + 0.3 * leg, 0.0 if leg % 2 == 0 else math.pi)
            up = keeper.add(Turn(t, _scan(pose), ANGLES, pose, placed=True, driving=True, now=t))
            if up.publication is not None:
                pubs.append(up.publication)
            t += 0.5
    return pubs


def test_the_map_s_submaps_are_listed_and_fetched_one_by_one_or_all(zenoh_peers) -> None:  # type: ignore[no-untyped-def]
    from fleetlink.agent.mapping.share import fetch_submap, fetch_submaps, submap_of
    from fleetlink.field.plans import nearest_segment_distances

    pubs = _keeper_publications()
    last = pubs[-1]
    assert len(last.submap_poses) >= 3
    # Each submap drawn when it changed: a finished one once, however many publications follow.
    drawn = [sm.index for p in pubs for sm in p.submaps]
    finished = [i for i, v, _ in last.submap_poses if v == 10]
    assert finished and all(drawn.count(i) <= 10 for i in finished)
    assert {sm.index for p in pubs for sm in p.submaps} == {i for i, _, _ in last.submap_poses}

    peers = zenoh_peers(2)
    agent, other = (ZenohEndpoint(session=s) for s in peers)
    agent.start()
    other.start()
    share = MapShare(agent, "r1", SimClock())
    share.start()
    try:
        for p in pubs:
            share.publish(p)
        listing = _until(lambda: fetch_submaps(other, "r1", timeout=2.0))
        assert listing is not None and listing.site_frame and listing.began == last.began
        assert [(e.index, e.version) for e in listing.submaps] == [(i, v) for i, v, _ in last.submap_poses]
        one = fetch_submap(other, "r1", 1, timeout=2.0)
        assert [m.index for m in one] == [1]
        every = fetch_submap(other, "r1", "*", timeout=2.0)
        assert sorted(m.index for m in every) == [e.index for e in listing.submaps]
        assert fetch_submap(other, "r1", 999, timeout=2.0) == []
        assert other.query("fleetlink/v1/r1/map/submap/01", 2.0) == []  # not an index as keys write it
        assert [k for k, _ in other.query("fleetlink/v1/*/map/submap/1", 2.0)] == ["fleetlink/v1/r1/map/submap/1"]
        # A submap's walls, placed where the list puts its frame, lie on the room's walls.
        for msg in every:
            e = listing.submaps[msg.index]
            sm = submap_of(msg, (e.x, e.y, e.theta))
            rows, cols = np.nonzero(sm.cells >= 65)
            assert len(rows) > 50
            px = sm.origin[0] + (cols + 0.5) * sm.resolution
            py = sm.origin[1] + (rows + 0.5) * sm.resolution
            c, s = math.cos(sm.pose[2]), math.sin(sm.pose[2])
            site = np.column_stack((sm.pose[0] + c * px - s * py, sm.pose[1] + s * px + c * py))
            assert np.median(nearest_segment_distances(site, ROOM)) < 0.05
    finally:
        share.stop()
    assert fetch_submaps(other, "r1", timeout=0.5) is None  # stopped: nothing answers


def test_a_submap_s_key_names_its_index() -> None:
    from fleetlink.shared.map_codec import snapshot_fields
    from fleetlink.shared.messages import MapSubmap

    counter = wire.HeaderCounter(SimClock(), robot="r1", sender="agent-r1")
    fields = snapshot_fields(np.zeros((2, 3), dtype=np.int8), 0.05, (0.0, 0.0), 3, began=1.0)
    msg = counter.make(MapSubmap, index=7, x=0.0, y=0.0, theta=0.0, **fields)
    assert wire.key_of(msg) == "fleetlink/v1/r1/map/submap/7"
    data = wire.encode(msg)
    assert wire.decode_key("fleetlink/v1/r1/map/submap/7", data) == msg
    for bad, reason in (
        ("fleetlink/v1/r1/map/submap/8", "index"),
        ("fleetlink/v1/r1/map/submap", "index"),
        ("fleetlink/v1/r1/map/submap/07", "key"),
    ):
        with pytest.raises(wire.WireError) as err:
            wire.decode_key(bad, data)
        assert err.value.field in (reason, "key", "topic"), (bad, err.value)
    assert keys.topic_of("fleetlink/v1/r1/map/submap/7") == "map/submap"
    with pytest.raises(ValueError):
        keys.indexed_key("r1", "map", 1)


def test_a_submap_reply_about_another_robot_is_left_out() -> None:
    """A link that answers a query about r2 with r1's submap (a valid message on r1's own key) gives
    only r2's: the other is left out with its reason."""
    from fleetlink.agent.mapping.share import fetch_submap
    from fleetlink.shared.map_codec import snapshot_fields
    from fleetlink.shared.messages import MapSubmap

    def submap(robot: str, index: int) -> tuple[str, bytes]:
        counter = wire.HeaderCounter(SimClock(), robot=robot, sender=f"agent-{robot}")
        fields = snapshot_fields(np.zeros((2, 3), dtype=np.int8), 0.05, (0.0, 0.0), 3, began=1.0)
        msg = counter.make(MapSubmap, index=index, x=0.0, y=0.0, theta=0.0, **fields)
        return wire.key_of(msg), wire.encode(msg)

    class Answering:
        def query(self, key_expr: str, timeout: float) -> list[tuple[str, bytes]]:
            return [submap("r1", 0), submap("r2", 1)]

    rejected: list[str] = []
    got = fetch_submap(Answering(), "r2", "*", rejected=rejected)  # type: ignore[arg-type]
    assert [(m.header.robot, m.index) for m in got] == [("r2", 1)]
    assert len(rejected) == 1 and "'r1'" in rejected[0]


def test_an_update_of_another_map_does_not_follow_a_copy_whose_versions_it_matches() -> None:
    """A restarted agent's new map counts its versions again: its update from version 3 to 4 must not
    be pasted onto a copy of the old map that happens to stand at version 3 (``began`` tells them apart)."""
    cells = np.zeros((4, 4), dtype=np.int8)
    copy = SharedMap(cells.copy(), 0.05, (0.0, 0.0), 3, began=1.0)
    changed = cells.copy()
    changed[1, 1] = 100
    other = patch_fields(changed, 0.05, (0.0, 0.0), (1, 1, 2, 2), 4, 3, began=2.0)
    same = patch_fields(changed, 0.05, (0.0, 0.0), (1, 1, 2, 2), 4, 3, began=1.0)
    assert other is not None and same is not None
    c = wire.HeaderCounter(SimClock(), robot="r1", sender="agent-r1")
    assert not copy.apply(c.make(MapUpdate, **other)) and copy.version == 3 and copy.cells[1, 1] == 0
    assert copy.apply(c.make(MapUpdate, **same)) and copy.version == 4 and copy.cells[1, 1] == 100
