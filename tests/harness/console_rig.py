"""The console on the real OperatorLink over in-memory links, with a fake robot voice.

Used by tests/test_console*.py and bench/console.py: the console sees exactly the bytes that would
go on Zenoh or MQTT, and the rig injects what a robot would say.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from fleetlink.links.base import LinkStats, key_matches
from fleetlink.operator.console import ConsoleApp, attach
from fleetlink.operator.fleet import FleetModel
from fleetlink.operator.linkmanager import LinkPolicy
from fleetlink.operator.links import OperatorLink
from fleetlink.shared import wire
from fleetlink.shared.clock import Clock, SystemClock
from fleetlink.shared.messages import UNKNOWN_SD_M, Ack, AckResult, InstantActions, LinkName, Order, Pose, Teleop
from fleetlink.site.rounds import plan_round

__all__ = ["CALM", "ME", "PROMPT", "MemoryTransport", "Rig"]

ME = "operator-1"

CALM = LinkPolicy(state_window_s=5.0, ack_timeout_s=2.0, holdoff_s=1.0)
"""The rig's default: the voice thread and the console share a loaded CI machine, where a 20 Hz
voice can miss the production window (0.35 s) and move commands to MQTT mid-test. Tests that
exercise failover pass ``PROMPT``."""
PROMPT = LinkPolicy(state_window_s=0.35, ack_timeout_s=0.25, holdoff_s=1.0)


MAX_ROUTES = 100_000
"""Keys whose receivers a ``MemoryTransport`` keeps (the rest are matched every time)."""


class MemoryTransport:
    """A ``fleetlink.links.base.Link`` that records what is published and injects what arrives."""

    PUBLISH_QUEUES = True
    """``publish`` only records (links/sender.py: sent inline, so a test reads it at once)."""

    def __init__(self, name: str) -> None:
        self.name = LinkName(name)
        self.stats = LinkStats()
        self.up = True
        self.sent: list[tuple[str, bytes]] = []
        self._receivers: list[tuple[str, Callable[[str, bytes], None]]] = []
        self._routes: dict[str, list[Callable[[str, bytes], None]]] = {}
        """The receivers of each key injected so far (as Zenoh routes a key once, not per sample:
        matching every sample against every subscription in Python cost the bench's console a
        quarter of its network thread at 500 robots)."""
        self.lock = threading.Lock()
        self.responder: Callable[[MemoryTransport, str, bytes], None] | None = None

    def start(self) -> None:
        pass

    def prioritise(self, priority_keys: frozenset[str], *, then_topics: frozenset[str] = frozenset()) -> None:
        pass

    def subscribe(self, key_expr: str, receiver: Callable[[str, bytes], None]) -> None:
        self._receivers.append((key_expr, receiver))
        self._routes.clear()

    def publish(self, key: str, payload: bytes) -> bool:
        with self.lock:
            self.sent.append((key, payload))
        if self.responder is not None:
            self.responder(self, key, payload)
        return True

    def close(self) -> None:
        self._receivers.clear()
        self._routes.clear()

    def inject(self, msg: wire.Message) -> None:
        self.inject_raw(wire.key_of(msg), wire.encode(msg))

    def inject_raw(self, key: str, payload: bytes) -> None:
        receivers = self._routes.get(key)
        if receivers is None:
            receivers = [r for expr, r in self._receivers if key_matches(expr, key)]
            if len(self._routes) < MAX_ROUTES:
                self._routes[key] = receivers
        assert receivers, "not started, or closed"
        for receiver in receivers:
            receiver(key, payload)

    def messages(self, cls: type[wire.Message] | None = None) -> list[Any]:
        with self.lock:
            out = [wire.decode_key(k, p) for k, p in self.sent]
        return [m for m in out if cls is None or isinstance(m, cls)]


class Rig:
    """Console + OperatorLink over memory transports + a fake robot voice."""

    def __init__(
        self,
        tmp_path: Path,
        read_only: bool = False,
        clock: Clock | None = None,
        repeat_timeout_s: float = 2.0,
        policy: LinkPolicy = CALM,
    ) -> None:
        self.clock = clock if clock is not None else SystemClock()
        self.zenoh = MemoryTransport("zenoh")
        self.mqtt = MemoryTransport("mqtt")
        self.link = OperatorLink(self.clock, ME, self.zenoh, self.mqtt, policy=policy, poll_hz=50.0)
        self.fleet = FleetModel(ME)
        self.lock = threading.Lock()
        attach(self.link, self.fleet, self.lock)
        self.marks_file = tmp_path / "marks.json"
        self.app = ConsoleApp(
            self.link, self.fleet, self.clock, lock=self.lock, read_only=read_only,
            marks_file=self.marks_file, repeat_timeout_s=repeat_timeout_s, planner=plan_round,
        )  # fmt: skip
        self.agents: dict[str, wire.HeaderCounter] = {}
        self.zenoh.responder = self.mqtt.responder = self._ack
        self.voices: dict[str, tuple[float, float]] = {}
        """Robots that keep talking (pose at 20 Hz) on ``self.up`` links, like a live agent."""
        self.unplaced: set[str] = set()
        """Robots whose voices say their position is unknown (no UWB: they map in their own frames)."""
        self.up: tuple[str, ...] = ("zenoh", "mqtt")
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._talk, daemon=True)

    def start(self) -> None:
        self.link.start()
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        self.link.close()

    def _ack(self, transport: MemoryTransport, key: str, payload: bytes) -> None:
        """Like an agent: ack every order, instant action and teleop on the link it came on (an
        unacked teleop counts as lost: after 2 s of them the console fails over to MQTT)."""
        msg = wire.decode_key(key, payload)
        if not isinstance(msg, Order | InstantActions | Teleop):
            return
        fields = {
            "commandTopic": msg.TOPIC, "commandSender": msg.header.sender, "commandHeaderId": msg.header.headerId,
            "orderId": None, "orderUpdateId": None, "result": AckResult.ACCEPTED, "reason": "",
            "link": LinkName(transport.name),
        }  # fmt: skip
        transport.inject(self.counter(msg.header.robot).make(Ack, **fields))

    def _talk(self) -> None:
        while not self._stop.wait(0.05):
            for robot, (x, y) in list(self.voices.items()):
                self.pose(robot, x, y, links=self.up, sd_m=UNKNOWN_SD_M if robot in self.unplaced else 0.05)

    def counter(self, robot: str) -> wire.HeaderCounter:
        if robot not in self.agents:
            self.agents[robot] = wire.HeaderCounter(self.clock, robot=robot, sender=f"agent-{robot}")
        return self.agents[robot]

    async def last_order(self, pilot: Any) -> Order:
        """The last Order sent, on whichever link carried it (on a loaded machine the link manager
        may have moved commands to MQTT), waiting up to 2.5 s for one."""
        for _ in range(50):
            if self.zenoh.messages(Order) or self.mqtt.messages(Order):
                break
            await pilot.pause(0.05)
        found: list[Order] = self.zenoh.messages(Order) + self.mqtt.messages(Order)
        assert found, "no Order on either link"
        return found[-1]

    def pose(
        self,
        robot: str,
        x: float,
        y: float,
        theta: float = 0.0,
        links: tuple[str, ...] = ("zenoh", "mqtt"),
        sd_m: float = 0.05,
    ) -> None:
        msg = self.counter(robot).make(
            Pose, x=x, y=y, theta=theta, sd_x_m=sd_m, sd_y_m=sd_m, sd_theta_rad=0.01, odom_x=x, odom_y=y,
            odom_theta=theta, vx=0.0, omega=0.0, uwbStale=False,
        )  # fmt: skip
        for link in links:
            (self.zenoh if link == "zenoh" else self.mqtt).inject(msg)


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[Rig]:
    """A started console rig (``Rig``), closed at teardown."""
    r = Rig(tmp_path)
    r.start()
    try:
        yield r
    finally:
        r.close()
