"""When each lidar turn was complete, from when the master read its samples. Pure: times are passed in.

A turn is complete when the next turn's first sample arrives, but the master learns of it only when
it reads the line, which may be long after: the line delivers steadily, and a reader that was busy
(mapping the last turn, or waiting for the interpreter behind other threads) finds several turns
waiting at once, all read at the same instant. Stamped by the read, they are stamped late by
whatever the reader was late, and a turning robot's map is drawn from the wrong headings: measured
in the real-time field on a loaded two-core host, half the reads held more than one turn, and the
time between reads of consecutive turns varied by 0.14 s (sd), seven degrees of a robot turning at
1 rad/s; its map of a room matched another robot's at 0.26.

The lidar samples at a steady rate, so the time its ``x``-th sample was sent is a straight line,
``c0 + x / rate``. A read that takes everything that has arrived (the samples of the turns it
completes and those of the turn under way) happens no sooner than its last sample was sent, so
every reading ``(samples received in all, read time)`` lies on or above that line, and a reading
that found nothing held back in the port's buffer lies on it, however late the reader was.
``TurnStamps`` keeps the last ``window`` readings, takes the slope of their lower convex hull over
the middle of the window and the line of that slope through the reading that lies lowest against
it; a turn's stamp is that line at its last sample, never later than its read. A reader that
polls on a fixed period whose turns are read a fixed time after they end (lockstep: a poll every
quarter turn) still has each of its reads on the line; stamped by the turns' reads alone, each
turn would be that fixed time late.

Samples lost on the way (a serial buffer that overflowed while the reader was held up, a device that
skipped what it could not send) put every later reading above the line by the time lost. When each
of ``resync_reads`` reads in a row lies more than ``RESYNC_TURNS`` of a turn above the line, the
readings before them are dropped: the line is drawn again through the readings since.
"""

from __future__ import annotations

import itertools
from collections import deque

__all__ = ["TurnStamps"]


class TurnStamps:
    """Completion times of consecutive turns from the times their samples were read.

    For each read: ``count(samples)`` for each turn it completed, in order (returns where the turn
    ends, in samples since the stream began), then, if the read took everything that was waiting,
    ``observe(received, read_at)`` with every sample received so far (those of the turn under way
    too) and when; then ``stamp(end, read_at)`` for each of those turns. ``reset()`` when the
    stream restarts (a new scan, a reconnection): the samples before a gap are not on the line of
    those after it.
    """

    def __init__(self, window: int = 64, resync_reads: int = 3) -> None:
        if window < 2 or resync_reads < 1:
            raise ValueError("the window needs at least two readings, a resync at least one read")
        self._readings: deque[tuple[float, float]] = deque(maxlen=window)
        self._reads: deque[tuple[float, float, float]] = deque(maxlen=resync_reads)
        """The last reads: (read time, the least height above the line of a reading then, the
        samples received before it)."""
        self._samples = 0.0
        self._turn = 0.0
        self._line: tuple[float, float] | None = None
        self._last: float | None = None
        self.resync_reads = resync_reads
        self.resyncs = 0
        """Times the line was drawn again after samples were lost."""

    @property
    def samples(self) -> float:
        """Samples of the turns counted so far."""
        return self._samples

    def reset(self) -> None:
        """The stream restarted: its samples are counted anew, on a line of their own (stamps still
        never go back)."""
        self._readings.clear()
        self._reads.clear()
        self._samples = 0.0
        self._line = None

    def count(self, samples: int) -> float:
        """A turn of ``samples`` completed: where it ends, in samples since the stream began."""
        n = max(1, samples)
        # The turn's length, smoothed (a short turn, where the stream restarted, says little of it).
        self._turn = n if self._turn == 0 else 0.8 * self._turn + 0.2 * n
        self._samples += n
        return self._samples

    def observe(self, received: float, read_at: float) -> None:
        """``received`` samples in all (the turns counted and the turn under way) by ``read_at``."""
        before = self._readings[-1][0] if self._readings else 0.0
        if received <= before:
            return  # nothing new arrived: it says nothing of when the samples were sent
        self._readings.append((received, read_at))
        line = _line_below(list(self._readings))
        if line is not None:
            above = read_at - (line[0] + line[1] * received)
            if self._reads and self._reads[-1][0] == read_at:
                t0, least, first = self._reads[-1]
                self._reads[-1] = (t0, min(least, above), first)
            else:
                self._reads.append((read_at, above, before))
            reads = self._reads
            turn = line[1] * self._turn
            if turn > 0.0 and len(reads) == reads.maxlen and min(r[1] for r in reads) > RESYNC_TURNS * turn:
                since = reads[0][2]
                kept = [r for r in self._readings if r[0] > since]
                self._readings.clear()
                self._readings.extend(kept)
                self._reads.clear()
                self.resyncs += 1
                line = _line_below(kept)
        self._line = line

    def stamp(self, end: float, read_at: float) -> float:
        """When the turn ending at sample ``end`` (``count``'s answer), read at ``read_at``, was
        complete, as the readings observed so far tell: never later than its read, never before the
        last stamp."""
        line = self._line
        t = read_at if line is None else min(read_at, line[0] + line[1] * end)
        if self._last is not None:
            t = max(t, self._last)  # the line moved between turns: a stamp never goes back
        self._last = t
        return t


RESYNC_TURNS = 0.5
"""How far above the line (in turns) each of the last reads must lie before the line is taken to be
broken: a read that takes everything that has arrived lies within the line's scatter of it (a
sample's time and the transfer's, milliseconds)."""


def _line_below(points: list[tuple[float, float]]) -> tuple[float, float] | None:
    """``(intercept, slope)`` of a line under every point: its slope that of their lower convex hull
    between the window's first and third quarters (the hull lies on the prompt readings, and over
    half the window a reading's few milliseconds change the slope by little), raised until it
    touches a point. None for fewer than two distinct ``x``."""
    if not points:
        return None
    hull: list[tuple[float, float]] = []
    for p in points:  # x does not decrease: Andrew's monotone chain, lower half
        while len(hull) >= 2 and _cross(hull[-2], hull[-1], p) <= 0.0:
            hull.pop()
        hull.append(p)
    x0, x1 = points[0][0], points[-1][0]
    if len(hull) < 2 or x1 <= x0:
        return None
    lo, hi = x0 + 0.25 * (x1 - x0), x0 + 0.75 * (x1 - x0)
    slope = (_at(hull, hi) - _at(hull, lo)) / (hi - lo)
    intercept = min(y - slope * x for x, y in points)
    return intercept, slope


def _at(hull: list[tuple[float, float]], x: float) -> float:
    """The hull's height at ``x`` (within its span)."""
    for (xa, ya), (xb, yb) in itertools.pairwise(hull):
        if x <= xb and xb > xa:
            return ya + (yb - ya) * (x - xa) / (xb - xa)
    return hull[-1][1]


def _cross(o: tuple[float, float], a: tuple[float, float], b: tuple[float, float]) -> float:
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])
