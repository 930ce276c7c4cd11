from __future__ import annotations

import threading

import pytest

from fleetlink.shared.clock import Clock, SimClock, SystemClock


def test_both_clocks_satisfy_the_interface() -> None:
    assert isinstance(SystemClock(), Clock)
    assert isinstance(SimClock(), Clock)


def test_system_clock_sleeps_until_a_deadline() -> None:
    clock = SystemClock()
    t0 = clock.now()
    clock.sleep_until(t0 + 0.02)
    assert clock.now() >= t0 + 0.02
    clock.sleep_until(t0)  # already past: returns at once
    assert clock.wall() > 1_600_000_000


def test_sim_clock_moves_only_when_told() -> None:
    clock = SimClock(start=5.0)
    assert clock.now() == 5.0
    clock.advance(0.25)
    assert clock.now() == 5.25
    clock.sleep_until(7.0)  # the lockstep owner jumps straight to the deadline
    assert clock.now() == 7.0
    clock.sleep_until(6.0)
    assert clock.now() == 7.0
    assert clock.wall() == pytest.approx(1_767_225_600.0 + 7.0)
    with pytest.raises(ValueError):
        clock.advance(-1)
    with pytest.raises(ValueError):
        clock.set(1.0)


def test_sim_clock_wakes_waiting_threads_when_advanced() -> None:
    clock = SimClock()
    woke = threading.Event()

    def waiter() -> None:
        if clock.wait_until(1.0, timeout=5.0):
            woke.set()

    t = threading.Thread(target=waiter)
    t.start()
    clock.advance(0.5)
    assert not woke.wait(0.05)
    clock.advance(0.5)
    t.join(5.0)
    assert woke.is_set()
