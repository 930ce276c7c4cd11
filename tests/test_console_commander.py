"""The console's outgoing messages (operator/commander.py), on a recording source."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import pytest

from fleetlink.operator.commander import LEASE_S, TELEOP_TTL_S, Commander
from fleetlink.operator.teleop import Twist
from fleetlink.shared import wire
from fleetlink.shared.clock import SimClock
from fleetlink.shared.messages import ActionType, InstantActions, LeaseRequest, Mark, Order, Teleop


class Recorder:
    sender = "op-1"

    def __init__(self, *, counter: bool = True) -> None:
        self.clock = SimClock(start=10.0, epoch=1699999990.25)  # wall 1700000000.25
        if counter:
            self.counter = wire.HeaderCounter(self.clock, robot="operator", sender=self.sender)
        self.sent: list[tuple[type[wire.Message], str, bool, dict[str, Any]]] = []
        self.published: list[tuple[wire.Message, tuple[str, ...]]] = []

    def send(self, cls: type[wire.Message], robot: str, *, expect_ack: bool = True, **fields: Any) -> wire.Message:
        self.sent.append((cls, robot, expect_ack, fields))
        msg = cls(header=wire.HeaderCounter(self.clock, robot=robot, sender=self.sender).header(cls.TOPIC), **fields)
        wire.encode(msg)  # what would go on the wire is valid
        return msg

    def publish(self, msg: wire.Message, *, links: Sequence[str] = ("zenoh",)) -> None:
        wire.encode(msg)
        self.published.append((msg, tuple(links)))


def commander(**kw: Any) -> tuple[Commander, Recorder]:
    source = Recorder(**kw)
    return Commander(source, source.clock), source  # type: ignore[arg-type]


def test_teleop_goes_once_unacked_with_the_deadman() -> None:
    c, s = commander()
    c.teleop("r1", Twist(0.3, -1.0))
    assert s.sent == [(Teleop, "r1", False, {"v": 0.3, "omega": -1.0, "ttl_s": TELEOP_TTL_S})]


def test_goal_and_home_are_orders_with_the_operator_and_time_in_their_id() -> None:
    c, s = commander()
    order_id = c.goal("r1", 1.5, 2.0, 0.5)
    assert order_id == "op-1-1700000000.250"
    cls, robot, acked, f = s.sent[-1]
    assert (cls, robot, acked, f["orderId"], f["returnHome"]) == (Order, "r1", True, order_id, False)
    assert (f["goal"].x, f["goal"].y, f["goal"].theta) == (1.5, 2.0, 0.5)
    c.home("r2")
    cls, robot, acked, f = s.sent[-1]
    assert (cls, robot, f["orderId"], f["goal"], f["returnHome"]) == (
        Order,
        "r2",
        "op-1-home-1700000000.250",
        None,
        True,
    )


def test_order_ids_fit_the_wire() -> None:
    c, s = commander()
    s.sender = "o" * 60
    assert len(c.goal("r1", 0.0, 0.0)) > 64
    assert len(s.sent[-1][3]["orderId"]) == 64


@pytest.mark.parametrize("on", [True, False])
def test_payload_and_stop_are_acked_instant_actions(on: bool) -> None:
    c, s = commander()
    c.payload("r1", on)
    c.stop("r1")
    (cls1, _, acked1, f1), (cls2, _, acked2, f2) = s.sent
    assert cls1 is cls2 is InstantActions and acked1 and acked2
    p = f1["actions"][0]
    params = {kv.key: kv.value for kv in p.actionParameters}
    assert p.actionType is ActionType.PAYLOAD and params == {"device": "uv", "on": "true" if on else "false"}
    assert f2["actions"][0].actionType is ActionType.STOP


def test_lease_requests_go_on_both_links() -> None:
    c, s = commander()
    c.lease("r1")
    c.lease("r1", release=True)
    (take, links1), (release, links2) = s.published
    assert isinstance(take, LeaseRequest) and isinstance(release, LeaseRequest)
    assert (take.duration_s, take.release, release.duration_s, release.release) == (LEASE_S, False, 0.0, True)
    assert links1 == links2 == ("zenoh", "mqtt")
    assert take.header.robot == "r1" and take.header.sender == "op-1"
    assert release.header.headerId > take.header.headerId  # the source's counter: ids never repeat


def test_headers_without_a_source_counter_come_from_one_of_its_own() -> None:
    c, _ = commander(counter=False)
    a, b = c.header(Mark.TOPIC, "r1"), c.header(Mark.TOPIC, "r1")
    other = c.header(LeaseRequest.TOPIC, "r2")
    assert (a.sender, a.robot, other.robot, other.sender) == ("op-1", "r1", "r2", "op-1")
    assert b.headerId == a.headerId + 1  # one counter kept across calls: ids never repeat
