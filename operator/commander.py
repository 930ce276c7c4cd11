"""The console's outgoing messages, built and handed to the source (``OperatorLink``).

The app decides whether a command may go (read-only, a robot selected, the lease) and tells the
operator; ``Commander`` only builds each message the same way every time and sends it: drive
commands once (a newer one supersedes them), orders and instant actions acked and re-sent by the
link manager (rounds too: orders with nodes), lease requests on both links.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from fleetlink.operator.feed import ConsoleSource
from fleetlink.operator.teleop import Twist
from fleetlink.shared import wire
from fleetlink.shared.clock import Clock
from fleetlink.shared.messages import (
    Action,
    ActionType,
    Goal,
    InstantActions,
    KeyValue,
    LeaseRequest,
    Order,
    Teleop,
)

__all__ = ["LEASE_S", "TELEOP_TTL_S", "Commander"]

TELEOP_TTL_S = 0.5
"""The robot stops by itself if no newer drive command comes within this (its deadman)."""
LEASE_S = 60.0
"""How long a requested control lease lasts; renewed every third of it (fleet.LeaseRenewal)."""
MAX_ORDER_ID = 64


class Commander:
    def __init__(self, source: ConsoleSource, clock: Clock) -> None:
        self.source = source
        self.clock = clock
        self._counter: wire.HeaderCounter | None = None

    def teleop(self, robot: str, twist: Twist) -> None:
        self.source.send(Teleop, robot, expect_ack=False, v=twist.v, omega=twist.omega, ttl_s=TELEOP_TTL_S)

    def stop(self, robot: str) -> None:
        """A stop instant action (acked, re-sent on failover)."""
        action = Action(actionId="stop-all", actionType=ActionType.STOP, actionParameters=())
        self.source.send(InstantActions, robot, actions=(action,))

    def goal(self, robot: str, x: float, y: float, theta: float | None = None) -> str:
        """An order to go to (x, y) [facing theta]; returns its order id as shown to the operator."""
        order_id = f"{self.source.sender}-{self.clock.wall():.3f}"
        goal = Goal(x=x, y=y, theta=theta)
        self.source.send(Order, robot, orderId=order_id[:MAX_ORDER_ID], orderUpdateId=0, goal=goal, returnHome=False)
        return order_id

    def order(self, robot: str, fields: Mapping[str, Any]) -> str:
        """An order with nodes (a round: operator/rounds.py, ``RobotRound.order``): the Order's
        fields as the planner gives them; acked and re-sent as goals are. Returns its order id."""
        self.source.send(Order, robot, **fields)
        return str(fields["orderId"])

    def home(self, robot: str) -> None:
        order_id = f"{self.source.sender}-home-{self.clock.wall():.3f}"
        self.source.send(Order, robot, orderId=order_id[:MAX_ORDER_ID], orderUpdateId=0, goal=None, returnHome=True)

    def action(self, robot: str, kind: ActionType, **params: str) -> None:
        """One instant action (acked, re-sent on failover); parameters as VDA 5050 key/values."""
        action = Action(
            actionId=f"{kind.value}-{self.clock.wall():.3f}"[:64],
            actionType=kind,
            actionParameters=tuple(KeyValue(key=k, value=v) for k, v in params.items()),
        )
        self.source.send(InstantActions, robot, actions=(action,))

    def estop(self, robot: str) -> None:
        """Latch the robot's e-stop: nothing moves until an authorised release."""
        self.action(robot, ActionType.ESTOP)

    def estop_release(self, robot: str) -> None:
        self.action(robot, ActionType.ESTOP_RELEASE)

    def set_home(self, robot: str, at: tuple[float, float] | None = None) -> None:
        """The robot's home here (None: where it stands) or at (x, y) m."""
        if at is None:
            self.action(robot, ActionType.SET_HOME)
        else:
            self.action(robot, ActionType.SET_HOME, x=repr(at[0]), y=repr(at[1]))

    def comms_policy(self, robot: str, policy: str) -> None:
        self.action(robot, ActionType.SET_COMMS_POLICY, policy=policy)

    def payload(self, robot: str, on: bool, device: str = "uv", level: int | None = None) -> None:
        """A payload instant action: the lamp (``uv``), the ``atomiser`` or the ``fan`` on or off,
        the last two at a level 0-3."""
        params = {"device": device, "on": "true" if on else "false"}
        if level is not None:
            params["level"] = str(level)
        self.action(robot, ActionType.PAYLOAD, **params)

    def lease(self, robot: str, *, release: bool = False) -> None:
        """Request (or renew) the robot's control lease for ``LEASE_S``, or release it; on both
        links, since the lease decides who may command the robot on either."""
        request = LeaseRequest(
            header=self.header(LeaseRequest.TOPIC, robot), duration_s=0.0 if release else LEASE_S, release=release
        )
        self.source.publish(request, links=("zenoh", "mqtt"))

    def header(self, topic: str, robot: str) -> wire.Header:
        """A header for a message published as is (lease requests, marks): from the source's own
        counter when it has one, so header ids never repeat across the two."""
        counter: wire.HeaderCounter | None = getattr(self.source, "counter", None)
        if counter is None:
            if self._counter is None:
                self._counter = wire.HeaderCounter(self.clock, robot=robot, sender=self.source.sender)
            counter = self._counter
        return counter.header(topic, robot=robot)
