"""The agent's lidar feed catches up at once after its reader was held up, and maps the newest turn
(agent/node.py ``LidarFeed.step``, ``AgentNode.add_revolutions``): real RPLIDAR bytes, lockstep."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

from fleetlink.agent.lidar.driver import LidarDriver
from fleetlink.agent.node import AgentNode, LidarFeed
from fleetlink.shared.clock import SimClock
from tests.test_lidar_link import make_lidar


class Node:
    """What the feed needs of a node, with the real ``AgentNode.add_revolutions`` in front of a
    recorder of the turns it maps."""

    def __init__(self, clock: SimClock) -> None:
        self.clock = clock
        self.robot = "r1"
        self.lidar_fault = None
        self.config = SimpleNamespace(lidar="inproc")
        self.stale_turns = 0
        self.recorded: list[Any] = []
        self.scan_sink = self.recorded.append
        self.mapped: list[Any] = []

    def add_revolutions(self, revs: list[Any], turn_s: float = 0.0) -> None:
        AgentNode.add_revolutions(self, revs, turn_s)  # type: ignore[arg-type]

    def add_revolution(self, rev: Any, turn_s: float = 0.0) -> None:
        self.mapped.append(rev)
        self.recorded.append(rev)


def test_a_feed_held_up_takes_every_turn_waiting_and_maps_the_newest() -> None:
    clock = SimClock(start=50.0)
    lidar = make_lidar(now=clock.now())  # 10 turns a second
    node = Node(clock)
    feed = LidarFeed(node, lambda: LidarDriver(lidar.in_process_port(clock, advance_clock=False), clock))
    for _ in range(40):  # read promptly, a step every 50 ms, for 2 s
        clock.advance(0.05)
        feed.step(clock.now())
    prompt = len(node.mapped)
    assert prompt >= 15 and node.stale_turns == 0
    clock.advance(1.2)  # the reader held up for 1.2 s: turns wait (as many as the device's backlog holds)
    feed.step(clock.now())
    assert len(node.mapped) == prompt + 1  # one turn mapped: the newest
    stale = node.stale_turns
    assert stale >= 2  # the rest counted, not mapped ...
    assert len(node.recorded) == len(node.mapped) + node.stale_turns  # ... and still recorded
    # The newest turn, dated on the lidar's clock: complete within a turn and a half of the read (the
    # device skipped what it could not send, so the line of the turns before lies 0.7 s early).
    newest = node.mapped[-1].stamp
    assert clock.now() - 1.5 * feed.turn_s - 1e-9 <= newest <= clock.now()
    clock.advance(0.05)
    feed.step(clock.now())  # caught up: the next step finds at most the turn completed since
    assert len(node.mapped) <= prompt + 2 and node.stale_turns == stale
    assert feed.driver.stats.revolutions == len(node.recorded)  # every turn the driver read, accounted for
    feed.close()
