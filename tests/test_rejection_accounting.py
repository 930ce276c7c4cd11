"""Rejections are counted without bound and remembered within one (issue 14), and the board's
loss and return are events.

A sender chooses the text of a rejection (an unknown field's name, a garbage payload): varying it
must not make every rejection a "first" one (logged and published as an event each), nor grow
the memory that remembers which ones were seen.
"""

from __future__ import annotations

import logging

import msgpack
import pytest

from fleetlink.agent.core import AgentCore, BoardView
from fleetlink.agent.links.gate import MAX_LOGGED_TAGS, CommandGate
from fleetlink.agent.pilot import Pilot
from fleetlink.operator.links import MAX_REJECT_REASONS, OTHER_REASONS, OperatorLink
from fleetlink.shared import keys, wire
from fleetlink.shared.clock import SimClock
from fleetlink.shared.messages import Event, LinkName, Severity, Teleop
from tests.harness.console_rig import MemoryTransport


def _teleop_with_field(counter: wire.HeaderCounter, name: str) -> bytes:
    body = msgpack.unpackb(wire.encode(counter.make(Teleop, v=0.0, omega=0.0, ttl_s=0.5)), raw=False)
    body[name] = 1  # an unknown field, named by the sender
    return msgpack.packb(body, use_bin_type=True)


def _receive(gate: CommandGate, link: LinkName, msg: wire.Message, now: float) -> object:
    """``msg`` through the gate on the key its sender publishes it on."""
    return gate.receive(link, wire.key_of(msg), wire.encode(msg), now)


def test_the_gate_logs_a_bounded_number_of_rejection_kinds_and_counts_them_all() -> None:
    gate = CommandGate("r1")
    counter = wire.HeaderCounter(SimClock(), robot="r1", sender="flooder")
    firsts = 0
    n = 4 * MAX_LOGGED_TAGS
    for i in range(n):
        verdict = gate.receive(
            LinkName.MQTT, keys.sender_key("r1", "teleop", "flooder"), _teleop_with_field(counter, f"f{i}"), 0.0
        )
        firsts += verdict.log  # type: ignore[union-attr]
    assert firsts == 1  # one log line for the link and topic, whatever names the sender invents
    assert gate.stats.rejected_total == n
    assert len(gate._logged) == 1 <= MAX_LOGGED_TAGS
    # Another link or topic is another first; its repeats are not.
    assert gate.receive(LinkName.ZENOH, keys.sender_key("r1", "order", "flooder"), b"\xc1", 0.0).log  # type: ignore[union-attr]
    assert not gate.receive(LinkName.ZENOH, keys.sender_key("r1", "order", "flooder"), b"\xc2", 0.0).log  # type: ignore[union-attr]


def test_the_agent_core_publishes_a_bounded_number_of_rejection_events() -> None:
    clock = SimClock()
    core = AgentCore("r1", clock, Pilot())
    counter = wire.HeaderCounter(clock, robot="r1", sender="flooder")
    events = 0
    for i in range(3 * MAX_LOGGED_TAGS):
        out = core.on_input(
            LinkName.MQTT, keys.sender_key("r1", "teleop", "flooder"), _teleop_with_field(counter, f"g{i}"), 0.0
        )
        events += sum(1 for m, _ in out.messages if isinstance(m, Event))
    assert events == 1


def test_the_operator_link_remembers_a_bounded_number_of_reasons(caplog: pytest.LogCaptureFixture) -> None:
    clock = SimClock()
    link = OperatorLink(clock, "operator-1", MemoryTransport("zenoh"), MemoryTransport("mqtt"))
    n = 3 * MAX_REJECT_REASONS
    with caplog.at_level(logging.WARNING, logger="fleetlink.operator.links"):
        for i in range(n):  # garbage whose reason quotes something different each time
            link._reject("zenoh", keys.key("r1", "pose"), f"bogus{i}: unknown field in Pose")
    assert len(link.rejected) <= MAX_REJECT_REASONS + 1
    assert sum(link.rejected.values()) == n
    assert link.rejected[OTHER_REASONS] == n - MAX_REJECT_REASONS
    assert len(caplog.records) <= MAX_REJECT_REASONS


def test_board_loss_and_return_are_events() -> None:
    clock = SimClock()
    core = AgentCore("r1", clock, Pilot())
    seen: list[Event] = []
    for connected in (True, True, False, False, True):
        clock.advance(0.05)
        out = core.tick(clock.now(), BoardView(connected=connected))
        seen += [m for m, _ in out.messages if isinstance(m, Event)]
    assert [e.kind for e in seen] == ["board_connected", "board_lost", "board_recovered"]
    assert seen[1].severity is Severity.ERROR and "lost" in seen[1].text


def test_rejection_counts_are_published_at_a_low_rate_while_they_move() -> None:
    from fleetlink.agent.core import DIAGNOSTICS_PERIOD_S
    from fleetlink.shared.messages import Diagnostics

    clock = SimClock()
    core = AgentCore("r1", clock, Pilot())
    links = {"zenoh": (0, 0), "mqtt": (0, 0)}

    def diagnostics(now: float) -> list[Diagnostics]:
        return [m for m, _ in core.diagnostics(now, links).messages if isinstance(m, Diagnostics)]

    first = diagnostics(0.0)  # everything zero: one message says so
    assert len(first) == 1 and first[0].rejected == () and first[0].handler_failures == 0
    for i in range(1000):  # a flood of garbage on one link
        core.on_input(LinkName.MQTT, keys.sender_key("r1", "teleop", "flooder"), b"\xc1" * (i % 7 + 1), 0.1)
    assert diagnostics(1.0) == []  # not before the period
    links["zenoh"] = (3, 12)  # the Zenoh endpoint refused three oversized messages, dropped twelve
    msgs = diagnostics(DIAGNOSTICS_PERIOD_S)
    assert len(msgs) == 1
    d = wire.decode_key(keys.key("r1", "diagnostics"), wire.encode(msgs[0]))  # it travels
    assert isinstance(d, Diagnostics)
    assert [(c.key, c.count) for c in d.rejected] == [("mqtt/teleop", 1000)]
    assert {c.key: c.count for c in d.oversized} == {"zenoh": 3, "mqtt": 0}
    assert {c.key: c.count for c in d.dropped} == {"zenoh": 12, "mqtt": 0}
    assert "msgpack" in d.last_reason
    assert diagnostics(3 * DIAGNOSTICS_PERIOD_S) == []  # nothing moved: nothing sent


def test_a_sender_over_its_rate_is_refused_before_any_work_and_stops_never_are() -> None:
    from fleetlink.agent.links.gate import RateLimit
    from fleetlink.shared.messages import Action, ActionType, InstantActions

    limit = RateLimit(rate=50.0, burst=100.0, max_senders=4)
    assert all(limit.allow("bob", 0.0) for _ in range(100))  # the burst
    assert not limit.allow("bob", 0.0)
    assert limit.allow("bob", 0.05)  # 2.5 tokens back after 50 ms
    for i in range(10):  # invented senders: at most four remembered
        limit.allow(f"s{i}", 1.0)
    assert len(limit._buckets) == 4

    gate = CommandGate("r1")
    clock = SimClock()
    bob = wire.HeaderCounter(clock, robot="r1", sender="op-bob")
    alice = wire.HeaderCounter(clock, robot="r1", sender="operator-1")
    verdicts = [_receive(gate, LinkName.ZENOH, bob.make(Teleop, v=0.0, omega=0.0, ttl_s=0.5), 0.0) for _ in range(1000)]
    assert sum(1 for v in verdicts if type(v).__name__ == "Accepted") == 100
    assert "over its rate (50 commands/s)" in gate.stats.last_reason
    assert len(gate._seen) == 100  # the refused ones are not remembered
    # The lease holder's stream is untouched, and bob's stop always passes.
    assert (
        type(_receive(gate, LinkName.ZENOH, alice.make(Teleop, v=0.1, omega=0.0, ttl_s=0.5), 0.0)).__name__
        == "Accepted"
    )
    stop = bob.make(InstantActions, actions=(Action(actionId="s", actionType=ActionType.STOP, actionParameters=()),))
    assert type(gate.receive(LinkName.MQTT, wire.key_of(stop), wire.encode(stop), 0.0)).__name__ == "Accepted"


def test_a_flood_under_invented_names_shares_one_bucket_and_the_lease_holder_is_not_in_it() -> None:
    gate = CommandGate("r1")
    gate.priority_sender = "operator-1"
    clock = SimClock()
    admitted = 0
    for i in range(2000):  # each name new, each with a fresh bucket of its own
        c = wire.HeaderCounter(clock, robot="r1", sender=f"fake-{i}")
        v = _receive(gate, LinkName.MQTT, c.make(Teleop, v=0.0, omega=0.0, ttl_s=0.5), 0.0)
        admitted += type(v).__name__ == "Accepted"
    assert admitted == gate.limit.shared_burst  # the shared bucket, not 2000 x 100
    holder = wire.HeaderCounter(clock, robot="r1", sender="operator-1")
    for k in range(50):  # the holder at 10 Hz meanwhile: every one admitted
        v = _receive(gate, LinkName.ZENOH, holder.make(Teleop, v=0.1, omega=0.0, ttl_s=0.5), 0.1 * k)
        assert type(v).__name__ == "Accepted", v
