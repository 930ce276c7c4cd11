"""Map sharing over real Zenoh peers on loopback: the queryable serves the map, updates patch a copy,
``fleetlink map save`` writes it as map_server files, bad replies are rejected."""

from __future__ import annotations

import math
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from fleetlink.agent.mapping.keeper import MapPublication
from fleetlink.agent.mapping.mapper import OnboardMapper
from fleetlink.agent.mapping.share import MapShare, fetch_map
from fleetlink.cli.main import main
from fleetlink.field.mapserver import read_map
from fleetlink.field.raycast import Raycaster
from fleetlink.links.zenoh import ZenohEndpoint
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import SimClock
from fleetlink.shared.map_codec import SharedMap, decode_cells
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
