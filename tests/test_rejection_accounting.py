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


def test_the_gate_logs_a_bounded_number_of_rejection_kinds_and_counts_them_all() -> None:
    gate = CommandGate("r1")
    counter = wire.HeaderCounter(SimClock(), robot="r1", sender="flooder")
    firsts = 0
    n = 4 * MAX_LOGGED_TAGS
    for i in range(n):
        verdict = gate.receive(LinkName.MQTT, keys.key("r1", "teleop"), _teleop_with_field(counter, f"f{i}"), 0.0)
        firsts += verdict.log  # type: ignore[union-attr]
    assert firsts <= MAX_LOGGED_TAGS
    assert gate.stats.rejected_total == n
    assert len(gate._logged) <= MAX_LOGGED_TAGS
    # Once full, a kind never seen before is silent too: no sender can buy a log line per message.
    verdict = gate.receive(LinkName.ZENOH, keys.key("r1", "order"), b"\xc1", 0.0)
    assert not verdict.log  # type: ignore[union-attr]


def test_the_agent_core_publishes_a_bounded_number_of_rejection_events() -> None:
    clock = SimClock()
    core = AgentCore("r1", clock, Pilot())
    counter = wire.HeaderCounter(clock, robot="r1", sender="flooder")
    events = 0
    for i in range(3 * MAX_LOGGED_TAGS):
        out = core.on_input(LinkName.MQTT, keys.key("r1", "teleop"), _teleop_with_field(counter, f"g{i}"), 0.0)
        events += sum(1 for m, _ in out.messages if isinstance(m, Event))
    assert events <= MAX_LOGGED_TAGS


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
