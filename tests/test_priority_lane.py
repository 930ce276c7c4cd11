"""The lease holder's priority lane (issue 14): samples on prioritised keys are handed on before
anything else waiting, so a flood queues behind the holder's commands, never in front of them.
The key names the sender (identity from the transport), so the lane needs no decoding."""

from __future__ import annotations

import threading

from fleetlink.links.zenoh import PRIORITY_INBOX_SIZE, ZenohEndpoint, _Inbox
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import SystemClock
from fleetlink.shared.messages import LeaseRequest
from tests.harness import wait_until
from tests.harness.zenoh_peers import loopback_endpoint
from tests.test_agent_links import Rig, rig  # noqa: F401  (the fixture)


def _noop(_key: str, _payload: bytes) -> None:
    pass


def test_the_priority_lane_is_served_first_and_bounded_apart() -> None:
    inbox = _Inbox(size=3)
    for i in range(3):
        assert inbox.put((_noop, f"flood/{i}", b""))
    assert not inbox.put((_noop, "flood/3", b""))  # the ordinary lane is full...
    assert inbox.put((_noop, "holder/0", b""), lane=0)  # ...the holder's is not
    assert inbox.put((_noop, "holder/1", b""), lane=0)
    got = [item[1] for item in (inbox.get(), inbox.get(), inbox.get()) if item is not None]
    assert got == ["holder/0", "holder/1", "flood/0"]  # in order within each lane
    for _ in range(PRIORITY_INBOX_SIZE):
        assert inbox.put((_noop, "holder", b""), lane=0)
    assert not inbox.put((_noop, "holder", b""), lane=0)


def test_the_second_lane_comes_after_the_holder_and_before_the_rest() -> None:
    inbox = _Inbox(size=8)
    assert inbox.put((_noop, "teleop/op-bob", b""))
    assert inbox.put((_noop, "actions/op-carol", b""), lane=1)
    assert inbox.put((_noop, "teleop/op-alice", b""), lane=0)
    got = [item[1] for item in (inbox.get(), inbox.get(), inbox.get()) if item is not None]
    assert got == ["teleop/op-alice", "actions/op-carol", "teleop/op-bob"]
    endpoint = ZenohEndpoint()
    endpoint.prioritise(frozenset({keys.sender_key("r1", "teleop", "op-alice")}), then_topics=frozenset({"actions"}))
    assert endpoint._lane(keys.sender_key("r1", "teleop", "op-alice")) == 0
    assert endpoint._lane(keys.sender_key("r1", "actions", "op-carol")) == 1  # anyone's stop
    assert endpoint._lane(keys.sender_key("r1", "teleop", "op-bob")) == 2


def test_a_prioritised_key_overtakes_a_backlog_on_a_real_session() -> None:
    endpoint = loopback_endpoint()
    receiver_side, sender_side = ZenohEndpoint(listen=[endpoint]), ZenohEndpoint(connect=[endpoint])
    flood_key, holder_key = keys.sender_key("r1", "teleop", "op-bob"), keys.sender_key("r1", "teleop", "op-alice")
    release = threading.Event()
    got: list[tuple[str, bytes]] = []

    def receive(key: str, payload: bytes) -> None:
        if payload == b"probe":
            got.append((key, payload))
            return
        release.wait(10)  # a busy receiver: the rest of the backlog waits in the inbox
        got.append((key, payload))

    receiver_side.subscribe(keys.sender_filter("r1", "teleop"), receive)
    receiver_side.prioritise(frozenset({holder_key}))
    try:
        receiver_side.start()
        sender_side.start()
        wait_until(
            lambda: sender_side.publish(flood_key, b"probe") and (flood_key, b"probe") in got,
            interval=0.05,
            message="the subscription in place",
        )
        wait_until(lambda: len(got) == receiver_side.stats.received, message="the probes delivered")
        base = receiver_side.stats.received
        for i in range(50):
            sender_side.publish(flood_key, f"flood-{i}".encode())
        wait_until(lambda: receiver_side.stats.received >= base + 50, message="the backlog queued")
        sender_side.publish(holder_key, b"holder")
        wait_until(lambda: len(receiver_side._inbox._lanes[0]) == 1, message="the holder's sample in its lane")
        release.set()
        wait_until(lambda: len(got) >= base + 51, message="everything delivered")
        order = [p for _, p in got if p != b"probe"]
        # flood-0 was in the receiver when the holder's came; the holder's is next.
        assert order[:2] == [b"flood-0", b"holder"], order[:5]
        assert order[2:] == [f"flood-{i}".encode() for i in range(1, 50)]
    finally:
        release.set()
        sender_side.close()
        receiver_side.close()


def test_the_agent_prioritises_its_lease_holder(rig: Rig) -> None:  # noqa: F811
    zenoh_link = rig.agent.zenoh
    assert zenoh_link is not None and zenoh_link._priority == frozenset()
    wait_until(lambda: zenoh_link._second == frozenset({"actions"}), message="anyone's stops in the second lane")
    holder = wire.HeaderCounter(SystemClock(), robot="r1", sender="operator-1")
    take = holder.make(LeaseRequest, duration_s=30.0, release=False)
    rig.op.send(take, mqtt_=False)
    expected = frozenset(
        keys.sender_key("r1", t, "operator-1") for t in ("order", "actions", "teleop", "lease/request")
    )
    wait_until(lambda: zenoh_link._priority == expected, message="the holder's keys in the priority lane")
    free = holder.make(LeaseRequest, duration_s=0.0, release=True)
    rig.op.send(free, mqtt_=False)
    wait_until(lambda: zenoh_link._priority == frozenset(), message="the lane emptied on release")
