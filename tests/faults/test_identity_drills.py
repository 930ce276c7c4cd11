"""Drill: op-bob claims to be op-alice on a secured site (issue 14, defect 6).

Before, a command's sender was whatever its ``header.sender`` said: with ``sender = op-alice``,
op-bob drove under alice's lease on both links, released it, took it, and alice was refused. Now
a command's key ends in its sender's login (``fleetlink/v1/<robot>/<topic>/<login>``): the
broker's ACL and the router's access control let each login write only under its own name, and
the agent refuses a ``header.sender`` that differs from the key's.

The site is the field's own secured site (deploy/'s Mosquitto with a password file and ACL, the
Zenoh router with usrpwd and access control, TLS when openssl is there), with whole agents.
op-bob logs in with his own credentials and tries, on each link, both forgeries: alice's name in
the key (the transport drops it) and in the header only (the agent refuses it, with the reason
logged). Sentinels show the absence: op-bob's refused copy on his own key travels the same path
after his forged one, so once the agent has counted it, the forged one would have arrived.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Iterator
from typing import Any

import pytest
import zenoh

from fleetlink.links.mqtt import connect_client
from fleetlink.links.zenoh import peer_config
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import SystemClock
from fleetlink.shared.messages import Ack, AckResult, Lease, LeaseRequest, Teleop
from fleetlink.site.field import FieldSite, Security
from tests.harness import wait_until
from tests.test_field_realtime import quiet_scenario

# One worker runs this module under pytest-xdist, so its module-scoped set-up runs once.
pytestmark = pytest.mark.xdist_group("identity_drills")

ALICE, BOB, ROBOT = "op-alice", "op-bob", "uvc-1"


class Watch:
    """What alice's console hears: acks and the lease."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.acks: list[Ack] = []
        self.holder = ""

    def sink(self, msg: wire.Message, _link: str, _now: float) -> None:
        with self.lock:
            if isinstance(msg, Ack):
                self.acks.append(msg)
            elif isinstance(msg, Lease) and msg.header.robot == ROBOT:
                self.holder = msg.holder


@pytest.fixture(scope="module")
def site() -> Iterator[tuple[FieldSite, Any, Watch]]:
    scenario = quiet_scenario(robots=[{"name": ROBOT, "start": "living", "drive": "idle"}], lidar={"enabled": False})
    fs = FieldSite(scenario, clock=SystemClock(), security=Security((ALICE, BOB))).start()
    alice = None
    try:
        assert fs.agents is not None and fs.security is not None
        agent = fs.agents.agents[ROBOT]
        wait_until(
            lambda: agent.zenoh is not None and agent.zenoh.up and agent.mqtt is not None and agent.mqtt.up,
            timeout=15,
            message="the agent logged in on both links",
        )
        watch = Watch()
        alice = fs.operator_link(ALICE)
        alice.add_sink(watch.sink)
        alice.start()
        yield fs, alice, watch
    finally:
        if alice is not None:
            alice.close()
        fs.stop()


def _pose(fs: FieldSite) -> tuple[float, float, float]:
    return next(r.pose for r in fs.field.world.robots if r.name == ROBOT)  # type: ignore[union-attr]


def test_op_bob_claiming_op_alice_is_refused_on_both_links(
    site: tuple[FieldSite, Any, Watch], caplog: pytest.LogCaptureFixture
) -> None:
    fs, alice, watch = site
    assert fs.security is not None and fs.agents is not None
    agent = fs.agents.agents[ROBOT]
    gate = agent.core.gate
    caplog.set_level(logging.WARNING)

    # Alice takes the robot's lease, on both links, as her console does.
    def take() -> bool:
        request = LeaseRequest(
            header=alice.counter.header(LeaseRequest.TOPIC, robot=ROBOT), duration_s=300.0, release=False
        )
        alice.publish(request, links=("zenoh", "mqtt"))
        with watch.lock:
            return watch.holder == ALICE

    wait_until(take, interval=0.3, timeout=20, message="alice holding the lease")

    # Bob, logged in as himself on both links, writes as alice.
    clock = SystemClock()
    forger = wire.HeaderCounter(clock, robot=ROBOT, sender=ALICE)
    bob_z = zenoh.open(peer_config(**fs.security.zenoh_auth(BOB)))
    bob_m = connect_client(fs.security.mqtt_settings(BOB), client_id="op-bob-raw")
    start = _pose(fs)
    try:
        wait_until(bob_m.is_connected, message="bob's MQTT login")
        for link in ("zenoh", "mqtt"):
            before = gate.stats.rejected.get((link, "teleop"), 0)

            def put(key: str, msg: wire.Message, link: str = link) -> None:
                data = wire.encode(msg)
                if link == "zenoh":
                    bob_z.put(key, data)
                else:
                    bob_m.publish(key, data, qos=1).wait_for_publish(5)

            def forge(link: str = link, before: int = before) -> bool:
                drive = forger.make(Teleop, v=0.5, omega=0.0, ttl_s=5.0)
                release = forger.make(LeaseRequest, duration_s=0.0, release=True)
                put(wire.key_of(drive), drive)  # alice's key: the broker / router drops it
                put(wire.key_of(release), release)
                own = keys.sender_key(ROBOT, Teleop.TOPIC, BOB)
                put(own, drive)  # bob's own key, alice in the header: the agent refuses it
                return gate.stats.rejected.get((link, "teleop"), 0) > before

            wait_until(forge, interval=0.3, timeout=15, message=f"the agent refusing bob's claim on {link}")

            # The counter moves before the refusal's log line is written (another thread): wait for it.
            def logged(link: str = link) -> bool:
                return any(
                    f"on {link} topic teleop" in m and "'op-bob'" in m
                    for m in (r.getMessage() for r in list(caplog.records))
                )

            wait_until(logged, interval=0.1, timeout=10, message=f"the refusal on {link} logged with its reason")
        assert "does not match the key's sender 'op-bob'" in gate.stats.last_reason
        # Nothing bob sent as alice did anything: no move, the lease is still hers, and no ack
        # answered a teleop "from alice" (she has sent none).
        assert math.hypot(_pose(fs)[0] - start[0], _pose(fs)[1] - start[1]) < 0.01
        assert agent.core.lease.view(agent.clock.now()).holder == ALICE
        with watch.lock:
            assert not [a for a in watch.acks if a.commandTopic == Teleop.TOPIC and a.commandSender == ALICE]
    finally:
        bob_m.disconnect()
        bob_z.close()

    # Alice still drives.
    sent: list[int] = []

    def drive() -> bool:
        sent.append(alice.send(Teleop, ROBOT, expect_ack=False, v=0.2, omega=0.0, ttl_s=0.5).header.headerId)
        with watch.lock:
            acked = any(a.commandHeaderId in sent and a.result is AckResult.ACCEPTED for a in watch.acks)
        return acked and math.hypot(_pose(fs)[0] - start[0], _pose(fs)[1] - start[1]) > 0.05

    wait_until(drive, interval=0.1, timeout=15, message="alice driving after bob's attempts")
