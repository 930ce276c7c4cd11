"""Python's garbage collector, paced by the console (docs/console.md, "Responsiveness").

CPython collects when enough objects have been allocated, in whichever thread allocates and at
whatever moment: at 500 robots a full pass walked 80-110 k objects and held the UI thread (and
every other thread: it holds the interpreter lock) for 45-170 ms, and a frame or a key press that
met it waited. While the console runs, automatic collection is off and the app collects at
moments it chooses, in slices (``Collector.step``, called after each frame, telemetry slice and
drive tick, so at least 20 times a second):

* the young objects (generation 0) once ``young`` more of them live than at the last pass: a pass
  walks only the survivors, the rest were freed by their reference counts;
* generation 1 every ``middle_every`` young passes;
* a full pass every ``full_every`` generation-1 passes, right after a frame (the next one is a
  tenth of a second away); one that waits more than twice that long is done at once;
* when the fleet has grown by a quarter since the last freeze, a full pass after the next frame
  and what survived it frozen (``gc.freeze``: out of later passes, never collected). Later passes
  then walk what the console made since, not the 500 robots' state; and as each freeze needs a
  larger fleet than the last, there are at most a few dozen of them in a console's life (most as
  the robots first appear), so what a freeze keeps that later becomes garbage stays bounded (the
  memory does not grow with the hours run).

``untangle_strips`` takes away the reference cycle Textual's ``Strip.divide`` made for every line
it drew (the compositor divides each line it draws; a line that needs no cut was kept in its own
cache): at 500 robots those lines were nine tenths of what full passes freed.
"""

from __future__ import annotations

import gc
from collections.abc import Callable, Iterable, Sequence
from typing import Any, Protocol

from textual.strip import Strip

__all__ = ["Collector", "GcModule", "untangle_strips"]

YOUNG = 5_000
"""Young objects (allocated and still alive since the last pass) that start a young pass: at 500
robots x 20 Hz about four passes a second, 1-3 ms of CPU each (20 000: 3-12 ms)."""
MIDDLE_EVERY = 10
"""A generation-1 pass every this many young passes (CPython's own ratio)."""
FULL_EVERY = 20
"""A full pass after this many generation-1 passes (CPython's default is 10, and more when the
old generation is large)."""
GROWTH_TO_FREEZE = 1.25
"""Freeze the survivors of a full pass when the fleet is this many times the one last frozen."""


class GcModule(Protocol):
    """What the collector uses of ``gc`` (a fake in the tests)."""

    def isenabled(self) -> bool: ...

    def enable(self) -> None: ...

    def disable(self) -> None: ...

    def get_count(self) -> tuple[int, int, int]: ...

    def collect(self, generation: int = 2) -> int: ...

    def freeze(self) -> None: ...


class Collector:
    """Paces collections (module docstring). ``start`` turns automatic collection off, ``stop``
    turns it back on if it was. Only the UI thread calls ``step``."""

    def __init__(
        self,
        now: Callable[[], float],
        *,
        young: int = YOUNG,
        middle_every: int = MIDDLE_EVERY,
        full_every: int = FULL_EVERY,
        gc_module: GcModule | None = None,
    ) -> None:
        """``now``: the console's clock (how long each pass took, for ``longest``)."""
        self._now = now
        self.young = young
        self.middle_every = middle_every
        self.full_every = full_every
        self._gc: Any = gc if gc_module is None else gc_module
        self._was_enabled = False
        self.running = False
        self.passes = [0, 0, 0]
        """Passes done by generation."""
        self.longest = [0.0, 0.0, 0.0]
        """The longest pass of each generation, in seconds."""
        self.freezes = 0
        self._young_since_middle = 0
        self._middle_since_full = 0
        self._frozen_fleet = 0

    def start(self) -> None:
        if self.running:
            return
        self._was_enabled = self._gc.isenabled()
        self._gc.disable()
        self.running = True

    def stop(self) -> None:
        if not self.running:
            return
        self.running = False
        if self._was_enabled:
            self._gc.enable()

    def step(self, *, after_frame: bool = False, fleet: int = 0) -> int | None:
        """Collect what is due (one pass at most): the generation collected, None if nothing was.
        ``after_frame``: a frame was just drawn (a full pass may run now); ``fleet``: the robots
        known (what a freeze waits for)."""
        if not self.running:
            return None
        grown = fleet > 0 and fleet >= GROWTH_TO_FREEZE * self._frozen_fleet
        full_due = self._middle_since_full >= self.full_every
        if (after_frame and (full_due or grown)) or self._middle_since_full >= 2 * self.full_every:
            self._collect(2)
            self._middle_since_full = self._young_since_middle = 0
            if grown:
                self._gc.freeze()
                self._frozen_fleet = fleet
                self.freezes += 1
            return 2
        if self._gc.get_count()[0] < self.young:
            return None
        if self._young_since_middle + 1 >= self.middle_every:
            self._collect(1)
            self._young_since_middle = 0
            self._middle_since_full += 1
            return 1
        self._collect(0)
        self._young_since_middle += 1
        return 0

    def _collect(self, generation: int) -> None:
        t0 = self._now()
        self._gc.collect(generation)
        took = self._now() - t0
        self.passes[generation] += 1
        self.longest[generation] = max(self.longest[generation], took)


_divide = Strip.divide


def _divide_untangled(self: Strip, cuts: Iterable[int]) -> Sequence[Strip]:
    """``Strip.divide``, but a strip that needs no cut is returned in a new list, not kept in its
    own cache (which made each drawn line a reference cycle that only a full pass frees)."""
    cuts = list(cuts)
    length = self.cell_length
    if [c for c in cuts if c <= length] == [length]:
        return [self]
    return _divide(self, cuts)


def untangle_strips() -> None:
    """Put ``_divide_untangled`` in place of ``Strip.divide`` (once; the same results)."""
    if Strip.divide is not _divide_untangled:
        Strip.divide = _divide_untangled  # type: ignore[method-assign]
