"""The console paces Python's garbage collector (operator/collector.py): no automatic collection
while it runs, young passes often, full passes after a frame, survivors frozen as the fleet grows,
memory bounded over a long run; and Textual's drawn lines are no longer reference cycles.
Behaviour, not timings (bench/console.py measures those)."""

from __future__ import annotations

import gc
import math
import weakref
from collections import deque
from itertools import pairwise
from pathlib import Path

from rich.segment import Segment
from textual.strip import Strip

from fleetlink.operator import collector as collector_module
from fleetlink.operator.collector import GROWTH_TO_FREEZE, Collector, untangle_strips
from fleetlink.shared.clock import SimClock
from tests.test_console import Rig, run_async, settle


class FakeGc:
    """``gc`` as the collector sees it: counts set by the test, passes and freezes recorded."""

    def __init__(self) -> None:
        self.enabled = True
        self.young = 0
        self.collected: list[int] = []
        self.freezes = 0

    def isenabled(self) -> bool:
        return self.enabled

    def enable(self) -> None:
        self.enabled = True

    def disable(self) -> None:
        self.enabled = False

    def get_count(self) -> tuple[int, int, int]:
        return (self.young, 0, 0)

    def collect(self, generation: int = 2) -> int:
        self.collected.append(generation)
        self.young = 0
        return 0

    def freeze(self) -> None:
        self.freezes += 1


def collector(fake: FakeGc, **kw: int) -> Collector:
    c = Collector(SimClock(start=0.0).now, gc_module=fake, **kw)
    c.start()
    return c


def test_automatic_collection_is_off_while_started_and_back_as_it_was() -> None:
    fake = FakeGc()
    c = collector(fake)
    assert not fake.enabled
    c.stop()
    assert fake.enabled
    fake.enabled = False  # someone had turned it off: it stays off
    c.start()
    c.stop()
    assert not fake.enabled
    assert c.step() is None  # stopped: never collects


def test_young_passes_when_enough_young_objects_then_a_middle_pass_every_tenth() -> None:
    fake = FakeGc()
    c = collector(fake, young=100, middle_every=3)
    fake.young = 99
    assert c.step() is None and fake.collected == []
    for _ in range(6):
        fake.young = 100
        c.step()
    assert fake.collected == [0, 0, 1, 0, 0, 1]


def test_a_full_pass_waits_for_a_frame_unless_long_overdue() -> None:
    fake = FakeGc()
    c = collector(fake, young=1, middle_every=1, full_every=2)
    for _ in range(2):  # two middle passes: a full one is due
        fake.young = 1
        c.step()
    assert fake.collected == [1, 1]
    fake.young = 1
    assert c.step() == 1  # not after a frame: not yet
    assert c.step(after_frame=True) == 2
    for _ in range(4):  # due again after two, then twice overdue after four
        fake.young = 1
        assert c.step() == 1
    fake.young = 1
    assert c.step() == 2  # done without waiting for a frame
    assert c.passes[2] == 2


def test_survivors_are_frozen_as_the_fleet_grows_a_bounded_number_of_times() -> None:
    fake = FakeGc()
    c = collector(fake, young=1, middle_every=1, full_every=1)
    for robots in range(1, 1001):  # a fleet growing to 1000 robots, a full pass at each size
        fake.young = 1
        c.step()
        c.step(after_frame=True, fleet=robots)
    assert fake.collected.count(2) == 1000
    assert fake.freezes == c.freezes <= math.log(1000, GROWTH_TO_FREEZE) + 1
    for _ in range(100):  # the fleet stays as it is: full passes go on, nothing more is frozen
        fake.young = 1
        c.step()
        c.step(after_frame=True, fleet=1000)
    assert fake.freezes == c.freezes


def test_a_fleet_grown_by_a_quarter_gets_a_full_pass_after_the_next_frame_and_is_frozen() -> None:
    fake = FakeGc()
    c = collector(fake)  # no pass due
    assert c.step(fleet=500) is None  # not after a frame
    assert c.step(after_frame=True, fleet=500) == 2 and fake.freezes == 1
    assert c.step(after_frame=True, fleet=600) is None  # not a quarter more
    assert c.step(after_frame=True, fleet=625) == 2 and fake.freezes == 2


class Knot:
    """A reference cycle that counts the knots alive."""

    alive = 0

    def __init__(self) -> None:
        self.me = self
        Knot.alive += 1

    def __del__(self) -> None:
        Knot.alive -= 1


def test_memory_stays_bounded_over_a_long_run_with_the_real_collector() -> None:
    """Cycles that live a few frames and then become garbage, as the console makes, while the
    fleet grows to 500 robots (survivors frozen on the way) and then holds: after each full pass
    what is alive is the last frames' cycles and what the freezes held, the same after 3000
    frames as after 1000; unfrozen, all of it goes."""
    Knot.alive = 0
    was_enabled = gc.isenabled()
    c = Collector(SimClock(start=0.0).now, young=1000, middle_every=3, full_every=3)
    recent: deque[list[Knot]] = deque(maxlen=3)
    after_full: list[tuple[int, int, int]] = []
    """(frame, knots alive, freezes so far) after each full pass."""
    most = 0
    c.start()
    try:
        for frame in range(3000):
            recent.append([Knot() for _ in range(50)])  # alive for three frames
            if c.step(after_frame=True, fleet=min(500, 1 + frame // 2)) == 2:
                after_full.append((frame, Knot.alive, c.freezes))
            most = max(most, Knot.alive)
    finally:
        c.stop()
        gc.unfreeze()
    assert gc.isenabled() == was_enabled
    assert c.passes[0] > 0 and c.passes[1] > 0 and len(after_full) > 10 and c.freezes > 3
    for _, alive, freezes in after_full:
        assert alive <= 3 * 50 * (1 + freezes)  # the last frames', and what each freeze held
    settled = {alive for frame, alive, _ in after_full if frame > 1000}  # the fleet no longer grows
    assert len(settled) == 1
    gaps = [b[0] - a[0] for a, b in pairwise(after_full)]
    assert most <= settled.pop() + 50 * max(gaps)  # and what became garbage since the last full pass
    recent.clear()
    gc.collect()
    assert Knot.alive == 0


def test_a_line_drawn_without_a_cut_is_not_a_reference_cycle() -> None:
    untangle_strips()
    strip = Strip([Segment("abc"), Segment("def")], 6)
    assert strip.divide([6]) == [strip]
    assert strip.divide([6, 9]) == [strip]  # cuts past the end are ignored, as before
    # Nothing the strip keeps holds it (Textual kept ``[strip]`` in the strip's own cache).
    assert not [r for r in gc.get_referrers(strip) if isinstance(r, list)]
    strip = Strip([Segment("abc"), Segment("def")], 6)
    cut = strip.divide([2, 6])
    assert [s.text for s in cut] == [s.text for s in collector_module._divide(strip, [2, 6])] == ["ab", "cdef"]


@run_async
async def test_the_console_collects_its_own_garbage_and_gives_the_collector_back(tmp_path: Path) -> None:
    was_enabled = gc.isenabled()
    rig = Rig(tmp_path, clock=SimClock(start=100.0))
    rig.link.start()
    try:
        async with rig.app.run_test(size=(120, 40)) as pilot:
            assert not gc.isenabled()  # no pass starts in whichever thread allocates
            rig.app.collector.young = 0  # a pass at every step
            knot = Knot()
            freed = weakref.ref(knot)
            del knot
            rig.pose("r01", 1.0, 1.0)
            await settle(pilot, 0.3)  # frames and drive ticks step the collector
            assert freed() is None
            assert rig.app.collector.passes[0] > 0
        assert gc.isenabled() == was_enabled
    finally:
        rig.link.close()
