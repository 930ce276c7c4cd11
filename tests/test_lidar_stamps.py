"""A lidar turn is stamped when it was complete, not when a late reader found it
(agent/lidar/stamps.py ``TurnStamps``, used by the driver for every turn it reads)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from fleetlink.agent.lidar.driver import LidarDriver
from fleetlink.agent.lidar.stamps import TurnStamps
from fleetlink.field import lidar as field_lidar
from fleetlink.field import lockstep
from fleetlink.field.lockstep import FieldRun
from fleetlink.field.scenario import LidarSettings, RobotSpec, Scenario
from fleetlink.shared.clock import SimClock
from tests.test_lidar_link import make_lidar

RATE = 8000.0  # samples per second
TURN = 800  # samples a turn: 10 turns a second
T0 = 3.0  # the first sample's time


def sent_by(t: float, lost_after: float = math.inf, lost_s: float = 0.0) -> int:
    """Samples received by ``t``: one every 1/RATE s from T0, but those sent from ``lost_after`` for
    ``lost_s`` never arrive (a serial buffer overflowed)."""
    if t <= lost_after:
        return math.floor((t - T0) * RATE)
    return math.floor((lost_after - T0) * RATE) + max(0, math.floor((t - lost_after - lost_s) * RATE))


def read(stamps: TurnStamps, received: int, read_at: float, counted: int) -> tuple[int, list[float]]:
    """A read at ``read_at`` that takes everything received by then: the turns it completes, counted
    and stamped. (Turns counted so far, their stamps.)"""
    ends = []
    while (counted + 1) * TURN < received:  # a turn is complete when the next one's first sample comes
        counted += 1
        ends.append(stamps.count(TURN))
    stamps.observe(received, read_at)
    return counted, [stamps.stamp(end, read_at) for end in ends]


def run(
    reads: np.ndarray, lost_after: float = math.inf, lost_s: float = 0.0
) -> tuple[np.ndarray, np.ndarray, TurnStamps]:
    """(each turn's completion, its stamp, the stamps) for reads at ``reads``."""
    stamps = TurnStamps()
    counted, stamped = 0, []
    for r in reads:
        counted, got = read(stamps, sent_by(float(r), lost_after, lost_s), float(r), counted)
        stamped += got
    n = len(stamped)
    complete = T0 + np.arange(1, n + 1) * TURN / RATE  # as the samples count time
    complete[complete > lost_after] += lost_s
    return complete, np.array(stamped), stamps


def late_reads(seed: int, seconds: float = 30.0) -> np.ndarray:
    """A reader that polls every 50 ms but is held up now and then (up to a second and more)."""
    rng = np.random.default_rng(seed)
    reads, t = [], T0
    while t < T0 + seconds:
        t += 0.05 + (rng.exponential(0.3) if rng.random() < 0.15 else 0.0)
        reads.append(t)
    return np.array(reads)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_turns_read_late_in_bunches_are_stamped_when_they_were_complete(seed: int) -> None:
    reads = late_reads(seed)
    complete, stamped, stamps = run(reads)
    read_at = reads[np.searchsorted(reads, complete + 1.0 / RATE)]  # each turn's read
    late = read_at - complete
    assert np.mean(np.diff(read_at) == 0.0) > 0.1  # many turns read together with the one before
    assert late.max() > 0.5
    assert np.all(stamped <= read_at + 1e-12)  # never later than read
    assert np.all(np.diff(stamped) >= 0.0)
    assert stamps.resyncs == 0  # late, however late, is not lost
    # Stamped by the read, a turn is off by the reader's delay; by the line of every sample read, by
    # a sample or so (the line touches the reading sent the least before its read).
    error = np.abs(stamped - complete)[8:]
    assert error.max() <= 2.0 / RATE, error.max()


def test_a_reader_polling_on_a_fixed_period_is_not_late_by_its_phase() -> None:
    # Polls every 25 ms, 22 ms after each turn's end (lockstep: a poll every quarter turn, in phase
    # with the turns). Stamped by the reads of whole turns alone, every turn is 22 ms late; the
    # samples of the turn under way say when the read was.
    reads = T0 + 0.022 + np.arange(1, 400) * 0.025
    complete, stamped, _ = run(reads)
    assert np.abs(stamped - complete)[8:].max() <= 2.0 / RATE


def test_prompt_reads_are_their_own_stamps() -> None:
    reads = T0 + np.arange(1, 50) * 0.1 + 1.0 / RATE  # as each turn's next sample arrives
    complete, stamped, _ = run(reads)
    assert stamped == pytest.approx(list(complete), abs=1.5 / RATE)


def test_a_reset_forgets_the_line() -> None:
    stamps = TurnStamps()
    counted = 0
    for r in T0 + np.arange(1, 20) * 0.1 + 0.01:
        counted, _ = read(stamps, sent_by(float(r)), float(r), counted)
    stamps.reset()
    # The stream restarted: its first turn's read is all there is to go by.
    end = stamps.count(800)
    stamps.observe(900, 10.0)
    assert stamps.stamp(end, 10.0) == 10.0


def test_after_samples_are_lost_the_line_is_drawn_again_within_a_few_reads() -> None:
    # Read promptly every 25-50 ms for 10 s; then 0.7 s of samples never arrive (a serial buffer
    # overflowed), and the turns after them are complete 0.7 s later than their samples say. The old
    # line would stamp them 0.7 s early for the whole window.
    rng = np.random.default_rng(7)
    reads = T0 + np.cumsum(rng.uniform(0.025, 0.05, 800))
    complete, stamped, stamps = run(reads, lost_after=T0 + 10.05, lost_s=0.7)
    assert stamps.resyncs == 1
    error = np.abs(stamped - complete)
    after = np.flatnonzero(complete > T0 + 10.05)
    assert error[8 : after[0]].max() <= 2.0 / RATE  # before: on the line
    assert error[after[2] :].max() <= 2.0 / RATE, error[after[2] :].max()  # within three reads, drawn again
    assert np.all(np.diff(stamped) >= 0.0)


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
        np.testing.assert_allclose(np.diff(stamps), 0.1, atol=0.002)
        assert stamps[0] < now - 0.25  # the oldest was complete long before it was read


class ChunkedPort:
    """An in-process port whose reads return at most ``READ_CHUNK`` bytes, as a serial port's do
    (``SerialPort.READ_CHUNK``), each a tenth of a millisecond after the last: a backlog comes in
    several reads, all but the last leaving more waiting."""

    READ_CHUNK = 4096

    def __init__(self, inner: Any, clock: SimClock) -> None:
        self.inner, self.clock, self.left = inner, clock, b""

    def write(self, data: bytes) -> None:
        self.inner.write(data)

    def read_some(self, clock: Any, deadline: float) -> bytes:
        self.clock.advance(0.0001)
        if not self.left:
            self.left = self.inner.read_some(clock, deadline)
        out, self.left = self.left[: self.READ_CHUNK], self.left[self.READ_CHUNK :]
        return out

    def set_dtr(self, level: bool) -> None:
        self.inner.set_dtr(level)

    def close(self) -> None:
        self.inner.close()


@pytest.mark.parametrize("mode", ["standard", "express"])
def test_a_backlog_read_in_chunks_is_stamped_when_its_turns_were_complete(mode: str) -> None:
    """Real bytes: a driver reading every 25 ms, then held up for a second; the backlog comes in
    4 kB reads. Each turn is stamped when the lidar completed it (a reading is taken only from a
    read that emptied the port), from the first turn on (express: the capsule the decoder holds
    back is not counted before the first turn's start, whose nodes before it are dropped)."""
    clock = SimClock(start=100.0)
    lidar = make_lidar(now=clock.now())
    lidar.config = dataclasses.replace(lidar.config, max_backlog_s=5.0)  # nothing skipped: all sent late
    starts: list[float] = []
    source = lidar.scan_source

    def recorded(t: float) -> Any:
        starts.append(t)
        return source(t)

    lidar.scan_source = recorded
    drv = LidarDriver(ChunkedPort(lidar.in_process_port(clock), clock), clock, scan_mode=mode)
    drv.start_scan()
    got: list[tuple[float, float]] = []

    def drain() -> None:
        now = clock.now()
        for _ in range(64):
            revs = drv.poll(now)
            if not revs:
                break
            got.extend((clock.now(), r.stamp) for r in revs)

    for _ in range(120):
        drain()
        clock.advance(0.025)
    clock.advance(1.0)
    drain()
    for _ in range(40):
        clock.advance(0.025)
        drain()
    drv.close()
    read_at = np.array([r for r, _ in got])
    stamps = np.array([s for _, s in got])
    # Turn k was complete when turn k + 1 began (express drops the first, begun before the stream).
    first = 1 if mode == "standard" else 2
    complete = np.array(starts[first : first + len(stamps)])
    assert len(stamps) > 40 and drv.turns.resyncs == 0
    assert read_at.max() - (read_at - complete).max() < read_at.max() - 0.5  # some read 0.5 s late and more
    assert np.all(stamps <= read_at)
    assert np.abs(stamps - complete).max() <= 0.002, np.abs(stamps - complete).max()


def test_in_lockstep_a_turning_robots_turns_are_dated_when_the_field_cast_them(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The lockstep field, a robot turning at 1 rad/s, its lidar's bytes read by the driver a quarter
    turn apart (as the agent's feed reads them, in phase with the turns): each turn's date (its stamp
    less a turn) is the time the field cast it, and the field cast it from where the robot was then."""
    scenario = Scenario(
        name="spin",
        plan="hall",
        seed=3,
        duration=6.0,
        robots=(RobotSpec("r1", pose=(10.0, 10.0, 0.0), drive="idle"),),
        lidar=LidarSettings(enabled=True),
    )
    casts: list[tuple[float, tuple[float, float, float]]] = []

    def recording(model: Any, pose: Callable[[float], Any], *args: Any) -> Callable[[float], Any]:
        def where(t: float) -> Any:  # the pose the field casts a turn from, and when
            casts.append((t, pose(t)))
            return casts[-1][1]

        return field_lidar.scan_source_for(model, where, *args)

    monkeypatch.setattr(lockstep, "scan_source_for", recording)
    with FieldRun(scenario, open_loop=False) as fr:
        robot = fr.rigs[0].robot
        driver = LidarDriver(fr.lidar_port(0), fr.clock, pwm_motor_control=True)
        revs: list[tuple[float, float | None]] = []
        due = [0.5]

        def controller(t: float) -> None:
            robot.board.state.last_ctrl_bus = t  # the watchdog fed, as a master would
            robot.board.drive(0.0, 1.0, t)
            if t >= due[0]:
                if not driver.scanning:
                    driver.start_scan()
                revs.extend((t, r.stamp) for r in driver.poll(t))
                due[0] = t + 0.025

        fr.controllers.append(controller)
        fr.run()
        truth = np.array([row[:4] for row in fr.result(fr.clock.now(), 0.0).truth["r1"]])
    stamps = np.array([s for _, s in revs if s is not None])
    assert len(stamps) >= 40 and np.all(stamps <= np.array([t for t, s in revs if s is not None]))
    turn = float(np.median(np.diff(stamps)))
    assert turn == pytest.approx(0.1, abs=0.002)
    # Turn k is the k-th cast after those the driver dropped whole (the first, whose start it did not
    # see: its nodes counted as orphans).
    dropped = driver.assembler.stats.orphan_nodes / (RATE * 0.1)
    assert dropped == 1.0
    cast_t = np.array([c[0] for c in casts])[1 : 1 + len(stamps)]
    dates = stamps - turn
    # Read a poll late, up to 25 ms; dated to a sample once the line has two seconds of readings.
    assert np.abs(dates - cast_t)[4:].max() <= 0.005
    assert np.abs(dates - cast_t)[16:].max() <= 2.0 / RATE
    # The cast's heading is the truth's at the date (the physics' steps, 5 ms, interpolated).
    th = np.unwrap(truth[:, 3])
    for t, (_, _, heading) in casts[5:]:
        assert abs(math.remainder(heading - float(np.interp(t, truth[:, 0], th)), math.tau)) < math.radians(0.1)


def test_in_lockstep_the_robots_a_turn_sees_are_where_they_were_when_it_was_cast(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A turn is cast from its start, which the lockstep field learns a poll later: the robot casting
    it is placed where it was then, and another robot crossing in front of it is too (0.4 m/s moves it
    up to a centimetre in a 25 ms poll)."""
    scenario = Scenario(
        name="crossing",
        plan="hall",
        seed=3,
        duration=3.0,
        robots=(
            RobotSpec("r1", pose=(10.0, 10.0, 0.0), drive="idle"),
            RobotSpec("r2", pose=(12.0, 8.0, math.pi / 2), drive="idle"),
        ),
        lidar=LidarSettings(enabled=True),
    )
    seen: list[tuple[float, Any]] = []

    def recording(model: Any, pose: Callable[[float], Any], raycaster: Any, circles: Any) -> Callable[[float], Any]:
        def bodies(x: float, y: float, at: float) -> Any:
            out = circles(x, y, at)
            seen.append((at, None if out is None else np.array(out)))
            return out

        return field_lidar.scan_source_for(model, pose, raycaster, bodies)

    monkeypatch.setattr(lockstep, "scan_source_for", recording)
    with FieldRun(scenario, open_loop=False) as fr:
        r1, r2 = fr.rigs[0].robot, fr.rigs[1].robot
        driver = LidarDriver(fr.lidar_port(0), fr.clock, pwm_motor_control=True)
        due = [0.5]

        def controller(t: float) -> None:
            for robot in (r1, r2):
                robot.board.state.last_ctrl_bus = t
            r2.board.drive(0.4, 0.4, t)
            if t >= due[0]:
                if not driver.scanning:
                    driver.start_scan()
                driver.poll(t)
                due[0] = t + 0.025

        fr.controllers.append(controller)
        fr.run()
        truth = np.array([row[:3] for row in fr.result(fr.clock.now(), 0.0).truth["r2"]])
    casts = [(t, c) for t, c in seen if t > 1.0]  # r2 at speed
    assert len(casts) >= 15
    for t, circles in casts:
        assert circles is not None and len(circles) == 1
        x, y = float(np.interp(t, truth[:, 0], truth[:, 1])), float(np.interp(t, truth[:, 0], truth[:, 2]))
        assert math.hypot(circles[0][0] - x, circles[0][1] - y) < 0.001, (t, circles[0], (x, y))
