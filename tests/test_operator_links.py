"""The operator's links against real parts: Zenoh peers on loopback and a private Mosquitto.

The robot here is the agent's real command gate (agent/links/gate.py: decode, dedupe, ack on the
link a command came from) behind a real Zenoh session and a real MQTT client, publishing its pose
at 20 Hz on both links. Cutting the primary closes the robot's Zenoh session: nothing more of it
reaches the operator over Zenoh, exactly like a dead radio.
"""

from __future__ import annotations

import time
from typing import Any

import paho.mqtt.client as mqtt
import pytest

from fleetlink.operator.linkmanager import FALLBACK, PRIMARY, LinkPolicy, Switch
from fleetlink.shared import keys
from fleetlink.shared.clock import SystemClock
from fleetlink.shared.messages import Order
from tests.harness import wait_until
from tests.harness.link_robot import LinkRobot, goal, open_operator

POLICY = LinkPolicy(state_window_s=0.35, ack_timeout_s=0.25, holdoff_s=0.6)


@pytest.fixture
def pair(mosquitto: Any) -> Any:
    op, endpoint = open_operator(mosquitto.port, POLICY)
    robot = LinkRobot("r1", endpoint, mosquitto.port, SystemClock())
    try:
        wait_until(
            lambda: op.health("r1")[0].age_s is not None and op.health("r1")[1].age_s is not None,
            message="poses from r1 on both links",
        )
        yield op, robot
    finally:
        robot.close()
        op.close()


def test_commands_use_zenoh_while_healthy(pair: Any) -> None:
    op, robot = pair
    for i in range(5):
        op.send(Order, "r1", **goal(i))
    wait_until(lambda: len(robot.executed) == 5 and op.pending("r1") == 0, message="5 goals executed and acked")
    assert {e.link for e in robot.executed} == {"zenoh"}
    assert op.active("r1") == PRIMARY
    zenoh_health = op.health("r1")[0]
    assert zenoh_health.healthy and zenoh_health.rtt_s is not None


def test_cut_primary_fails_over_without_loss_or_duplicates_and_fails_back(pair: Any) -> None:
    op, robot = pair
    switches: list[Switch] = []
    op.add_listener(lambda a: switches.append(a) if isinstance(a, Switch) else None)
    sent = 0
    for _ in range(5):
        op.send(Order, "r1", **goal(sent))
        sent += 1
        time.sleep(0.05)
    wait_until(lambda: op.pending("r1") == 0, message="acks before the cut")
    robot.cut_primary()
    cut_at = time.monotonic()
    # Keep commanding through the cut: every goal must run exactly once.
    while time.monotonic() - cut_at < 1.0:
        op.send(Order, "r1", **goal(sent))
        sent += 1
        time.sleep(0.05)
    wait_until(lambda: op.pending("r1") == 0, message="every goal acked after the cut")
    assert op.active("r1") == FALLBACK
    assert switches and switches[0].to_link == FALLBACK
    first_fallback = min(e.at for e in robot.executed if e.link == "mqtt")
    print(f"failover: first command over MQTT {1000 * (first_fallback - cut_at):.0f} ms after the cut")
    orders = [e.order for e in robot.executed if e.topic == "order"]
    assert sorted(orders) == sorted((f"goal-{i}", 0) for i in range(sent)), "lost or duplicated goals"
    assert len(orders) == len(set(orders)) == sent
    # The primary comes back: after the hold-off commands return to Zenoh.
    robot.open_primary()
    wait_until(lambda: op.active("r1") == PRIMARY, timeout=10.0, message="fail-back to zenoh")
    assert switches[-1].to_link == PRIMARY

    # The robot's fresh session may not have declared its subscriptions to the console yet: a goal
    # sent before that is acked over MQTT after the ack timeout. Goals go back to Zenoh soon.
    def goal_over_zenoh() -> bool:
        nonlocal sent
        before = len(robot.executed)
        op.send(Order, "r1", **goal(sent))
        sent += 1
        wait_until(lambda: len(robot.executed) == before + 1, message="goal after fail-back")
        return robot.executed[-1].link == "zenoh"

    wait_until(goal_over_zenoh, timeout=10.0, message="a goal over zenoh after fail-back")


def test_garbage_is_counted_and_logged_once(pair: Any, mosquitto: Any, caplog: Any) -> None:
    op, robot = pair
    client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id="vandal")
    client.connect("127.0.0.1", mosquitto.port)
    client.loop_start()
    try:
        for _ in range(5):
            client.publish(keys.key("r1", "pose"), b"\xc1garbage", qos=1).wait_for_publish(2)
            client.publish("fleetlink/v1/r1/nosuchtopic", b"\x80", qos=1).wait_for_publish(2)
        wait_until(lambda: sum(op.rejected.values()) >= 10, message="10 rejections")
    finally:
        client.disconnect()
        client.loop_stop()
    assert len(op.rejected) == 2
    assert len([r for r in caplog.records if "rejected a message" in r.getMessage()]) == 2
    # Still serving.
    op.send(Order, "r1", **goal(99))
    wait_until(lambda: any(e.order == ("goal-99", 0) for e in robot.executed), message="goal after garbage")
