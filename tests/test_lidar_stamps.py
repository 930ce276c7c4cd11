"""A lidar turn is stamped when it was complete, not when a late reader found it
(agent/lidar/stamps.py ``TurnStamps``, used by the driver for every turn it reads)."""

from __future__ import annotations

import numpy as np
import pytest

from fleetlink.agent.lidar.driver import LidarDriver
from fleetlink.agent.lidar.stamps import TurnStamps
from fleetlink.shared.clock import SimClock
from tests.test_lidar_link import make_lidar

RATE = 8000.0  # samples per second
TURN = 800  # samples a turn: 10 turns a second


def read_late(seed: int, turns: int = 300) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Turns complete every 0.1 s; a reader that polls every 50 ms but is held up now and then (up
    to 1.2 s) reads them in bunches: (completion, read, stamp) per turn."""
    rng = np.random.default_rng(seed)
    complete = 3.0 + np.arange(1, turns + 1) * TURN / RATE
    reads = []
    t = 3.0
    while t < complete[-1] + 2.0:
        t += 0.05 + (rng.exponential(0.3) if rng.random() < 0.15 else 0.0)
        reads.append(t)
    read_at = np.array([reads[int(np.searchsorted(reads, c))] for c in complete])
    stamps = TurnStamps()
    stamped = np.array([stamps.stamp(TURN, float(r)) for r in read_at])
    return complete, read_at, stamped


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_turns_read_late_in_bunches_are_stamped_when_they_were_complete(seed: int) -> None:
    complete, read_at, stamped = read_late(seed)
    late = read_at - complete
    assert np.mean(np.diff(read_at) == 0.0) > 0.1  # many turns read together with the one before
    assert late.max() > 0.5
    assert np.all(stamped <= read_at)  # never later than read
    assert np.all(np.diff(stamped) >= 0.0)
    steady = slice(64, None)  # once the window is full
    error = np.abs(stamped - complete)[steady]
    # Stamped by the read, a turn is off by the reader's delay; by the line, by the least delay
    # among the window's prompt reads (a poll's 50 ms at most).
    assert error.max() <= 0.05 + 1e-9, error.max()
    assert np.median(error) < 0.25 * np.median(late[steady])


def test_prompt_reads_are_their_own_stamps() -> None:
    stamps = TurnStamps()
    reads = 10.0 + np.arange(1, 50) * 0.1
    assert [stamps.stamp(TURN, float(r)) for r in reads] == pytest.approx(list(reads), abs=1e-9)


def test_a_reset_forgets_the_line() -> None:
    stamps = TurnStamps()
    for k in range(1, 20):
        stamps.stamp(TURN, 1.0 + 0.1 * k)
    stamps.reset()
    # The stream restarted 5 s later, its first two turns read together: nothing before the reset
    # says when they were complete (the old line would stamp them seconds early), so the first is
    # stamped when read; the turns after them, read promptly, lie on a line of their own.
    assert stamps.stamp(TURN, 10.0) == 10.0
    assert stamps.stamp(TURN, 10.0) == 10.0
    reads = 10.0 + np.arange(1, 30) * 0.1
    stamped = [stamps.stamp(TURN, float(r)) for r in reads]
    assert stamped[-10:] == pytest.approx(list(reads[-10:]), abs=1e-9)


def test_the_driver_stamps_a_bunch_of_turns_a_turn_apart() -> None:
    """Real bytes, lockstep: the driver reads promptly for 3 s, then not for half a second. The turns
    it then finds at once are stamped 0.1 s apart, as they came off the lidar."""
    clock = SimClock(start=100.0)
    lidar = make_lidar(now=clock.now())
    with LidarDriver(lidar.in_process_port(clock), clock) as drv:
        drv.start_scan()
        prompt = [r for _ in range(150) for r in drv.poll(clock.now() + 0.02)]
        assert len(prompt) >= 25
        clock.advance(0.45)
        now = clock.now()
        bunch = drv.poll(now)
        assert len(bunch) >= 4
        stamps = np.array([r.stamp for r in bunch])
        assert np.all(stamps <= now)
        np.testing.assert_allclose(np.diff(stamps), 0.1, atol=0.005)
        assert stamps[0] < now - 0.25  # the oldest was complete long before it was read
