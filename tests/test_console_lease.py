"""The robot-side control lease (agent/lease.py) and the console's reading of it (fleet.may_drive)."""

from __future__ import annotations

from fleetlink.agent.lease import LeaseKeeper
from fleetlink.operator.fleet import FleetModel
from fleetlink.shared import wire
from fleetlink.shared.clock import SimClock
from fleetlink.shared.messages import Lease


def test_first_requester_gets_it_others_are_refused_until_expiry() -> None:
    k = LeaseKeeper(max_duration_s=60)
    assert k.request("op1", 30, False, now=0.0, wall=1000.0) == (True, "")
    assert k.view(1.0).holder == "op1" and k.view(1.0).until_wall == 1030.0
    ok, reason = k.request("op2", 30, False, now=5.0, wall=1005.0)
    assert not ok and "held by op1" in reason
    assert k.allows("op1", 10.0) and not k.allows("op2", 10.0)
    assert "leased to op1" in k.refusal("op2", 10.0)
    # Renewal by the holder, capped at the maximum.
    assert k.request("op1", 999, False, now=20.0, wall=1020.0)[0]
    assert k.view(21.0).until_wall == 1080.0
    # Expiry frees it.
    assert not k.allows("op1", 80.0)
    assert k.view(80.0).holder == ""
    assert k.request("op2", 10, False, now=81.0, wall=1081.0)[0]


def test_only_the_holder_releases() -> None:
    k = LeaseKeeper()
    k.request("op1", 30, False, now=0.0, wall=0.0)
    ok, reason = k.request("op2", 0, True, now=1.0, wall=1.0)
    assert not ok and "op1 does" in reason
    assert k.request("op1", 0, True, now=2.0, wall=2.0) == (True, "")
    assert not k.allows("op1", 3.0)
    assert "take the lease first" in k.refusal("op1", 3.0)


def test_driving_claims_a_free_lease_renews_it_and_never_shortens_a_longer_one() -> None:
    k = LeaseKeeper(max_duration_s=300)
    assert k.claim("op1", 15, now=0.0, wall=100.0)
    assert k.view(1.0).holder == "op1" and k.view(1.0).until_wall == 115.0
    assert not k.claim("op2", 15, now=5.0, wall=105.0)  # op1 is driving
    assert k.claim("op1", 15, now=10.0, wall=110.0) and k.view(10.0).until_wall == 125.0  # renewed
    assert k.view(26.0).holder == ""  # runs out 15 s after the last command
    assert k.claim("op2", 15, now=26.0, wall=126.0)
    # An explicit 120 s lease is not cut to 15 s by driving.
    k2 = LeaseKeeper()
    k2.request("op1", 120, False, now=0.0, wall=0.0)
    assert k2.claim("op1", 15, now=1.0, wall=1.0) and k2.view(1.0).until_wall == 120.0


def test_console_reads_leases_from_the_robot() -> None:
    clock = SimClock()
    fleet = FleetModel("op1")
    agent = wire.HeaderCounter(clock, robot="r1", sender="agent-r1")
    assert fleet.may_drive("r1") == (True, "")  # never announced: an agent without leases
    fleet.apply(agent.make(Lease, holder="", until=0.0), "zenoh", 0.0)
    assert fleet.may_drive("r1") == (True, "")  # free: anyone may drive, as the agent decides
    fleet.apply(agent.make(Lease, holder="op2", until=100.0), "zenoh", 0.1)
    ok, reason = fleet.may_drive("r1")
    assert not ok and "held by op2" in reason
    fleet.apply(agent.make(Lease, holder="op1", until=100.0), "mqtt", 0.2)
    assert fleet.may_drive("r1") == (True, "")
    assert any("held by op1" in n.text for n in fleet.drain())
