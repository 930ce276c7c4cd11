"""The console's dose layer on the in-memory rig (tests/harness/console_rig.py): robots' layers from
their queryables (a snapshot on first sight) and their ``dose/updates`` patches (as the real
OperatorLink decodes them), merged off the UI thread into the fleet's layer, drawn on the map with
``D`` (cells at the target, under it, none; a legend), summarised by ``:dose`` and written by
``:dose save DIR``."""

from __future__ import annotations

import asyncio
import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rich.color import Color
from textual.widgets import RichLog

from fleetlink.agent.dose_layer import DoseKeeper, DoseSample
from fleetlink.operator.dose import AT_TARGET, NONE, DoseFetcher, DoseFollower, merge_layers
from fleetlink.operator.maprender import DOSE_PIXELS, PIXEL_COLOURS, UNKNOWN
from fleetlink.operator.maps import MapFollower
from fleetlink.operator.mapview import MapView
from fleetlink.shared import wire
from fleetlink.shared.dose import FloorMask, Lamp
from fleetlink.shared.dose_codec import SharedDose, patch_fields, snapshot_fields
from fleetlink.shared.map_codec import snapshot_fields as map_fields
from fleetlink.shared.messages import DoseSnapshot, DoseUpdate, MapSnapshot
from tests.harness import wait_until
from tests.harness.console_rig import Rig
from tests.test_console import run_async, settle

ROOM = np.full((80, 120), 100, dtype=np.int8)  # 6 m x 4 m at 0.05 m from (0, 0), walls all round
ROOM[1:-1, 1:-1] = 0


def _layer(x: float, y: float, seconds: float) -> DoseKeeper:
    """A robot's dose keeper after standing at (x, y) with the lamp on for ``seconds``."""
    k = DoseKeeper(Lamp(10.0, 0.6), 100.0, 0.1)
    k.set_floor(FloorMask.from_occupancy(ROOM, 0.05, (0.0, 0.0)), 1)
    n = round(seconds * 20)
    for i in range(n + 1):
        k.step(DoseSample(i / 20.0, x, y, i < n, True))
    return k


def _snapshot(rig: Rig, robot: str, k: DoseKeeper) -> DoseSnapshot:
    g = k.grid
    fields = snapshot_fields(
        g.dose,
        g.resolution,
        g.origin,
        k.version,
        target_j_m2=100.0,
        lamp_on_s=g.lamp_seconds,
        unplaced_s=0.0,
        lamp=k.lamp,
    )
    assert fields is not None
    return rig.counter(robot).make(DoseSnapshot, **fields)


def notices(app: Any) -> list[str]:
    return [line.text for line in app.query_one("#notices", RichLog).lines]


@run_async
async def test_dose_layer_drawn_summarised_and_saved(rig: Rig, tmp_path: Path) -> None:
    k1 = _layer(2.0, 2.0, 60.0)  # a minute at (2, 2): the target around it
    k2 = _layer(4.5, 2.0, 20.0)
    served = {"r1": _snapshot(rig, "r1", k1), "r2": _snapshot(rig, "r2", k2)}
    asked: list[str] = []

    def fetch(robot: str) -> DoseSnapshot | None:  # the robots' queryables (OperatorLink.fetch_dose)
        asked.append(robot)
        return served.get(robot)

    doses = rig.app.doses
    assert isinstance(doses, DoseFollower) and rig.app.feed.doses is doses
    maps = MapFollower(rig.fleet)
    rig.app.feed.maps = maps
    with rig.lock:
        assert maps.on_snapshot("r1", rig.counter("r1").make(MapSnapshot, **map_fields(ROOM, 0.05, (0.0, 0.0), 1)))
    fetcher = DoseFetcher(doses, fetch, rig.clock, rig.lock, period_s=0.1, merge_s=0.2).start()
    try:
        async with rig.app.run_test(size=(140, 44)) as pilot:
            rig.voices["r1"] = (2.0, 2.0)
            rig.voices["r2"] = (4.5, 2.0)
            await settle(pilot)
            wait_until(lambda: doses.layer is not None and set(doses.layer.robots) == {"r1", "r2"}, timeout=5)
            assert {"r1", "r2"} <= set(asked)  # a snapshot on first sight
            layer = doses.layer
            assert layer is not None
            both = layer.grid.dose_at(np.array([3.3]), np.array([2.0]))[0, 0]
            one = k1.grid.dose_at(np.array([3.3]), np.array([2.0]))[0, 0]
            two = k2.grid.dose_at(np.array([3.3]), np.array([2.0]))[0, 0]
            assert both == pytest.approx(one + two, rel=1e-6)  # summed in the site frame
            assert layer.lamp_on_s == pytest.approx(80.0)
            # A round is planned for the robot's own lamp, as its layer advertises it.
            assert rig.app.lamp_for(("r1",)) is doses.layers["r1"].lamp == k1.lamp
            assert rig.app.lamp_for(("nobody",)) is rig.app.lamp

            # The layer on the map: hidden until D, then backgrounds and a legend.
            view = rig.app.query_one(MapView)
            await pilot.press("f")
            await settle(pilot)
            assert view.dose is None
            await pilot.press("D")
            await settle(pilot)
            assert view.dose is layer and any("dose layer shown: r1, r2" in n for n in notices(rig.app))
            g = view.geometry
            char, style = view.cell(*g.to_cell(2.0, 2.0))  # r1, selected: its own background
            assert char == "→" and view.pixel_at(2.0, 2.0) == DOSE_PIXELS[-1]  # on dose at the target
            xs, ys = g.pixel_centres()
            checked = 0
            for x, y in ((2.6, 2.0), (3.3, 1.0), (5.7, 0.2), (0.3, 3.7), (4.0, 3.0)):  # a pixel by its dose / target
                col, prow = g.to_pixel(x, y)
                if not g.inside(col, prow // 2):
                    continue
                checked += 1
                ratio = layer.grid.dose_at(xs[col : col + 1], ys[prow : prow + 1])[0, 0] / layer.target_j_m2
                want = DOSE_PIXELS[min(4, int(ratio * 4))]
                assert view.pixel_at(x, y) == want, (x, y, ratio)
                assert view.frame is not None
                if view.frame.glyph(col, prow // 2) is None:  # not under a robot or the legend
                    char, style = view.cell(col, prow // 2)
                    assert Color.parse(PIXEL_COLOURS[want]) in (style.color, style.bgcolor)
            assert checked >= 3
            # The far corner, behind r2's weaker dose: under the target.
            assert view.pixel_at(5.7, 0.2) in DOSE_PIXELS[:-1]
            assert view.pixel_at(-3.0, 2.0) in (UNKNOWN, None)  # no map, no dose (or off the view)
            bottom = [view.render_line(g.height - k).text for k in (1, 2, 3)]
            scale = next(line for line in bottom if "dose of" in line)  # the dose scale above the legend
            assert "dose of 100 J/m²" in scale and "<25%" in scale and "at/over" in scale and "none" in scale
            assert layer.classes(np.array([2.0, -3.0]), np.array([2.0]))[0].tolist() == [AT_TARGET, NONE]

            # A patch on dose/updates (the real OperatorLink decodes it): applied, merged, redrawn.
            before = doses.version
            pubs = []
            for i in range(20 * 5):
                p = k1.step(DoseSample(60.05 + i / 20.0, 2.0, 2.0, True, True))
                if p is not None:
                    pubs.append(p)
            pub = pubs[-1]
            base = served["r1"].version
            assert pub.changed is not None
            f = patch_fields(
                pub.dose, pub.resolution, pub.origin, pub.changed, pub.version, base,
                target_j_m2=100.0, lamp_on_s=pub.lamp_on_s, unplaced_s=0.0,
            )  # fmt: skip
            assert f is not None
            rig.zenoh.inject(rig.counter("r1").make(DoseUpdate, **f))
            await settle(pilot)
            assert doses.version == before + 1  # applied to r1's copy at once
            wait_until(lambda: doses.layer is not None and doses.layer.version == doses.version, timeout=5)
            await settle(pilot, 0.6)  # the next clock tick draws it
            assert view.dose is doses.layer and view.dose.lamp_on_s == pytest.approx(pub.lamp_on_s + 20.0)
            assert view.dose.grid.dose_at(np.array([2.0]), np.array([2.0]))[0, 0] > both

            # :dose summarises on a thread; the notices say how much floor reached the target and where not.
            rig.app.run_command("dose")
            # One notice per line, each posted from the worker: wait for the last line that is always there.
            await _until(pilot, lambda: any("lowest dose on the floor" in n for n in notices(rig.app)))
            said = notices(rig.app)
            assert any("at or above target" in n for n in said)
            assert any("dose: floor: the robots' maps (1), 0.1 m cells" in n for n in said)
            assert any("below target:" in n and "region(s)" in n for n in said)
            rig.app.run_command("dose 1 1 3 3")
            await _until(pilot, lambda: any("within x 1..3, y 1..3" in n for n in notices(rig.app)))
            # At a round's own dose (target D, mJ/cm²) instead of the robots' 100 J/m².
            rig.app.run_command("dose 1 1 3 3 target 0.5")
            await _until(pilot, lambda: any("target dose: 5 J/m² (0.5 mJ/cm²)" in n for n in notices(rig.app)))
            rig.app.run_command("dose target 0")
            await pilot.pause()
            assert any("the target dose must be above 0" in n for n in notices(rig.app))

            out = tmp_path / "report"
            rig.app.run_command(f"dose save {out}")
            await _until(pilot, lambda: any("dose report written to" in n for n in notices(rig.app)))
            assert sorted(p.name for p in out.iterdir()) == [
                "dose.csv", "dose.pgm", "dose.png", "summary.json", "summary.txt",
            ]  # fmt: skip
            summary = json.loads((out / "summary.json").read_text())
            assert summary["floor_m2"] == pytest.approx(118 * 78 * 0.0025, rel=0.03)
            assert 0 < summary["reached_m2"] < summary["floor_m2"]
            assert [r["robot"] for r in summary["robots"]] == ["r1", "r2"]

            rig.app.run_command("dose 1 2")
            await pilot.pause()
            assert any("bad command 'dose 1 2'" in n for n in notices(rig.app))
            await pilot.press("D")
            await settle(pilot)
            assert view.dose is None and "at/over" not in view.render_line(g.height - 1).text
    finally:
        fetcher.stop()


@run_async
async def test_dose_without_any_layer_says_so(rig: Rig) -> None:
    async with rig.app.run_test(size=(120, 40)) as pilot:
        rig.app.run_command("dose")
        await pilot.press("D")
        await pilot.pause()
        said = notices(rig.app)
        assert any("no dose layer yet" in n for n in said)
        assert any("dose layer shown: none yet" in n for n in said)


def test_follower_refetches_on_a_gap_and_merges_one_resolution() -> None:
    """Pure parts: a patch that does not follow asks for a snapshot; layers at another resolution
    are left out of the sum (and named)."""
    from fleetlink.operator.fleet import FleetModel
    from fleetlink.shared.clock import SimClock

    clock = SimClock(start=10.0)
    fleet = FleetModel("op")
    f = DoseFollower(fleet, retry_s=1.0, absent_retry_s=5.0)
    counter = wire.HeaderCounter(clock, robot="r1", sender="agent-r1")
    k = _layer(2.0, 2.0, 5.0)
    g = k.grid
    fields = snapshot_fields(
        g.dose,
        g.resolution,
        g.origin,
        k.version,
        target_j_m2=100.0,
        lamp_on_s=g.lamp_seconds,
        unplaced_s=0.0,
        lamp=k.lamp,
    )
    assert fields is not None
    snap = counter.make(DoseSnapshot, **fields)
    upd_fields = patch_fields(g.dose, g.resolution, g.origin, (0, 0, 2, 2), k.version + 5, k.version + 4,
                              target_j_m2=100.0, lamp_on_s=1.0, unplaced_s=0.0)  # fmt: skip
    assert upd_fields is not None
    gap = counter.make(DoseUpdate, **upd_fields)
    assert not f.on_update(gap) and f.wanted(10.0) == ["r1"]  # heard, no copy: fetch
    assert f.wanted(10.5) == []  # not again before retry_s
    assert f.on_snapshot("r1", snap) and f.wanted(12.0) == []
    assert not f.on_update(gap) and f.wanted(12.0) == ["r1"]  # a missed update: fetch again
    assert not f.on_snapshot("r2", dataclasses.replace(snap, width=3))  # cells of the wrong size: refused
    assert f.rejected == 1
    # The agent restarted: its updates go back in version; the next snapshot replaces the copy.
    f.on_snapshot("r1", dataclasses.replace(snap, version=k.version + 9))
    assert f.layers["r1"].version == k.version + 9
    restarted = patch_fields(g.dose, g.resolution, g.origin, (0, 0, 2, 2), 3, 2,
                             target_j_m2=100.0, lamp_on_s=1.0, unplaced_s=0.0)  # fmt: skip
    assert restarted is not None
    assert not f.on_update(counter.make(DoseUpdate, **restarted)) and f.wanted(20.0) == ["r1"]
    assert f.on_snapshot("r1", dataclasses.replace(snap, version=3)) and f.layers["r1"].version == 3
    assert not f.on_snapshot("r1", dataclasses.replace(snap, version=2))  # an older answer after that: kept
    coarse = SharedDose.from_snapshot(snap)
    other = SharedDose(np.ones((4, 4), dtype=np.float32), 0.2, (-0.1, -0.1), 1, 100.0, 2.0, 0.0)
    merged = merge_layers({"r1": coarse, "r2": coarse, "r3": other})
    assert merged is not None and merged.robots == ("r1", "r2") and merged.left_out == ("r3",)


async def _until(pilot: Any, cond: Any, timeout: float = 5.0) -> None:
    """Let the app run (its thread workers post their notices) until ``cond()``."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while not cond():
        assert loop.time() < deadline, "timed out"
        await pilot.pause(0.05)
