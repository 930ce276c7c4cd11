"""When each lidar turn was complete, from when the master read it. Pure: times are passed in.

A turn is complete when the next turn's first sample arrives, but the master learns of it only when
it reads the line, which may be long after: the line delivers steadily, and a reader that was busy
(mapping the last turn, or waiting for the interpreter behind other threads) finds several turns
waiting at once, all read at the same instant. Stamped by the read, they are stamped late by
whatever the reader was late, and a turning robot's map is drawn from the wrong headings: measured
in the real-time field on a loaded two-core host, half the reads held more than one turn, and the
time between reads of consecutive turns varied by 0.14 s (sd), seven degrees of a robot turning at
1 rad/s; its map of a room matched another robot's at 0.26.

The lidar samples at a steady rate, so a turn's completion is a straight line in the samples read
so far: ``c = c0 + x / rate``, with ``x`` the samples up to the turn's end. Each read happens no
sooner than the turns it holds were complete, so every reading lies on or above that line, and the
readings made promptly lie on it. ``TurnStamps`` keeps the last ``window`` readings, takes the
slope of their lower convex hull over the middle of the window and the line of that slope through
the reading that lies lowest against it; a turn's stamp is that line at its last sample, never later
than its read. Readings that were late lie above the line and do not move it; a line through prompt
readings is the lidar's own clock.
"""

from __future__ import annotations

import itertools
from collections import deque

__all__ = ["TurnStamps"]


class TurnStamps:
    """Completion times of consecutive turns from the times they were read.

    ``stamp(samples, read_at)`` for each turn in the order read: ``samples`` in the turn, ``read_at``
    when the bytes that completed it were read; returns when it was complete. ``reset()`` when the
    stream restarts (a new scan, a reconnection): the samples before a gap are not on the line of
    those after it.
    """

    def __init__(self, window: int = 64) -> None:
        if window < 2:
            raise ValueError("the window needs at least two turns")
        self._readings: deque[tuple[float, float]] = deque(maxlen=window)
        self._samples = 0.0
        self._last: float | None = None

    def reset(self) -> None:
        self._readings.clear()
        self._samples = 0.0
        self._last = None

    def stamp(self, samples: int, read_at: float) -> float:
        self._samples += max(1, samples)
        self._readings.append((self._samples, read_at))
        line = _line_below(list(self._readings))
        t = read_at if line is None else min(read_at, line[0] + line[1] * self._samples)
        if self._last is not None:
            t = max(t, self._last)  # the line moved between turns: a stamp never goes back
        self._last = t
        return t


def _line_below(points: list[tuple[float, float]]) -> tuple[float, float] | None:
    """``(intercept, slope)`` of a line under every point: its slope that of their lower convex hull
    between the window's first and third quarters (the hull lies on the readings made promptly, and
    over half the window a prompt reading's few milliseconds change the slope by little: the
    hull's own short edges can be steeper or flatter by those milliseconds over one turn), raised
    until it touches a point. None for fewer than two distinct ``x``."""
    hull: list[tuple[float, float]] = []
    for p in points:  # x increases: Andrew's monotone chain, lower half
        while len(hull) >= 2 and _cross(hull[-2], hull[-1], p) <= 0.0:
            hull.pop()
        hull.append(p)
    if len(hull) < 2:
        return None
    x0, x1 = points[0][0], points[-1][0]
    lo, hi = x0 + 0.25 * (x1 - x0), x0 + 0.75 * (x1 - x0)
    slope = (_at(hull, hi) - _at(hull, lo)) / (hi - lo)
    intercept = min(y - slope * x for x, y in points)
    return intercept, slope


def _at(hull: list[tuple[float, float]], x: float) -> float:
    """The hull's height at ``x`` (within its span)."""
    for (xa, ya), (xb, yb) in itertools.pairwise(hull):
        if x <= xb:
            return ya + (yb - ya) * (x - xa) / (xb - xa)
    return hull[-1][1]


def _cross(o: tuple[float, float], a: tuple[float, float], b: tuple[float, float]) -> float:
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])
