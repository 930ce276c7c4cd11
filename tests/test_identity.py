"""Identity from the transport (issue 14): what people publish is keyed by their login.

A command's key is ``fleetlink/v1/<robot>/<topic>/<sender>``; the ACLs let each login write only
under its own name (tests/test_deploy.py shows the real broker and router enforcing it;
tests/faults/test_identity_drills.py the whole site); the decoder refuses a header that claims
another sender, or a command key without one. These are the pure parts.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from fleetlink.agent.links.gate import CommandGate, Rejected
from fleetlink.cli.main import build_parser
from fleetlink.shared import keys, wire
from fleetlink.shared.access import mosquitto_acl, zenoh_access_control
from fleetlink.shared.clock import SimClock
from fleetlink.shared.messages import (
    Action,
    ActionType,
    Goal,
    InstantActions,
    LeaseRequest,
    LinkName,
    Mark,
    Order,
    Teleop,
)

CLOCK = SimClock()
ALICE = wire.HeaderCounter(CLOCK, robot="r1", sender="op-alice")


def _commands(counter: wire.HeaderCounter) -> list[wire.Message]:
    stop = Action(actionId="s", actionType=ActionType.STOP, actionParameters=())
    return [
        counter.make(Teleop, v=0.1, omega=0.0, ttl_s=0.5),
        counter.make(Order, orderId="o1", orderUpdateId=0, goal=Goal(x=1.0, y=2.0, theta=None), returnHome=False),
        counter.make(InstantActions, actions=(stop,)),
        counter.make(LeaseRequest, duration_s=60.0, release=False),
        counter.make(Mark, markId="m1", x=1.0, y=1.0, label="door", kind="note", sd_m=0.0, removed=False),
    ]


def test_keys_of_what_people_publish_end_in_the_sender() -> None:
    assert keys.sender_key("r1", "lease/request", "op-alice") == "fleetlink/v1/r1/lease/request/op-alice"
    assert keys.split_sender("lease/request/op-alice") == ("lease/request", "op-alice")
    assert keys.split_sender("lease/request") == ("lease/request", None)  # the lease/request topic itself
    assert keys.split_sender("map/updates") == ("map/updates", None)
    assert keys.split_sender("teleop") == ("teleop", None)
    assert keys.topic_of("fleetlink/v1/r1/teleop/op-a") == "teleop"
    assert keys.topic_of("fleetlink/v1/r1/map/updates") == "map/updates"
    assert keys.topic_of("dwm/node/1/uplink/location") == ""
    assert keys.sender_filter("r1", "teleop") == "fleetlink/v1/r1/teleop/*"
    assert keys.sender_filter("*", "marks", "op-a") == "fleetlink/v1/*/marks/op-a"
    with pytest.raises(ValueError, match="not published under its sender"):
        keys.sender_key("r1", "state", "op-a")
    with pytest.raises(ValueError, match="sender id"):
        keys.sender_key("r1", "teleop", "op/a")


@pytest.mark.parametrize("msg", _commands(ALICE), ids=lambda m: m.TOPIC)
def test_decode_checks_the_sender_against_the_key(msg: wire.Message) -> None:
    data = wire.encode(msg)
    assert wire.key_of(msg) == f"fleetlink/v1/r1/{msg.TOPIC}/op-alice"
    assert wire.decode_key(wire.key_of(msg), data) == msg
    with pytest.raises(wire.WireError, match="does not match the key's sender 'op-bob'") as bob:
        wire.decode_key(keys.sender_key("r1", msg.TOPIC, "op-bob"), data)
    assert bob.value.field == "header.sender"
    with pytest.raises(wire.WireError, match="must be published on fleetlink/v1/<robot>/") as nameless:
        wire.decode_key(keys.key("r1", msg.TOPIC), data)
    assert nameless.value.field == "key"


def test_telemetry_keys_carry_no_sender() -> None:
    from fleetlink.shared.messages import Lease

    lease = wire.HeaderCounter(CLOCK, robot="r1", sender="agent-r1").make(Lease, holder="op-alice", until=1.0)
    assert wire.key_of(lease) == "fleetlink/v1/r1/lease"
    assert wire.decode_key("fleetlink/v1/r1/lease", wire.encode(lease)) == lease


def test_the_gate_refuses_a_claimed_sender_and_logs_it_even_after_garbage() -> None:
    gate = CommandGate("r1")
    garbage = gate.receive(LinkName.MQTT, keys.sender_key("r1", "teleop", "op-bob"), b"\xc1", 0.0)
    assert isinstance(garbage, Rejected) and garbage.log
    forged = ALICE.make(Teleop, v=0.5, omega=0.0, ttl_s=5.0)
    verdicts = [
        gate.receive(LinkName.MQTT, keys.sender_key("r1", "teleop", "op-bob"), wire.encode(forged), 0.1)
        for _ in range(3)
    ]
    assert all(isinstance(v, Rejected) for v in verdicts)
    first, *rest = verdicts
    assert isinstance(first, Rejected) and first.log and first.topic == "teleop"
    assert "'op-alice' does not match the key's sender 'op-bob'" in first.reason
    assert not any(v.log for v in rest if isinstance(v, Rejected))  # once, not per attempt
    assert gate.stats.rejected[("mqtt", "teleop")] == 4


def test_acls_let_each_operator_write_only_under_its_own_name() -> None:
    acl = mosquitto_acl(["op-alice", "op-bob"])
    alice_block = acl.split("user op-alice\n")[1].split("user op-bob\n")[0]
    writes = re.findall(r"^topic write (\S+)$", alice_block, flags=re.M)
    assert writes and all(w.endswith("/op-alice") for w in writes), writes
    assert "pattern read fleetlink/v1/%u/teleop/+" in acl
    ac = zenoh_access_control(["r1"], ["op-alice", "op-bob"])
    rules = {r["id"]: r for r in ac["rules"]}
    for op in ("op-alice", "op-bob"):
        assert all(k.endswith(f"/{op}") for k in rules[f"{op}-commands"]["key_exprs"])
        policy = next(p for p in ac["policies"] if p["subjects"] == [f"operator-{op}"])
        assert f"{op}-commands" in policy["rules"] and "operator-watch" in policy["rules"]
        other = "op-bob" if op == "op-alice" else "op-alice"
        assert f"{other}-commands" not in policy["rules"]
    assert rules["r1-commands-in"]["key_exprs"][:3] == [
        "fleetlink/v1/r1/order/*",
        "fleetlink/v1/r1/actions/*",
        "fleetlink/v1/r1/teleop/*",
    ]
    # The fleet map is shared under the id "fleet": no robot may log in as it.
    with pytest.raises(ValueError, match="fleet map"):
        zenoh_access_control(["fleet"], ["op-alice"])


def test_a_console_logged_in_sends_as_its_login(tmp_path: Path) -> None:
    from fleetlink.cli.console import load_settings

    pw = tmp_path / "pw"
    pw.write_text("secret\n")
    parser = build_parser()
    args = parser.parse_args(["console", "--user", "op-alice", "--password-file", str(pw)])
    assert load_settings(args).operator == "op-alice"
    args = parser.parse_args(["console", "--user", "op-alice", "--password-file", str(pw), "--operator", "op-bob"])
    with pytest.raises(ValueError, match="differs from the login"):
        load_settings(args)
