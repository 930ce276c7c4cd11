"""Drill: goals at the edge of what a float holds, sent over each real link to a running agent.

A foreign sender (raw msgpack, not our encoder) orders the robot to x = y = 1e308, -1e308 and
1e-308 over Zenoh and over MQTT. The first two lie beyond the wire contract's extent
(``MAX_COORDINATE_M``): refused at decode, counted, never acknowledged as accepted, and the agent
goes on serving. 1e-308 is a valid goal where the robot already stands: accepted, and reached
only because it is reached. (Issue 14: the planner used to raise OverflowError inside the input
handler, and the pilot then reported a false "goal_reached (0.0 cm off)".)
"""

from __future__ import annotations

import math

import msgpack

from fleetlink.shared import wire
from fleetlink.shared.messages import AckResult, Goal, Order, Teleop
from tests.harness import MosquittoBroker, wait_until
from tests.test_agent_links import make_rig


def _order_bytes(counter: wire.HeaderCounter, order_id: str, x: float, y: float) -> tuple[int, bytes]:
    msg = counter.make(Order, orderId=order_id, orderUpdateId=0, goal=Goal(x=0.0, y=0.0, theta=None), returnHome=False)
    body = msgpack.unpackb(wire.encode(msg), raw=False)
    body["goal"]["x"], body["goal"]["y"] = x, y
    return msg.header.headerId, msgpack.packb(body, use_bin_type=True)


def test_extreme_goals_over_both_links(mosquitto: MosquittoBroker) -> None:
    with make_rig(mosquitto) as rig:
        op, core = rig.op, rig.agent.core
        for link in ("zenoh", "mqtt"):
            only = {"zenoh_": link == "zenoh", "mqtt_": link == "mqtt"}
            rejected = core.gate.stats.rejected_total
            sent = []
            for i, v in enumerate((1e308, -1e308)):
                hid, data = _order_bytes(op.counter, f"{link}-huge-{i}", v, v)
                op.send_raw("order", data, **only)
                sent.append(hid)
            wait_until(lambda r=rejected: core.gate.stats.rejected_total >= r + 2, message=f"{link}: both refused")
            assert "out of range" in core.gate.stats.last_reason
            # Still serving on that link: a valid teleop is accepted and acked.
            t = op.counter.make(Teleop, v=0.0, omega=0.0, ttl_s=0.5)
            op.send(t, **only)
            wait_until(lambda t=t: op.acks_for(t.header.headerId, "teleop"), message=f"{link}: a teleop acked")
            assert op.acks_for(t.header.headerId, "teleop")[0][1].result is AckResult.ACCEPTED
            assert not any(op.acks_for(h, "order") for h in sent)  # nothing acknowledged for them

            hid, data = _order_bytes(op.counter, f"{link}-tiny", 1e-308, 1e-308)
            op.send_raw("order", data, **only)
            wait_until(lambda h=hid: op.acks_for(h, "order"), message=f"{link}: the tiny goal acked")
            assert op.acks_for(hid, "order")[0][1].result is AckResult.ACCEPTED
        assert core.handler_failures == 0
        with op.lock:
            reached = [e for _, e in op.events if e.kind == "goal_reached"]
            pose = op.poses[-1][1] if op.poses else None
        for e in reached:  # a real success: the robot stands at the goal (0, 0 give or take)
            assert pose is not None and math.hypot(pose.x, pose.y) < 0.05, (e.text, pose)
