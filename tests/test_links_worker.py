"""The one worker lifecycle, Clock.wait, and the in-process link (wire bytes, pumped, cuttable)."""

from __future__ import annotations

import os
import threading
import time

import pytest

from fleetlink.links.base import Link, key_matches, to_mqtt_filter
from fleetlink.links.inprocess import InProcessBus
from fleetlink.shared.clock import SimClock, SystemClock
from fleetlink.shared.messages import LinkName
from fleetlink.shared.worker import BACKGROUND_NICE, Worker


def test_system_clock_wait_returns_early_when_set() -> None:
    ev = threading.Event()
    threading.Timer(0.02, ev.set).start()
    assert SystemClock().wait(ev, 5.0) is True
    assert SystemClock().wait(threading.Event(), 0.01) is False


def test_sim_clock_wait_ends_when_time_is_advanced_or_event_set() -> None:
    clock = SimClock()
    ev = threading.Event()
    result: list[bool] = []
    t = threading.Thread(target=lambda: result.append(clock.wait(ev, 1.0)))
    t.start()
    time.sleep(0.05)
    assert t.is_alive()  # real time alone does not end a simulated wait
    clock.advance(1.0)
    t.join(2.0)
    assert result == [False]
    t = threading.Thread(target=lambda: result.append(clock.wait(ev, 10.0)))
    t.start()
    ev.set()
    t.join(2.0)
    assert result == [False, True]


class Counter(Worker):
    def __init__(self, clock: SimClock | SystemClock) -> None:
        super().__init__("counter", clock=clock)
        self.ticks = 0

    def run(self) -> None:
        while not self.stopping:
            self.ticks += 1
            self.wait(0.01)


@pytest.mark.parametrize("clock", [SystemClock(), SimClock()], ids=["system", "sim"])
def test_worker_stops_promptly_under_either_clock(clock: SimClock | SystemClock) -> None:
    w = Counter(clock).start()
    time.sleep(0.05)
    t0 = time.monotonic()
    w.stop()
    assert not w.running
    assert time.monotonic() - t0 < 1.0  # woken, not left to sleep out a simulated wait
    assert w.ticks >= 1
    w.stop()  # idempotent


def test_worker_logs_and_keeps_an_error(caplog: pytest.LogCaptureFixture) -> None:
    def boom(worker: Worker) -> None:
        raise RuntimeError("board unplugged")

    w = Worker("boom", target=boom).start()
    for _ in range(100):
        if not w.running:
            break
        time.sleep(0.01)
    assert isinstance(w.error, RuntimeError)
    assert "worker boom failed: board unplugged" in caplog.text
    w.stop()


@pytest.mark.skipif(not hasattr(os, "setpriority"), reason="no per-thread priorities here")
def test_a_background_worker_runs_at_a_lower_priority_than_its_process() -> None:
    """Only its own thread is lowered (Linux nice is per thread): the owner's stays as it was."""
    seen: list[int] = []

    def look(worker: Worker) -> None:
        seen.append(os.getpriority(os.PRIO_PROCESS, threading.get_native_id()))

    own = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    for background in (False, True):
        w = Worker("look", target=look, background=background).start()
        for _ in range(200):
            if not w.running:
                break
            time.sleep(0.01)
        w.stop()
    assert seen == [own, min(19, own + BACKGROUND_NICE)]
    assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == own


def test_the_agents_closure_search_runs_in_the_background() -> None:
    """The closure search is a background worker (the lidar worker too: tests/test_field_agents.py):
    on a host short of CPU, control and links go first."""
    from fleetlink.agent.mapping.worker import SearchWorker

    assert SearchWorker("closure-r1").background
    assert not Worker("agent-r1").background


def test_key_matching_and_mqtt_filters() -> None:
    assert key_matches("fleetlink/v1/*/order", "fleetlink/v1/r1/order")
    assert not key_matches("fleetlink/v1/*/order", "fleetlink/v1/r1/map/order")
    assert key_matches("fleetlink/v1/r1/**", "fleetlink/v1/r1/map/updates")
    assert key_matches("fleetlink/v1/r1/**", "fleetlink/v1/r1")
    assert not key_matches("fleetlink/v1/r1", "fleetlink/v1/r2")
    assert to_mqtt_filter("fleetlink/v1/*/order") == "fleetlink/v1/+/order"
    assert to_mqtt_filter("fleetlink/v1/r1/**") == "fleetlink/v1/r1/#"
    with pytest.raises(ValueError, match="at the end"):
        to_mqtt_filter("fleetlink/**/order")


def test_in_process_bus_carries_bytes_in_order_only_when_pumped() -> None:
    bus = InProcessBus(LinkName.ZENOH)
    agent, console = bus.endpoint("agent-r1"), bus.endpoint("console")
    assert isinstance(agent, Link)
    for e in (agent, console):
        e.start()
    got: list[tuple[str, bytes]] = []
    console.subscribe("fleetlink/v1/*/ack", lambda k, p: got.append((k, p)))
    # The agent acks every command at once: a command and its ack cross in one deliver().
    agent.subscribe("fleetlink/v1/r1/teleop", lambda k, p: agent.publish("fleetlink/v1/r1/ack", b"ack:" + p))
    assert console.publish("fleetlink/v1/r1/teleop", b"\x01")
    assert console.publish("fleetlink/v1/r1/teleop", b"\x02")
    assert got == []  # nothing moves until the owner of time pumps the bus
    assert bus.deliver() == 4
    assert got == [("fleetlink/v1/r1/ack", b"ack:\x01"), ("fleetlink/v1/r1/ack", b"ack:\x02")]
    assert agent.stats.received == 2 and console.stats.sent == 2


def test_in_process_cut_and_restore() -> None:
    bus = InProcessBus(LinkName.MQTT)
    agent, console = bus.endpoint("agent-r1"), bus.endpoint("console")
    agent.start()
    console.start()
    got: list[bytes] = []
    agent.subscribe("fleetlink/v1/r1/#".replace("#", "**"), lambda k, p: got.append(p))
    bus.cut("agent-r1")
    assert not agent.up
    console.publish("fleetlink/v1/r1/order", b"lost")
    assert not agent.publish("fleetlink/v1/r1/state", b"x")
    bus.deliver()
    assert got == [] and agent.stats.dropped == 2
    bus.restore("agent-r1")
    console.publish("fleetlink/v1/r1/order", b"kept")
    bus.deliver()
    assert got == [b"kept"]
    with pytest.raises(KeyError):
        bus.cut("nobody")
    with pytest.raises(ValueError):
        bus.endpoint("console")


def test_in_process_queries() -> None:
    bus = InProcessBus(LinkName.ZENOH)
    agent, console = bus.endpoint("agent-r1"), bus.endpoint("console")
    agent.start()
    console.start()
    agent.serve("fleetlink/v1/r1/map", lambda asked: [("fleetlink/v1/r1/map", b"grid")])
    assert console.query("fleetlink/v1/r1/map") == [("fleetlink/v1/r1/map", b"grid")]
    assert console.query("fleetlink/v1/*/map") == [("fleetlink/v1/r1/map", b"grid")]
    assert console.query("fleetlink/v1/r2/map") == []
